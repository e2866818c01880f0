"""The one lagged worker: work handed over at frame n and taken at frame n + lag, or all of
it now, so that when a result lands never depends on the machine (runs stay deterministic).

``Worker`` is one thread at the lowest CPU priority (tracking comes first; the work takes the
cycles left over), or none (``inline``: each task runs when it is handed over). A
``Lagged`` queue on it keeps tasks in the order handed over with the frame each is due at;
``due(n)`` waits for and returns, oldest first, those due at frame ``n`` (``due(None)``: all
of them). The window (``window.worker``), the keyframe map's describer and the loops
(``tracking.backend``, ``map.loops``) each own one worker.
"""

from __future__ import annotations

import os
import threading
from collections import deque
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any, Generic, TypeVar

T = TypeVar("T")


def lower_priority() -> None:
    """Run the calling thread at the lowest CPU priority where the OS allows it (Linux sets a
    nice value per thread): tracking comes first, the worker takes the cycles left over."""
    try:
        os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), 19)
    except (AttributeError, OSError):  # no per-thread priorities here: run as is
        pass


class Worker:
    """One worker thread named ``name`` at the lowest priority; ``inline``: no thread, each
    task runs in the caller's thread when handed over. ``close()`` stops it after the task in
    progress (tasks not started are dropped)."""

    def __init__(self, name: str, *, inline: bool = False) -> None:
        self._pool = None if inline else ThreadPoolExecutor(
            1, thread_name_prefix=f"edgevo-{name}", initializer=lower_priority)

    @property
    def inline(self) -> bool:
        """Whether tasks run in the caller's thread."""
        return self._pool is None

    def run(self, fn: Callable[..., T], *args: Any) -> Future:
        """Hand ``fn(*args)`` over, after every task handed over before it (inline: run now);
        its future."""
        if self._pool is not None:
            return self._pool.submit(fn, *args)
        future: Future = Future()
        try:
            future.set_result(fn(*args))
        except BaseException as exc:  # raised when the result is read, as a thread's would be
            future.set_exception(exc)
        return future

    def queue(self, lag: int = 0) -> Lagged:
        """A queue of results due ``lag`` frames after they are handed over, on this worker."""
        return Lagged(self, lag)

    def close(self) -> None:
        """Stop after the task in progress; tasks not started are dropped."""
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)


class Lagged(Generic[T]):
    """Results handed over at frame n and due at n + ``lag``, in order (module doc). Each
    entry carries a ``tag`` (what its owner needs to read the result: a key, a record of
    what happened while it was pending)."""

    def __init__(self, worker: Worker, lag: int) -> None:
        self.worker, self.lag = worker, lag
        self._entries: deque[tuple[int, Any, Future]] = deque()

    def __len__(self) -> int:
        return len(self._entries)

    @property
    def tags(self) -> list:
        """The tags of the entries not taken yet, oldest first."""
        return [tag for _, tag, _ in self._entries]

    def submit(self, frame: int, tag: Any, fn: Callable[..., T], *args: Any) -> None:
        """Hand ``fn(*args)`` over at frame ``frame``: due at ``frame + lag``."""
        self._entries.append((frame + self.lag, tag, self.worker.run(fn, *args)))

    def due(self, frame: int | None) -> list[tuple[Any, T]]:
        """(tag, result) of the entries due at ``frame`` (None: all), oldest first, waited
        for."""
        out = []
        while self._entries and (frame is None or self._entries[0][0] <= frame):
            _, tag, future = self._entries.popleft()
            out.append((tag, future.result()))
        return out

    def clear(self) -> None:
        """Drop every entry not taken (their tasks still run unless the worker closes)."""
        self._entries.clear()
