"""The local map beside tracking: each new keyframe goes to ``backend.local_map.LocalMap`` on a
worker thread, and the tracker takes the refined keyframe pose at a fixed frame lag.

Determinism: when a result is taken never depends on when the worker finishes. The refined
pose of the keyframe made at frame i is applied when frame i + ``Config.mapping_lag`` is
concluded, or earlier when a new keyframe is made (its pose is computed from refined poses
only, so the window sees the same poses as with the map inline); the tracker waits for the
worker if it is not done by then. The worker takes keyframes one at a time, in order. With
``mapping_lag = 0`` the window runs inline, in the tracking thread, and the keyframe's own
pose is already the refined one.
"""

from __future__ import annotations

import os
import threading
import time
from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from ..camera import Intrinsics
from ..config import Config
from ..frontend.selection import KeyframeEdges
from ..image.preprocess import Frame
from .local_map import LocalMap


def lower_priority() -> None:
    """Run the calling thread at the lowest CPU priority where the OS allows it (Linux sets a
    nice value per thread): tracking comes first, the window takes the cycles left over."""
    try:
        os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), 19)
    except (AttributeError, OSError):  # no per-thread priorities here: run as is
        pass


@dataclass(frozen=True)
class Mapped:
    """A keyframe's refinement taken by the tracker: the tracker's handle of the keyframe
    (``key``), its refined pose (T_world_kf, (4, 4) float64) and the window's intrinsics
    after the step."""

    key: object
    pose: np.ndarray
    intrinsics: Intrinsics


class Mapper:
    """The local map of one tracker, inline (``lag`` 0) or on its own worker thread.

    ``add(key, pose, edges, frame, frame_index)`` hands over a keyframe (T_world_kf; its
    selected edges, numpy; its Frame) made at ``frame_index``; inline it returns the refined
    pose at once, beside tracking None. ``due(frame_index)`` returns, in order, the
    refinements whose frame lag has run out at that frame (waiting for the worker where
    needed); ``due(None)`` all of them. ``close()`` stops the worker (pending results are
    dropped); a closed Mapper takes no more keyframes."""

    def __init__(self, config: Config, intrinsics: Intrinsics, shape: tuple[int, int], *,
                 rolling_shutter: bool = False) -> None:
        self.lag = config.mapping_lag
        self.local_map = LocalMap(config, np.asarray(intrinsics), shape,
                                  rolling_shutter=rolling_shutter)
        self._pool = (ThreadPoolExecutor(1, thread_name_prefix="edgevo-map",
                                         initializer=lower_priority)
                      if self.lag > 0 else None)
        #: (due frame, key, step, corrections of the map made while it was pending)
        self._pending: deque[tuple[int, object, Future, list[dict]]] = deque()
        self.worker_ms: list[float] = []  # the window's time per keyframe, in order
        self.warm_since: float | None = None  # when ``warm_up`` started (perf_counter)
        self._warm: Future | None = None

    def warm_up(self) -> None:
        """Start compiling or loading the window's programs (``LocalMap.warm_up``): beside
        tracking on the worker, ahead of every keyframe; inline at once. ``warmed`` waits for
        them."""
        self.warm_since = time.perf_counter()
        if self._pool is None:
            self.local_map.warm_up()
        else:
            self._warm = self._pool.submit(self.local_map.warm_up)

    def warmed(self) -> None:
        """Wait until the programs ``warm_up`` started are ready."""
        if self._warm is not None:
            self._warm.result()

    def add(self, key: object, pose: np.ndarray, edges: KeyframeEdges, frame: Frame,
            frame_index: int, row_twist: np.ndarray | None = None) -> Mapped | None:
        """Hand over a keyframe (see the class doc; ``row_twist``: its rolling-shutter
        motion per row, ``LocalMap.add_keyframe``)."""
        pose = np.asarray(pose, np.float64)
        if self._pool is None:
            return self._mapped(key, self._step(key, pose, edges, frame, row_twist))
        self._pending.append((frame_index + self.lag, key,
                              self._pool.submit(self._step, key, pose, edges, frame,
                                                row_twist), []))
        return None

    def due(self, frame_index: int | None) -> list[Mapped]:
        """The refinements due at ``frame_index`` (None: all handed over), oldest first."""
        out = []
        while self._pending and (frame_index is None or self._pending[0][0] <= frame_index):
            _, key, future, moves = self._pending.popleft()
            mapped = self._mapped(key, future.result())
            for corrections in moves:  # a step solved before a move: in the old frame
                if key in corrections:
                    mapped = Mapped(key, corrections[key] @ mapped.pose, mapped.intrinsics)
            out.append(mapped)
        return out

    def close(self) -> None:
        """Stop the worker after the step it is in; results not taken are dropped."""
        if self._pool is not None:
            self._pending.clear()
            self._pool.shutdown(wait=True, cancel_futures=True)

    def move(self, corrections: dict) -> None:
        """Move the window's keyframes (by the keys they were handed with) with a correction
        of the map (``LocalMap.move``; key -> C = T_world_new_world_old): after the steps
        handed over so far, before any later one (on the worker, in order; inline at once).
        The refinements of the steps handed over so far, not taken yet, are in the old frame:
        each is moved by its key's C when taken. Nothing waits for the worker."""
        if self._pool is None:
            self.local_map.move(corrections)
            return
        corrections = dict(corrections)
        for entry in self._pending:
            entry[3].append(corrections)
        self._pool.submit(self.local_map.move, corrections)

    def _step(self, key: object, pose: np.ndarray, edges: KeyframeEdges, frame: Frame,
              row_twist: np.ndarray | None) -> tuple[np.ndarray, Intrinsics, float]:
        t0 = time.perf_counter()
        refined, _ = self.local_map.add_keyframe(pose, edges, frame, row_twist, key=key)
        return refined, self.local_map.camera, (time.perf_counter() - t0) * 1e3

    def _mapped(self, key: object, step) -> Mapped:
        refined, intrinsics, ms = step
        self.worker_ms.append(ms)
        return Mapped(key, np.asarray(refined, np.float64), intrinsics)
