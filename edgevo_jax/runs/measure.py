"""Measuring runs, for benchmarks and experiments: a clip at a lower frame rate, a peer's run
(``edgevo_jax.peers``) from edgevo's first pose, accuracy against the ground truth with the
reason when there is none, statistics of per-frame times over the warm frames and of results
over seeds, and the frames that went wrong silently (called OK, off the ground truth)."""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from typing import Any

import numpy as np

from ..datasets.tum import TumSequence, load_sequence, subsequence
from ..geometry import inverse_np, rotation_angle_np
from ..io import matrices_to_poses7
from ..metrics import ate, rpe_per_second
from ..peers import PeerTrack, make_peer, track_peer
from .run import initial_pose
from .truth import (
    DIVERGED_ROT_DEG,
    DIVERGED_TRANS_M,
    GT_MAX_DIFF_S,
    diverged_frames,
    groundtruth_at,
    motion_errors,
    silently_wrong,
)

__all__ = ["DIVERGED_ROT_DEG", "DIVERGED_TRANS_M", "GT_MAX_DIFF_S", "WARMUP_FRAMES",
           "accuracy", "diverged_frames", "finite_stats", "frame_stats", "groundtruth_at",
           "load_clip", "motion_errors", "pose_errors", "run_peer", "silently_wrong"]

#: frames left out of warm statistics: frame 0 sets up, frame 1 is the first pair (compiles)
WARMUP_FRAMES = 2



def load_clip(path: str | os.PathLike[str], *, frame_step: int = 1,
              max_frames: int | None = None, camera: Any = None) -> TumSequence:
    """The TUM folder at ``path`` played at 1/``frame_step`` of its frame rate as the
    benchmark's lists would be recorded (``load_sequence(..., frame_step=k)``: every k-th
    line of rgb.txt and of depth.txt, then associated), cut to the span of time of the full
    sequence's first ``max_frames`` frames (None: all; the cut keeps ``subsequence``'s
    name); ``camera``: ``load_sequence``'s (None: the folder's own)."""
    seq = load_sequence(path, frame_step=frame_step, camera=camera)
    if max_frames is None:
        return seq
    if max_frames < 1:
        raise ValueError(f"max_frames must be positive, got {max_frames}")
    full = seq if frame_step == 1 else load_sequence(path)
    t_end = full.timestamps[min(max_frames, len(full)) - 1]
    return subsequence(seq, 0, int(np.searchsorted(seq.timestamps, t_end, "right")))


def run_peer(method: str, seq: Any, *, max_frames: int | None = None) -> PeerTrack:
    """Track the first ``max_frames`` frames of ``seq`` (None: all) with the peer ``method``
    (``peers.make_peer``; PeerMissing when it cannot run here) from edgevo's first pose
    (``run.initial_pose``); the track, with the peer's description."""
    peer = make_peer(method, seq.intrinsics, seq.width, seq.height)
    n = len(seq) if max_frames is None else min(len(seq), max_frames)
    return track_peer(peer, seq, n, initial_pose(seq))


def frame_stats(frame_ms: Sequence[float], *, skip: int = WARMUP_FRAMES) -> dict[str, float]:
    """Median, p90, mean and max of per-frame times after the first ``skip`` frames (NaN each
    when none is left)."""
    v = np.asarray(frame_ms[skip:], np.float64)
    if not v.size:
        return dict.fromkeys(("median", "p90", "mean", "max"), math.nan)
    return {"median": float(np.median(v)), "p90": float(np.percentile(v, 90)),
            "mean": float(v.mean()), "max": float(v.max())}


def finite_stats(values: Sequence[float | None]) -> dict[str, float]:
    """Mean, standard deviation (ddof 1; NaN under two values), min, max and median of the
    finite values (None, NaN and infinities left out; NaN each when none is left), e.g. one
    setting's ATE over seeds."""
    v = np.asarray([math.nan if x is None else x for x in values], np.float64)
    v = v[np.isfinite(v)]
    if not v.size:
        return dict.fromkeys(("mean", "std", "min", "max", "median"), math.nan)
    return {"mean": float(v.mean()), "std": float(v.std(ddof=1)) if v.size > 1 else math.nan,
            "min": float(v.min()), "max": float(v.max()), "median": float(np.median(v))}


def accuracy(groundtruth: tuple[np.ndarray, np.ndarray] | None, timestamps: np.ndarray,
             poses: np.ndarray, *, no_groundtruth: str = "no ground truth") -> dict[str, Any]:
    """ATE RMSE (m; TUM's ``evaluate_ate``: rigid alignment) and RPE over 1 s
    (``rpe_m_per_s``, ``rpe_deg_per_s``) of T_world_cam ``poses`` (N, 4, 4) at
    ``timestamps`` against ``groundtruth`` (times, poses7). NaN where they cannot be
    computed, with an ``accuracy_note`` saying why: ``no_groundtruth`` without one, a clip
    spanning under 1 s (RPE), or the metric's error (e.g. fewer than 3 poses associated)."""
    ts = np.asarray(timestamps, np.float64)
    out: dict[str, Any] = {"ate_rmse_m": math.nan, "rpe_m_per_s": math.nan,
                           "rpe_deg_per_s": math.nan}
    if groundtruth is None:
        out["accuracy_note"] = no_groundtruth
        return out
    est = matrices_to_poses7(np.asarray(poses, np.float64))
    try:
        out["ate_rmse_m"] = float(ate(groundtruth, (ts, est))["rmse"])
        if ts.size and ts[-1] - ts[0] >= 1.0:
            r = rpe_per_second(groundtruth, (ts, est))
            out["rpe_m_per_s"] = float(r["trans_rmse_m_per_s"])
            out["rpe_deg_per_s"] = float(r["rot_rmse_deg_per_s"])
        else:
            out["accuracy_note"] = "RPE n/a: clip shorter than 1 s"
    except ValueError as err:  # e.g. fewer than 3 poses associated with the ground truth
        out["accuracy_note"] = str(err)
    return out


def pose_errors(poses: np.ndarray, gt_poses: np.ndarray, fit: Sequence[int]
                ) -> tuple[np.ndarray, np.ndarray]:
    """Each frame's pose error against the ground truth once the estimate is aligned on the
    frames ``fit`` (indices): the rigid A = (R, t) with R the rotation nearest the sum of
    G_i R_i^T (its polar factor) and t the mean of g_i - R p_i over the fit frames with
    ground truth, so that orientations count as positions do; returns, per frame, |trans(E)|
    (m) and angle(E) (degrees) of E = G^-1 A P (NaN where the ground truth is). ValueError
    when no fit frame has ground truth."""
    P = np.asarray(poses, np.float64)
    G = np.asarray(gt_poses, np.float64)
    if P.shape != G.shape or P.ndim != 3 or P.shape[1:] != (4, 4):
        raise ValueError(f"poses {P.shape} and gt_poses {G.shape} must both be (N, 4, 4)")
    fit = [i for i in fit if np.all(np.isfinite(G[i]))]
    if not fit:
        raise ValueError("no frame to align on has ground truth")
    M = sum(G[i, :3, :3] @ P[i, :3, :3].T for i in fit)
    u, _, vt = np.linalg.svd(M)
    R = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
    A = np.eye(4)
    A[:3, :3] = R
    A[:3, 3] = np.mean([G[i, :3, 3] - R @ P[i, :3, 3] for i in fit], axis=0)
    E = inverse_np(np.where(np.isfinite(G), G, np.eye(4))) @ A @ P
    bad = ~np.all(np.isfinite(G), axis=(1, 2))
    trans = np.where(bad, np.nan, np.linalg.norm(E[:, :3, 3], axis=-1))
    rot = np.degrees(np.asarray(rotation_angle_np(E), np.float64).reshape(-1))
    return trans, np.where(bad, np.nan, rot)


def wrong_loops(loops: dict | None, seq: Any, *, metres: float = DIVERGED_TRANS_M,
                degrees: float = DIVERGED_ROT_DEG) -> int:
    """How many kept loop edges (``loops["closed"]``, a run's ``RunResult.loops``) are more
    than ``metres`` or ``degrees`` from the truth's relative pose of their two keyframes
    (``seq``'s ground truth at their timestamps)."""
    wrong = 0
    for e in (loops or {}).get("closed", []):
        gt = groundtruth_at(seq, np.array([e["older_t"], e["newer_t"]]))
        D = inverse_np(inverse_np(gt[0]) @ gt[1]) @ np.asarray(e["measured"])
        wrong += bool(np.linalg.norm(D[:3, 3]) > metres
                      or np.degrees(rotation_angle_np(D)) > degrees)
    return wrong


def end_to_end_error(poses: np.ndarray, gt_poses: np.ndarray) -> tuple[float, float]:
    """The error of the estimated motion from the first frame the ground truth reaches to
    the last (``gt_poses`` (N, 4, 4), NaN where none) against the truth's: (m, radians)."""
    has = np.flatnonzero(np.isfinite(gt_poses[:, 0, 0]))
    a, b = has[0], has[-1]
    D = inverse_np(inverse_np(gt_poses[a]) @ gt_poses[b]) @ inverse_np(poses[a]) @ poses[b]
    return float(np.linalg.norm(D[:3, 3])), float(rotation_angle_np(D))
