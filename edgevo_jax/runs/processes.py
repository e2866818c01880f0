"""The local processes of a sweep (``edgevo batch SWEEP.toml --processes N``): a free port
for the coordinator, children started with the parent's command line that die with it, and
the failure notes through which the processes of a sweep learn that one of them failed."""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Callable, Sequence
from pathlib import Path


def free_port() -> int:
    """A TCP port free on this host now (for a local coordinator)."""
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("localhost", 0))
        return s.getsockname()[1]


def _die_with_parent() -> None:  # pragma: no cover - runs in the child before exec
    """Linux: the child is killed when the process that started it dies (even by kill -9),
    so that no process of a killed sweep runs on beside the next one."""
    import ctypes
    import signal

    try:
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


def start_processes(command: Sequence[str], processes: int, coordinator: str) -> list:
    """Start processes 1 .. processes - 1 of a local sweep: ``command`` (the child's argv,
    e.g. ``[python, -m, edgevo_jax.cli, batch, SWEEP, --out, DIR]``) with
    ``--coordinator``, ``--num-processes`` and ``--process-id`` added; returns their
    ``subprocess.Popen``s (the caller is process 0)."""

    return [subprocess.Popen([*command, "--coordinator", coordinator, "--num-processes",
                              str(processes), "--process-id", str(i)],
                             preexec_fn=_die_with_parent if sys.platform == "linux" else None)
            for i in range(1, processes)]


def children_check(children: Sequence) -> Callable[[], None]:
    """``wait_for_runs``'s check for local children: RuntimeError once one has failed."""
    def check() -> None:
        for i, child in enumerate(children, start=1):
            code = child.poll()
            if code not in (None, 0):
                raise RuntimeError(f"process {i} of the sweep exited with code {code}; its "
                                   "finished runs are kept: run the same command again")
    return check


def failure_check(out: str | os.PathLike[str]) -> Callable[[], None]:
    """``wait_for_runs``'s check for a cluster: RuntimeError once a process has left a
    ``log/process-<i>.failed`` note (``note_failure``)."""
    def check() -> None:
        for note in sorted((Path(out) / "log").glob("process-*.failed")):
            raise RuntimeError(f"{note.stem} of the sweep failed: {note.read_text().strip()}; "
                               "finished runs are kept: run the same command again")
    return check


def note_failure(out: str | os.PathLike[str], process: int, error: BaseException | None
                 ) -> None:
    """Leave (``error``) or clear (None) process ``process``'s failure note in ``out``."""
    path = Path(out) / "log" / f"process-{process}.failed"
    if error is None:
        path.unlink(missing_ok=True)
    else:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(f"{type(error).__name__}: {error}\n")
