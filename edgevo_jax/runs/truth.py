"""A run against its ground truth, frame by frame: the truth at the run's timestamps, each
motion's error against the truth's, and the frames that went wrong silently (called OK, off
the truth). Used by a run's statistics (``run.summarise``) and by the benchmarks
(``measure``)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from ..datasets.groundtruth import groundtruth_pose_at
from ..geometry import inverse_np, rotation_angle_np
from ..io import poses7_to_matrices

__all__ = ["DIVERGED_ROT_DEG", "DIVERGED_TRANS_M", "GT_MAX_DIFF_S", "diverged_frames",
           "groundtruth_at", "motion_errors", "silently_wrong"]

#: a frame called OK whose motion is off the ground truth's by more than these has diverged
DIVERGED_TRANS_M = 0.05
DIVERGED_ROT_DEG = 3.0
GT_MAX_DIFF_S = 0.02  # s to the nearest ground-truth pose, as the ATE's association


def groundtruth_at(seq: Any, timestamps: Sequence[float], *, max_diff: float = GT_MAX_DIFF_S,
                   interpolate: bool = False) -> np.ndarray:
    """Ground-truth T_world_cam (N, 4, 4) at each timestamp (``datasets.groundtruth_pose_at``:
    the nearest pose, or with ``interpolate`` the pose at that time), all NaN where there is
    none within ``max_diff`` s or the sequence has no ground truth."""
    out = np.full((len(timestamps), 4, 4), np.nan)
    for i, t in enumerate(np.asarray(timestamps, np.float64)):
        pose7 = groundtruth_pose_at(seq, float(t), max_diff, interpolate=interpolate)
        if pose7 is not None:
            out[i] = poses7_to_matrices(np.asarray(pose7)[None])[0]
    return out


def motion_errors(poses: np.ndarray, gt_poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For each frame i >= 1, the error of the estimated motion from frame i-1 against the
    ground truth's: E = (G_{i-1}^-1 G_i)^-1 (P_{i-1}^-1 P_i); returns (|trans(E)| in m,
    angle(E) in degrees), each of length N - 1 (NaN where a ground-truth pose is NaN)."""
    p = np.asarray(poses, np.float64)
    g = np.asarray(gt_poses, np.float64)
    if p.shape != g.shape or p.ndim != 3 or p.shape[1:] != (4, 4):
        raise ValueError(f"poses {p.shape} and gt_poses {g.shape} must both be (N, 4, 4)")
    if p.shape[0] < 2:
        return np.zeros(0), np.zeros(0)
    rel_est = inverse_np(p[:-1]) @ p[1:]
    rel_gt = inverse_np(g[:-1]) @ g[1:]
    e = inverse_np(rel_gt) @ rel_est
    trans = np.linalg.norm(e[:, :3, 3], axis=-1)
    rot = np.degrees(np.asarray(rotation_angle_np(e), np.float64).reshape(-1))
    return trans, rot


def diverged_frames(poses: np.ndarray, states: Sequence[str], gt_poses: np.ndarray, *,
                    trans_m: float = DIVERGED_TRANS_M, rot_deg: float = DIVERGED_ROT_DEG
                    ) -> list[int]:
    """Indices of the silently diverged frames of a run.

    ``poses`` (N, 4, 4) are the run's T_world_cam in frame order, ``states`` its N states
    (``"OK"``, ``"WEAK"``, ``"LOST"``) and ``gt_poses`` (N, 4, 4) the ground truth at the
    same frames' timestamps (NaN where unknown: :func:`groundtruth_at`). Frame i >= 1 is
    diverged when it and the frame before it (the previous frame the method tracked) are
    both OK and its motion from that frame differs from the ground truth's motion between
    the same timestamps by more than ``trans_m`` metres or ``rot_deg`` degrees. A motion into
    or out of a WEAK or LOST frame is not judged: the method flagged it, so any jump there
    is not silent. Frames without ground truth on either side are not judged."""
    return _off(poses, states, gt_poses, trans_m, rot_deg, after_ok=True)


def silently_wrong(poses: np.ndarray, states: Sequence[str], gt_poses: np.ndarray, *,
                   trans_m: float = DIVERGED_TRANS_M, rot_deg: float = DIVERGED_ROT_DEG
                   ) -> list[int]:
    """Indices of the frames called OK whose motion from the previous frame of the written
    trajectory, whatever that frame's state, differs from the ground truth's by more than
    ``trans_m`` metres or ``rot_deg`` degrees (arguments as :func:`diverged_frames`, which
    judges only OK after OK): an OK frame that jumps away from a WEAK or LOST one is a user's
    wrong pose all the same. Frames without ground truth on either side are not judged."""
    return _off(poses, states, gt_poses, trans_m, rot_deg, after_ok=False)


def _off(poses, states, gt_poses, trans_m: float, rot_deg: float, *, after_ok: bool
         ) -> list[int]:
    """The OK frames i >= 1 (after an OK frame too, with ``after_ok``) whose motion from
    frame i - 1 is off the truth's by more than the bounds."""
    if len(states) != len(poses):
        raise ValueError(f"{len(states)} states for {len(poses)} poses")
    trans, rot = motion_errors(poses, gt_poses)
    out = []
    for i in range(1, len(states)):
        if states[i] != "OK" or (after_ok and states[i - 1] != "OK"):
            continue
        t, r = trans[i - 1], rot[i - 1]
        if math.isfinite(t) and math.isfinite(r) and (t > trans_m or r > rot_deg):
            out.append(i)
    return out
