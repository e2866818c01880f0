"""The Python examples of the README and of the docs pages it sends a newcomer to run (docs
that run), each from an empty folder. docs/camera_file.md's example reads the user's own
camera file and sequence: its format is tested in tests/test_camera_file.py."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGES = ["README.md", "docs/usage.md", "docs/batch.md", "docs/map-and-loops.md"]


def _blocks(page: str) -> list[str]:
    return re.findall(r"```python\n(.*?)```", (ROOT / page).read_text(), re.S)


EXAMPLES = [(page, i, code) for page in PAGES for i, code in enumerate(_blocks(page))]


@pytest.mark.parametrize("page,index,code", EXAMPLES,
                         ids=[f"{page}-block{i}" for page, i, _ in EXAMPLES])
def test_example_runs(page: str, index: int, code: str, monkeypatch, tmp_path) -> None:
    monkeypatch.chdir(tmp_path)  # the examples must run from any folder
    exec(compile(code, f"{page} block {index}", "exec"), {"__name__": "readme"})


def test_readme_has_examples() -> None:
    assert len(_blocks("README.md")) >= 2 and all(_blocks(page) for page in PAGES)
