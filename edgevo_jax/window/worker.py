"""The sliding window beside tracking (``Window``): each new keyframe goes to
``window.sliding.SlidingWindow`` on a worker thread (``workers.Worker``), and the tracker
takes the refined keyframe pose at a fixed frame lag.

Determinism: when a result is taken never depends on when the worker finishes. The refined
pose of the keyframe made at frame i is taken when frame i + ``Config.mapping_lag`` is
concluded, or earlier when a new keyframe is made (its pose is computed from refined poses
only, so the window sees the same poses as when it runs inline); the tracker waits for the
worker if it is not done by then. The worker takes keyframes one at a time, in order. With
``mapping_lag = 0`` the window runs inline, in the tracking thread, and the keyframe's own
pose is already the refined one.
"""

from __future__ import annotations

import time
from concurrent.futures import Future
from dataclasses import dataclass

import numpy as np

from ..camera import Intrinsics
from ..config import Config
from ..frontend.selection import KeyframeEdges
from ..image.preprocess import Frame
from ..workers import Worker
from .sliding import SlidingWindow


@dataclass(frozen=True)
class Refined:
    """A keyframe's refinement taken by the tracker: the keyframe's id (``key``), its
    refined pose (T_world_kf, (4, 4) float64) and the window's intrinsics after the step."""

    key: int
    pose: np.ndarray
    intrinsics: Intrinsics


class Window:
    """The sliding window of one tracker, inline (``lag`` 0) or on its own worker thread.

    ``add(key, pose, edges, frame, frame_index)`` hands over a keyframe (T_world_kf; its
    selected edges, numpy; its Frame) made at ``frame_index``; inline it returns the refined
    pose at once, beside tracking None. ``due(frame_index)`` returns, in order, the
    refinements whose frame lag has run out at that frame (waiting for the worker where
    needed); ``due(None)`` all of them. ``close()`` stops the worker (pending results are
    dropped); a closed Window takes no more keyframes."""

    def __init__(self, config: Config, intrinsics: Intrinsics, shape: tuple[int, int], *,
                 rolling_shutter: bool = False) -> None:
        self.lag = config.mapping_lag
        self.sliding = SlidingWindow(config, np.asarray(intrinsics), shape,
                                     rolling_shutter=rolling_shutter)
        self._worker = Worker("window", inline=self.lag <= 0)
        #: tagged (key, corrections of the map made while it was pending)
        self._steps = self._worker.queue(self.lag)
        self.worker_ms: list[float] = []  # the window's time per keyframe, in order
        self.warm_since: float | None = None  # when ``warm_up`` started (perf_counter)
        self._warm: Future | None = None

    def warm_up(self) -> None:
        """Start compiling or loading the window's programs (``SlidingWindow.warm_up``):
        beside tracking on the worker, ahead of every keyframe; inline at once. ``warmed``
        waits for them."""
        self.warm_since = time.perf_counter()
        self._warm = self._worker.run(self.sliding.warm_up)

    def warmed(self) -> None:
        """Wait until the programs ``warm_up`` started are ready."""
        if self._warm is not None:
            self._warm.result()

    @property
    def pending(self) -> list[int]:
        """The keyframes handed over whose refinements are not taken yet, oldest first."""
        return [key for key, _ in self._steps.tags]

    def add(self, key: int, pose: np.ndarray, edges: KeyframeEdges, frame: Frame,
            frame_index: int, row_twist: np.ndarray | None = None) -> Refined | None:
        """Hand over a keyframe (see the class doc; ``row_twist``: its rolling-shutter
        motion per row, ``SlidingWindow.add_keyframe``)."""
        pose = np.asarray(pose, np.float64)
        if self._worker.inline:
            return self._refined(key, self._step(key, pose, edges, frame, row_twist))
        self._steps.submit(frame_index, (key, []), self._step, key, pose, edges, frame,
                           row_twist)
        return None

    def due(self, frame_index: int | None) -> list[Refined]:
        """The refinements due at ``frame_index`` (None: all handed over), oldest first."""
        out = []
        for (key, moves), step in self._steps.due(frame_index):
            refined = self._refined(key, step)
            for corrections in moves:  # a step solved before a move: in the old frame
                if key in corrections:
                    refined = Refined(key, corrections[key] @ refined.pose, refined.intrinsics)
            out.append(refined)
        return out

    def close(self) -> None:
        """Stop the worker after the step it is in; results not taken are dropped."""
        self._steps.clear()
        self._worker.close()

    def move(self, corrections: dict) -> None:
        """Move the window's keyframes (by id) with a correction of the map
        (``SlidingWindow.move``; key -> C = T_world_new_world_old): after the steps handed
        over so far, before any later one (on the worker, in order; inline at once). The
        refinements of the steps handed over so far, not taken yet, are in the old frame:
        each is moved by its key's C when taken. Nothing waits for the worker."""
        corrections = dict(corrections)
        for _, moves in self._steps.tags:
            moves.append(corrections)
        self._worker.run(self.sliding.move, corrections)

    def _step(self, key: int, pose: np.ndarray, edges: KeyframeEdges, frame: Frame,
              row_twist: np.ndarray | None) -> tuple[np.ndarray, Intrinsics, float]:
        t0 = time.perf_counter()
        refined, _ = self.sliding.add_keyframe(pose, edges, frame, row_twist, key=key)
        return refined, self.sliding.camera, (time.perf_counter() - t0) * 1e3

    def _refined(self, key: int, step) -> Refined:
        refined, intrinsics, ms = step
        self.worker_ms.append(ms)
        return Refined(key, np.asarray(refined, np.float64), intrinsics)
