"""Ground-truth poses of any sequence with a ``groundtruth`` (timestamps (N,), pose7 (N, 7),
``tx ty tz qx qy qz qw``; TUM folders, bags with ``--groundtruth``), looked up by time."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from .base import Source

__all__ = ["groundtruth_pose_at"]


def groundtruth_pose_at(
    seq: Source, t: float, max_diff: float | None = None, *, interpolate: bool = False
) -> np.ndarray | None:
    """Ground-truth pose7 nearest in time to ``t``; None without ground truth, or when the
    nearest one is more than ``max_diff`` seconds away (if given).

    ``interpolate``: the pose at ``t`` itself, between the ground-truth poses before and
    after it (position linearly, orientation by slerp); None outside the ground truth's time
    span or when the two are more than ``max_diff`` seconds apart (if given). At TUM's
    100 Hz a camera moving 0.3 m/s is up to 1.5 mm from its nearest ground-truth pose."""
    if not math.isfinite(t):
        raise ValueError(f"timestamp must be finite, got {t}")
    if seq.groundtruth is None or seq.groundtruth[0].size == 0:
        return None
    gt_t, gt_p = seq.groundtruth
    order = np.argsort(gt_t, kind="stable")
    ts = gt_t[order]
    if interpolate:
        return _interpolated(ts, gt_p[order], t, max_diff)
    k = int(np.clip(np.searchsorted(ts, t), 1, max(ts.size - 1, 1)))
    if ts.size == 1:
        k = 0
    elif abs(ts[k - 1] - t) <= abs(ts[k] - t):
        k -= 1
    if max_diff is not None and abs(ts[k] - t) > max_diff:
        return None
    return gt_p[order[k]].copy()


def _interpolated(ts: np.ndarray, poses: np.ndarray, t: float,
                  max_diff: float | None) -> np.ndarray | None:
    """pose7 at t between the sorted samples (ts, poses) around it (see groundtruth_pose_at)."""
    if t < ts[0] or t > ts[-1]:
        return None
    k = int(np.searchsorted(ts, t, side="right"))
    if k == ts.size:  # t == ts[-1]
        return poses[-1].copy()
    a, b = k - 1, k
    if max_diff is not None and ts[b] - ts[a] > max_diff:
        return None
    s = (t - ts[a]) / (ts[b] - ts[a])
    qa, qb = (poses[i, 3:] / np.linalg.norm(poses[i, 3:]) for i in (a, b))
    if qa @ qb < 0:
        qb = -qb
    angle = np.arccos(np.clip(qa @ qb, -1.0, 1.0))
    if angle < 1e-9:
        q = qa
    else:
        q = (np.sin((1 - s) * angle) * qa + np.sin(s * angle) * qb) / np.sin(angle)
    out = np.empty(7)
    out[:3] = (1 - s) * poses[a, :3] + s * poses[b, :3]
    out[3:] = q / np.linalg.norm(q)
    return out
