"""Frames whose poses the keyframe map may still move (``Ledger``): those since the last
frame tracked OK from a keyframe tied to the map. When the map places a frame (a ``Tie``),
a chain of keyframes made at a guess moves into the map's frame with the correction the
placed frame measured, and the LOST frames in between are filled in: each takes the pose
interpolated (along the screw motion, by time) between the tracked frames on either side,
the placed frame being the last of them. A held or extrapolated pose of a loss is a
guess; once both ends are known, the path between them is the better one."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from ..geometry import inverse_np, scale_motion_np
from ..tracking.records import Tie
from ..tracking.results import LOST, Correction, FrameResult

#: frames the ledger keeps open at most (a loss longer than this is not filled in past it)
MAX_OPEN = 3000


class _Entry(NamedTuple):
    index: int
    timestamp: float
    lost: bool
    pose: np.ndarray


class Ledger:
    """The frames not settled yet (module doc), in order."""

    def __init__(self) -> None:
        self._settled: _Entry | None = None  # the last frame settled
        self._open: list[_Entry] = []

    def record(self, index: int, result: FrameResult, *, settled: bool,
               tie: Tie | None = None) -> Correction | None:
        """Frame ``index`` was concluded with ``result``; ``settled``: tracked OK from a
        keyframe tied to the map, or placed by it (``tie``). A settled frame settles the
        frames before it: the earlier poses that moved (None: none did)."""
        entry = _Entry(index, result.timestamp, result.state == LOST, result.pose)
        if not settled:
            self._open = [*self._open, entry][-MAX_OPEN:]
            return None
        frames = self._open
        moved = frames
        if tie is not None and tie.correction is not None and tie.since is not None:
            moved = [e._replace(pose=tie.correction @ e.pose) if e.index >= tie.since else e
                     for e in frames]
        head = [self._settled] if self._settled is not None else []
        poses = _filled([*head, *moved, entry])[len(head):len(head) + len(moved)]
        self._settled, self._open = entry, []
        if all(p is e.pose for p, e in zip(poses, frames, strict=True)):
            return None
        return Correction(frames[0].index, index - 1, np.stack(poses))

    def move(self, first: int, poses: np.ndarray) -> None:
        """Frames ``first`` on took the poses ``poses`` (a loop closed): the frames kept here
        take theirs."""
        def moved(e: _Entry | None) -> _Entry | None:
            if e is None or not first <= e.index < first + len(poses):
                return e
            return e._replace(pose=poses[e.index - first])
        self._settled = moved(self._settled)
        self._open = [moved(e) for e in self._open]


def _filled(entries: list[_Entry]) -> list[np.ndarray]:
    """The entries' poses with every run of LOST ones between two that are not interpolated
    between those two (a run with no tracked frame before it keeps its poses)."""
    poses = [e.pose for e in entries]
    left = None
    for k, e in enumerate(entries):
        if e.lost:
            continue
        if left is not None and k - left > 1:
            a, b = entries[left], e
            step = inverse_np(a.pose) @ b.pose
            span = max(b.timestamp - a.timestamp, 1e-9)
            for j in range(left + 1, k):
                poses[j] = a.pose @ scale_motion_np(step, (entries[j].timestamp
                                                           - a.timestamp) / span)
        left = k
    return poses
