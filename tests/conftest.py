"""Shared test helpers: the real TUM RGB-D clips in ../shared/data/tum (skipped when absent)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import pytest

SHARED_TUM = Path(__file__).resolve().parents[2] / "shared" / "data" / "tum"


def shared_tum_dir() -> Path:
    """The shared TUM clips folder, or skip the calling test with the reason."""
    if not SHARED_TUM.is_dir():
        pytest.skip(f"../shared/data/tum not found: {SHARED_TUM}")
    return SHARED_TUM


@pytest.fixture
def shared_clip() -> Callable[[str], Path]:
    """``shared_clip(name)`` -> path of a clip folder; skips the test when it is absent."""

    def get(name: str) -> Path:
        clip = shared_tum_dir() / name
        if not clip.is_dir():
            pytest.skip(f"../shared/data/tum not found: {clip}")
        return clip

    return get
