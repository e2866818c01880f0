"""Where and with what a benchmark or experiment ran: machine, package versions, git state."""

from __future__ import annotations

import datetime
import importlib.metadata
import os
import platform
import subprocess
import sys
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("numpy", "jax", "jaxlib", "opencv-python-headless", "edgevo_jax")


def package_version(dist: str) -> str | None:
    """Installed version of a distribution, or None."""
    try:
        return importlib.metadata.version(dist)
    except importlib.metadata.PackageNotFoundError:
        return None


def git(*args: str) -> str | None:
    """Output of a read-only git command in the repository, or None outside one."""
    try:
        return subprocess.run(["git", *args], cwd=REPO_ROOT, capture_output=True, text=True,
                              timeout=10, check=True,  # no index.lock: others may commit
                              env={**os.environ, "GIT_OPTIONAL_LOCKS": "0"}).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return None


def load_average() -> list[float] | None:
    """1, 5 and 15 minute load averages (timings on a loaded machine are slower)."""
    try:
        return list(os.getloadavg())
    except (AttributeError, OSError):
        return None


def machine_info(extra_packages: tuple[str, ...] = ()) -> dict:
    """Date, platform, CPUs, Python, package versions and the git commit (dirty or not)."""
    status = git("status", "--porcelain", "--untracked-files=no")
    info = {
        "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "platform": platform.platform(),
        "processor": platform.processor() or platform.machine(),
        "cpu_count": os.cpu_count(),
        "cpus_usable": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None,
        "python": sys.version.split()[0],
        "load_average": load_average(),
    }
    info.update({name: package_version(name) for name in PACKAGES + tuple(extra_packages)})
    info["git_commit"] = git("rev-parse", "HEAD")
    info["git_dirty"] = bool(status) if status is not None else None
    return info
