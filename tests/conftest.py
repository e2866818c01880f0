"""Shared test set-up (the CLI's batch-exact arithmetic) and helpers: the real TUM RGB-D
clips in ../shared/data/tum (skipped when absent), and the scripts in scripts/ loaded as
modules."""

from __future__ import annotations

import importlib.util
import os
from collections.abc import Callable
from pathlib import Path
from types import ModuleType

import pytest

from edgevo_jax import enable_batch_exact
from edgevo_jax.programs import CACHE_ENV, release_compiled

# batch-size-exact arithmetic before any JAX computation (the CLI does the same): a run then
# equals its batched self bit for bit (tests/test_batch.py, notebooks/05)
enable_batch_exact()

SCRIPTS = Path(__file__).resolve().parents[1] / "scripts"


def pytest_xdist_auto_num_workers(config) -> int:
    """``-n auto`` (pyproject's addopts): a worker per core, at most 4: almost all of the
    suite's time is compilation, one core each, and each worker holds its own programs."""
    return max(1, min(4, os.cpu_count() or 1))


@pytest.fixture(autouse=True)
def _room_for_programs():
    """Each test starts with room for its compiled programs (``programs.release_compiled``:
    the suite compiles hundreds of configurations in one process, ~2,500 memory maps each)."""
    release_compiled()


@pytest.fixture(autouse=True, scope="session")
def _session_program_cache(tmp_path_factory):
    """The on-disk caches (compiled and exported programs, ``EDGEVO_CACHE_DIR``) in one
    temporary folder for the session: every tracker and the CLI switch them on
    (``programs.enable_cache``), which would otherwise write the user's ~/.cache/edgevo_jax.
    The session's tests, its CLI subprocesses and its notebooks' kernels then load the
    programs one of them compiled instead of compiling them again (``release_compiled``
    before each test drops only what is in memory). Each xdist worker has a folder of its
    own (its own temporary root): no two processes write one cache. A test of the cache
    itself gives it a folder of its own (``kept_programs``; the defaults in new processes,
    tests/test_programs.py)."""
    before = os.environ.get(CACHE_ENV)
    os.environ[CACHE_ENV] = str(tmp_path_factory.mktemp("programs"))
    yield
    if before is None:
        os.environ.pop(CACHE_ENV, None)
    else:
        os.environ[CACHE_ENV] = before


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


@pytest.fixture
def kept_programs(tmp_path: Path, monkeypatch):
    """Programs exported to and loaded from ``tmp_path`` (``edgevo_jax.programs``) for the
    test, then the session's folder again. Through the cache's own variable, as a user sets
    it: every tracker switches the cache on (``programs.enable_cache``) and would otherwise
    put the session's folder back."""
    from edgevo_jax import programs

    session = os.environ.get(CACHE_ENV, "")
    monkeypatch.setenv(CACHE_ENV, str(tmp_path))
    programs.enable_cache()
    yield tmp_path
    monkeypatch.setenv(CACHE_ENV, session)
    programs.enable_cache()


def load_script(name: str) -> ModuleType:
    """scripts/<name>.py as a module (the scripts are not a package)."""
    spec = importlib.util.spec_from_file_location(name, SCRIPTS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module
