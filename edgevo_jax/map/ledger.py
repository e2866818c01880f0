"""Which frames the keyframe map may still move (``Ledger``): those since the last frame
settled (tracked OK from a keyframe tied to the map, or placed by it). When a frame settles,
the LOST frames before it are filled in: each takes the pose interpolated (along the screw
motion, by time) between the frames tracked on either side, the settled frame being the last
of them. A held or extrapolated pose of a loss is a guess; once both ends are known, the path
between them is the better one. A chain made at a guess that the settling frame ties to the
map has moved with its keyframes already (``map.poses``); the ledger says which frames moved.
Frames are kept by index; their poses are ``map.poses``'s.
"""

from __future__ import annotations

import numpy as np

from ..geometry import inverse_np, scale_motion_np
from .poses import Correction, Poses


class Ledger:
    """The frames not settled yet, by index, over the poses of ``poses`` (module doc)."""

    def __init__(self, poses: Poses) -> None:
        self._poses = poses
        self._settled: int | None = None  # the last frame settled
        self._open: list[int] = []

    def record(self, index: int, *, settled: bool, moved: frozenset[int] = frozenset()
               ) -> Correction | None:
        """Frame ``index`` (recorded in the poses) was concluded; ``settled``: tracked OK from
        a keyframe tied to the map, or placed by it. A settled frame settles the frames
        before it: the earlier poses that moved (None: none did), where ``moved`` are the
        keyframes a tie moved with it."""
        if not settled:
            self._open.append(index)
            return None
        frames, poses = self._open, self._poses
        head = [] if self._settled is None else [self._settled]
        filled = _filled(poses, [*head, *frames, index])
        for i, pose in filled.items():
            poses.fill(i, pose)
        self._settled, self._open = index, []
        if not filled and not any(poses.hangs_from(i) in moved for i in frames):
            return None
        return Correction(frames[0], index - 1, poses.poses(frames[0], index))


def _filled(poses: Poses, frames: list[int]) -> dict[int, np.ndarray]:
    """Frame -> its pose interpolated, for every run of LOST frames among ``frames`` between
    two that are not (a run with no tracked frame before it keeps its poses)."""
    out: dict[int, np.ndarray] = {}
    left = None
    for k, i in enumerate(frames):
        if poses.lost(i):
            continue
        if left is not None and k - left > 1:
            a, b = frames[left], i
            pa = poses.pose(a)
            step = inverse_np(pa) @ poses.pose(b)
            ta = poses.timestamp(a)
            span = max(poses.timestamp(b) - ta, 1e-9)
            for j in frames[left + 1:k]:
                out[j] = pa @ scale_motion_np(step, (poses.timestamp(j) - ta) / span)
        left = k
    return out
