"""Judging a solve: whether it can be used at all (``lost_reason``), whether it is doubtful
(``weak_reason``; the inlier share against the recent frames': ``reference_share``,
``under``, ``share_doubt``; a start too far to trust without features: ``far_reason``),
the one judgement of a verified alignment (``verified``) and when two poses
agree (``agree``).

An alignment of a frame to a keyframe (a ``frontend.align.TrackResult``) is *verified* when
more than the distance field speaks for it (``verified``): the solve is usable
(``decision.lost_reason``: finite, enough inliers, a well-conditioned covariance), it stayed
within the alignment's basin of its start (``derive.basin_px``: it converged from where it
began, so a start of its own, a feature pose or the chain's, and the solve agree), and its
inlier share is at least ``ratio`` times a ``standard`` share (the best share a frame had
against that keyframe, or the recent frames'). Every place that accepts an alignment it did
not track calls it, with its thresholds as parameters:
- a frame found again (``places.Places.relocalise``): the lost ratio of the keyframe's own
  standard, and the doubt ratio to stand without a second keyframe;
- a second keyframe confirming a place (``places.confirmed``): the lost ratio of its own
  standard, and the pose within ``SECOND_M``, ``SECOND_DEG`` of the first (``agree``);
- a revisit and a loop (``places.Places.revisit``, ``loop``): the doubt ratio of the recent
  frames' share.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from ..config import Config
from ..derive import basin_px
from ..geometry import inverse_np, rotation_angle_np
from .records import TrackerState

#: frames (not lost) whose highest inlier share is the reference for the share ratios
SHARE_HISTORY = 5


def inlier_share(res) -> float:
    """Level-0 inliers per keyframe edge in view of a TrackResult (0 with none in view)."""
    return float(res.inliers) / max(float(res.visible), 1.0)


def lost_reason(num_edges: int, res, config: Config) -> str | None:
    """Why a solve result cannot be used (None: it can): no edges in the frame,
    non-finite pose or covariance, too few inliers, ill-conditioned covariance."""
    if num_edges == 0:
        return "no edges in the frame"
    T = np.asarray(res.T_c_k, np.float64)
    cov = np.asarray(res.covariance, np.float64)
    if not (np.all(np.isfinite(T)) and np.all(np.isfinite(cov))):
        return "non-finite pose"
    if int(res.inliers) < config.min_inliers:
        return f"too few inliers ({int(res.inliers)})"
    eig = np.linalg.eigvalsh(0.5 * (cov + cov.T))  # symmetric: cheaper than cond's SVD
    cond = eig[-1] / eig[0] if eig[0] > 0 else np.inf
    if not cond <= config.max_covariance_condition:
        return f"covariance ill-conditioned (condition {cond:.2g})"
    return None


def weak_reason(has_depth: bool, res, config: Config) -> str | None:
    """Why a usable result is doubtful: inliers whose mean residual is over half the gate
    (random matches under the gate average half of it), or a frame without depth (it
    cannot become a keyframe)."""
    mean = float(res.mean_residual)
    if mean > 0.5 * config.max_residual[0]:
        return f"mean residual {mean:.2f} px over half the gate"
    if not has_depth:
        return "no depth (cannot become a keyframe)"
    return None


def reference_share(state: TrackerState, config: Config) -> float | None:
    """The highest inlier share of the last ``SHARE_HISTORY`` frames not lost; None before
    there are any or with the check off (``doubt_share_ratio`` 0)."""
    if not state.shares or config.doubt_share_ratio <= 0:
        return None
    return float(np.max(state.shares))


def under(res, reference: float | None, ratio: float) -> bool:
    """Whether a result's inlier share is under ``ratio`` x the reference share."""
    return reference is not None and inlier_share(res) < ratio * reference


def share_doubt(res, reference: float | None, config: Config) -> str | None:
    """Why a solve is doubtful (WEAK) by its share: under ``doubt_share_ratio`` of the
    recent frames' from every start, with no feature start to confirm it."""
    doubt = config.doubt_share_ratio
    if under(res, reference, doubt):
        return (f"inlier share {inlier_share(res):.2f} under {doubt:g} x the recent "
                f"{reference:.2f}, not confirmed by features")
    return None


def far_reason(res, config: Config, gap: float | None) -> str | None:
    """Why a solve needs a feature start to confirm it (None: it does not): it moved farther
    from its start than the alignment's basin (``derive.basin_px``), or its frame comes more
    than ``lost_extrapolate_s`` after the last tracked one (``gap``, s: a start predicted
    across a gap that long is no evidence, and the recent shares say little of a view that
    far)."""
    basin, moved = basin_px(config), float(res.moved)
    if moved > basin:
        return f"moved {moved:.0f} px from its start, past the {basin:.0f} px basin"
    if gap is not None and gap > config.lost_extrapolate_s:
        return f"{gap:.2f} s after the last tracked frame"
    return None


#: two alignments against one keyframe agree (converged into one minimum) within this
#: translation (m) and rotation (degrees): ~2 px at 1.5 m for f ~ 530 px, under the spacing
#: of distinct minima (edges)
AGREE_M, AGREE_DEG = 0.005, 0.5
#: a second keyframe confirms a place when it puts the frame within this much of the first
#: (m, degrees): twice ``AGREE_M``, ``AGREE_DEG``, for the two keyframes' own pose errors
SECOND_M, SECOND_DEG = 2 * AGREE_M, 2 * AGREE_DEG


def verified(solve, usable: Callable[[object], bool], *, basin_px: float,
             standard: float | None, ratio: float) -> bool:
    """Whether ``solve`` is a verified alignment (module doc): ``usable(solve)``, moved at
    most ``basin_px`` (level-0 px) from its start, and an inlier share of at least ``ratio``
    x ``standard`` (None: no share to meet)."""
    return bool(usable(solve) and float(solve.moved) <= basin_px
                and (standard is None or inlier_share(solve) >= ratio * standard))


def agree(a: np.ndarray, b: np.ndarray, *, metres: float = AGREE_M,
          degrees: float = AGREE_DEG) -> bool:
    """Whether two poses (4, 4; in one frame) are within ``metres`` and ``degrees`` of each
    other."""
    D = inverse_np(np.asarray(a, np.float64)) @ np.asarray(b, np.float64)
    return bool(np.linalg.norm(D[:3, 3]) <= metres
                and np.degrees(rotation_angle_np(D)) <= degrees)
