"""The one record of every pose a run has: each keyframe's pose T_world_kf and each frame as
its keyframe and its pose as reported, from which its written pose is derived.

A frame hangs from its keyframe (the one it was tracked from, or made; a LOST frame from the
keyframe it kept), as ORB-SLAM3 stores a frame against its reference keyframe: its pose as
reported is its keyframe's pose as tracked times its pose in the keyframe, and its written
pose is that times every correction that moved the keyframe since (``pose``). Writes:
- ``add_keyframe``: a keyframe made, at its pose;
- ``refine``: the window refined a keyframe's pose. No frame moves: frames already reported
  keep their poses, later ones are tracked from the refined pose;
- ``move``: keyframes moved by a correction C = T_world_new_world_old (a chain made at a
  guess tied to the map, a loop closed): each frame hanging from one of them moves with it;
- ``fill``: a LOST frame's pose, a guess, replaced by the path between the frames tracked on
  either side of the loss (``map.ledger``); corrections of its keyframe after that apply on
  top.
The tracker's records of keyframes (``tracking.records.Keyframe.pose``) and the map's queries
(``map.store``) read the poses from here; the window keeps its working copies, as a solver
must. Host side, numpy; the tracker's thread owns it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from ..geometry import orthonormalise_np


@dataclass(frozen=True)
class Correction:
    """Earlier poses moved: frames ``first`` to ``last`` (indices, inclusive) take ``poses``
    ((last - first + 1, 4, 4) T_world_cam). ``reason`` ``"tie"``: the keyframe map placed
    the frame after ``last``, a chain of keyframes made at a guess moved into the map's
    frame with it, and LOST frames were filled in between the tracked frames on either
    side; ``"loop"``: a loop was closed, and the frames tracked from the keyframes the pose
    graph moved moved with them (``last``: the last frame concluded). States and reasons
    stay as they were reported."""

    first: int
    last: int
    poses: np.ndarray
    reason: str = "tie"


class _Frame(NamedTuple):
    keyframe: int | None  # None: no keyframe yet (a first frame that could not be one)
    timestamp: float
    lost: bool
    pose: np.ndarray  # T_world_cam as reported, or as filled in
    base: int  # how many of its keyframe's corrections ``pose`` holds already


class Poses:
    """Every keyframe's pose and every frame's (module doc)."""

    def __init__(self) -> None:
        self._array = np.zeros((64, 4, 4))  # T_world_kf by keyframe id
        self._known = np.zeros(64, bool)
        self._moves: dict[int, list[np.ndarray]] = {}  # id -> its corrections, in order
        self._times: dict[int, float] = {}  # id -> its frame's timestamp
        self._frames: list[_Frame] = []
        self._first: dict[int, int] = {}  # keyframe id -> the first frame hanging from it

    # -- keyframes -------------------------------------------------------------------------
    def __contains__(self, key: int) -> bool:
        return 0 <= key < len(self._known) and bool(self._known[key])

    def keyframe(self, key: int) -> np.ndarray:
        """Keyframe ``key``'s pose T_world_kf (4, 4) (a copy). KeyError when unknown."""
        if key not in self:
            raise KeyError(f"keyframe {key} has no pose")
        return self._array[key].copy()

    def keyframes(self, keys) -> np.ndarray:
        """(n, 4, 4) poses of keyframes ``keys`` (ids, all known), for queries over many."""
        return self._array[np.asarray(keys, int)]

    def add_keyframe(self, key: int, pose: np.ndarray, timestamp: float) -> None:
        """Keyframe ``key`` made at ``pose`` (T_world_kf) from the frame at ``timestamp`` (s).
        ValueError for an id known already or a negative one."""
        if key < 0 or key in self:
            raise ValueError(f"keyframe {key} has a pose already" if key >= 0
                             else f"keyframe ids are non-negative, got {key}")
        while key >= len(self._known):
            self._array = np.concatenate([self._array, np.zeros_like(self._array)])
            self._known = np.concatenate([self._known, np.zeros_like(self._known)])
        self._array[key], self._known[key] = pose, True
        self._moves[key], self._times[key] = [], float(timestamp)

    def keyframe_time(self, key: int) -> float:
        """The timestamp (s) of the frame keyframe ``key`` was made from."""
        return self._times[key]

    def refine(self, key: int, pose: np.ndarray) -> None:
        """The window refined keyframe ``key``: its pose is ``pose``; no frame moves."""
        self.keyframe(key)  # known
        self._array[key] = np.asarray(pose, np.float64)

    def move(self, corrections: dict[int, np.ndarray], *, orthonormalise: bool = False) -> None:
        """Keyframes move: each ``key`` of ``corrections`` takes C @ its pose (C =
        T_world_new_world_old; ``orthonormalise``: its rotation made orthonormal again, as
        after a pose graph's solve), and every frame hanging from it moves with it."""
        for key, C in corrections.items():
            pose = C @ self.keyframe(key)
            self._array[key] = orthonormalise_np(pose) if orthonormalise else pose
            self._moves[key].append(np.asarray(C, np.float64))

    # -- frames -----------------------------------------------------------------------------
    def __len__(self) -> int:
        """Frames recorded."""
        return len(self._frames)

    def add_frame(self, keyframe: int | None, timestamp: float, pose: np.ndarray, *,
                  lost: bool) -> int:
        """A frame concluded at ``pose`` (T_world_cam, as reported), hanging from keyframe
        ``keyframe`` (None: none); its index."""
        base = 0 if keyframe is None else len(self._moves[keyframe])
        self._frames.append(_Frame(keyframe, float(timestamp), lost, pose, base))
        if keyframe is not None:
            self._first.setdefault(keyframe, len(self._frames) - 1)
        return len(self._frames) - 1

    def pose(self, index: int) -> np.ndarray:
        """Frame ``index``'s written pose: as reported (or filled in), times the corrections
        of its keyframe since, in order."""
        f = self._frames[index]
        pose = f.pose
        for C in ([] if f.keyframe is None else self._moves[f.keyframe][f.base:]):
            pose = C @ pose
        return pose

    def poses(self, start: int = 0, stop: int | None = None) -> np.ndarray:
        """(n, 4, 4) written poses of frames ``start`` to ``stop`` (exclusive; None: all)."""
        stop = len(self._frames) if stop is None else stop
        return np.array([self.pose(i) for i in range(start, stop)]).reshape(-1, 4, 4)

    def hangs_from(self, index: int) -> int | None:
        """The keyframe frame ``index`` hangs from (None: none)."""
        return self._frames[index].keyframe

    def lost(self, index: int) -> bool:
        """Whether frame ``index`` was LOST when reported."""
        return self._frames[index].lost

    def timestamp(self, index: int) -> float:
        """Frame ``index``'s timestamp (s)."""
        return self._frames[index].timestamp

    def first_hanging_from(self, keys) -> int | None:
        """The first frame hanging from one of keyframes ``keys`` (None: none)."""
        return min((self._first[k] for k in keys if k in self._first), default=None)

    def fill(self, index: int, pose: np.ndarray) -> None:
        """Frame ``index`` (a LOST one) takes ``pose`` as its pose from now on (module doc)."""
        f = self._frames[index]
        base = 0 if f.keyframe is None else len(self._moves[f.keyframe])
        self._frames[index] = f._replace(pose=pose, base=base)
