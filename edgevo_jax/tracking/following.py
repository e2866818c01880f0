"""The tracker's state following the keyframes that moved in the map's record of poses
(``map.poses``: the window's refinements, a loop's correction): the keyframes it holds take
their new poses and the last frames' poses move with the current one (``follow``,
``begin_frame``); the device's prediction inputs from world poses (``relative_from_world``).
Used by the decision (``decision``) and its driver (``odometry``)."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

import numpy as np

from ..geometry import inverse_np
from ..hostmem import aligned_array
from .records import Keyframe, Motion, TrackerState

__all__ = ["begin_frame", "follow", "relative_from_world", "with_keyframe"]


def follow(state: TrackerState, moved: Sequence[Any]) -> TrackerState:
    """The state with the keyframes that moved in the map's record of poses (each with
    ``key``, the keyframe's id, and its new ``pose``: a refinement of the window, a loop's
    correction), in order: each keyframe the state holds takes its new pose; when it is the
    current keyframe the last two frame poses move with it (their motion relative to it,
    which the device predicts from, is unchanged). A keyframe the state no longer holds (one
    a recovery left) is skipped."""
    for m in moved:
        kf = next((k for k in (state.keyframe, *state.previous) if k is not None
                   and k.id == m.key), None)
        if kf is None:
            continue
        motion = state.motion
        if state.keyframe is not None and kf.id == state.keyframe.id:
            motion = motion.moved(m.pose @ inverse_np(kf.pose))
        state = dataclasses.replace(with_keyframe(state, dataclasses.replace(kf, pose=m.pose)),
                                    motion=motion)
    return state


def begin_frame(state: TrackerState, moved: Sequence[Any]) -> TrackerState:
    """Count the frame being concluded, the keyframes that ``moved`` before it followed
    (``follow``)."""
    return follow(dataclasses.replace(state, index=state.index + 1), moved)


def with_keyframe(state: TrackerState, kf: Keyframe) -> TrackerState:
    """``kf`` in place of every record of the same keyframe (current and earlier)."""
    def swap(k):
        return kf if k is not None and k.id == kf.id else k
    return dataclasses.replace(state, keyframe=swap(state.keyframe),
                               previous=tuple(swap(k) for k in state.previous))


def relative_from_world(motion: Motion, kf_pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A, B (float32) from the last two world poses and the keyframe's (float64)."""
    rel = [aligned_array(inverse_np(p) @ kf_pose, np.float32) for p in motion.poses]
    return rel[-1], rel[0]
