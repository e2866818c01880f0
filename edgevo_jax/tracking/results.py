"""What tracking gives per frame: the tracking states, ``FrameResult`` and the ``FrameResults``
mixin of a run's results (timestamps, poses); ``Correction`` (earlier poses moved,
``map.poses``) and ``Refinement`` (a keyframe pose the window refined)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..config import Config
from ..map.poses import Correction

__all__ = ["LOST", "OK", "WEAK", "Correction", "FrameResult", "FrameResults", "Refinement"]

OK, WEAK, LOST = "OK", "WEAK", "LOST"


@dataclass(frozen=True)
class FrameResult:
    """What tracking one frame gives: pose T_world_cam (4, 4, float64), tracking state
    (``OK``; ``WEAK``: usable but doubtful; ``LOST``: the pose is the constant-velocity
    prediction, never NaN) and the reason when not OK, covariance (6, 6) of a left twist [v, w]
    of T_cur_kf, level-0 inliers, whether the frame became a keyframe (and why), the number of
    keyframe edges it was tracked with, the edge selection and local mapping times when it
    became a keyframe (mapping None when off), and host timings in ms (preprocess; solve =
    from dispatch to read-back; total); ``inlier_share``: the level-0 inliers per keyframe
    edge in view (None for the first frame and LOST ones); ``placed``: how the keyframe map
    placed the frame, when it did (found again after a loss or a guess, or an older keyframe
    taking over on a revisit; None otherwise); ``depth_agreement``: the second opinion's
    share of the previous frame's depth points on the frame's surfaces at its pose (None
    where the frame was not checked or could not be: ``Config.depth_check_share``). A
    keyframe's pose is the window's refined one."""

    timestamp: float
    pose: np.ndarray
    state: str
    reason: str | None
    inliers: int
    covariance: np.ndarray | None
    keyframe: str | None
    edges_used: int
    select_ms: float | None
    mapping_ms: float | None
    preprocess_ms: float
    solve_ms: float
    total_ms: float
    inlier_share: float | None = None
    placed: str | None = None
    depth_agreement: float | None = None


@dataclass(frozen=True)
class Refinement:
    """A keyframe pose refined by the local window, as the tracker took it: the keyframe's
    timestamp, the index of the frame being concluded when it was taken, and its pose
    T_world_kf before and after (4, 4)."""

    keyframe_timestamp: float
    frame_index: int
    before: np.ndarray
    after: np.ndarray


class FrameResults:
    """Mixin for a run's ``results`` (list of FrameResult): its timestamps and poses; a run
    also has ``config`` and ``num_keyframes``, and ``summary_fields`` (its own statistics
    for ``run.summarise``)."""

    results: list[FrameResult]
    config: Config | None
    num_keyframes: int

    def summary_fields(self) -> dict:
        """Statistics of this kind of run beyond the common ones (none here)."""
        return {}

    @property
    def timestamps(self) -> np.ndarray:
        """(N,) timestamps of the tracked frames (s)."""
        return np.array([r.timestamp for r in self.results])

    @property
    def poses(self) -> np.ndarray:
        """(N, 4, 4) T_world_cam of the tracked frames."""
        return np.array([r.pose for r in self.results]).reshape(-1, 4, 4)
