"""TUM RGB-D benchmark metrics (host side, numpy float64).

Follows the benchmark's ``associate.py``, ``evaluate_ate.py`` and ``evaluate_rpe.py``
(Sturm et al., IROS 2012): greedy one-to-one timestamp association, rigid (no scale) Horn
alignment for the ATE, and the relative pose error over a fixed time interval.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from .geometry import inverse_np, rotation_angle_np
from .io import poses7_to_matrices

__all__ = ["TrajectoryAlignment", "align_trajectory", "associate_timestamps", "ate", "horn_align",
           "rpe"]


def _stamps(name: str, t: np.ndarray) -> np.ndarray:
    a = np.asarray(t, np.float64)
    if a.ndim != 1:
        raise ValueError(f"{name} timestamps must be 1-D, got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} timestamps must be finite")
    return a


def _trajectory(name: str, t: np.ndarray, poses7: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    ts = _stamps(name, t)
    ps = np.asarray(poses7, np.float64)
    if ps.shape != (ts.shape[0], 7):
        raise ValueError(
            f"{name}: expected poses7 of shape ({ts.shape[0]}, 7) to match its timestamps, "
            f"got {ps.shape}"
        )
    if not np.all(np.isfinite(ps)):
        raise ValueError(f"{name} poses must be finite")
    return ts, ps


def associate_timestamps(
    first: np.ndarray, second: np.ndarray, max_diff: float = 0.02, offset: float = 0.0
) -> np.ndarray:
    """Match two timestamp lists like TUM's ``associate.py``.

    Candidates are all pairs with ``|a - (b + offset)| < max_diff``; they are taken greedily
    in order of increasing difference (ties by the first, then the second timestamp, as
    ``associate.py`` sorts), each index at most once. Returns (M, 2) int64 index pairs
    ``(i into first, j into second)`` sorted by i. Only candidates inside the window are
    generated (np.searchsorted), so long lists are cheap.
    """
    a = _stamps("first", first)
    b = _stamps("second", second)
    if not (math.isfinite(max_diff) and max_diff > 0):
        raise ValueError(f"max_diff must be positive and finite, got {max_diff}")
    if not math.isfinite(offset):
        raise ValueError(f"offset must be finite, got {offset}")
    if a.size == 0 or b.size == 0:
        return np.zeros((0, 2), np.int64)
    order = np.argsort(b, kind="stable")
    bs = b[order] + offset
    # Slightly widened window; the exact TUM test below decides.
    pad = max_diff * (1.0 + 1e-9) + 1e-9
    lo = np.searchsorted(bs, a - pad, side="left")
    hi = np.searchsorted(bs, a + pad, side="right")
    counts = hi - lo
    total = int(counts.sum())
    if total == 0:
        return np.zeros((0, 2), np.int64)
    i = np.repeat(np.arange(a.size), counts)
    starts = np.repeat(lo - np.concatenate([[0], np.cumsum(counts)[:-1]]), counts)
    k = starts + np.arange(total)
    j = order[k]
    diff = np.abs(a[i] - (b[j] + offset))
    keep = diff < max_diff
    i, j, diff = i[keep], j[keep], diff[keep]
    # Order of associate.py's sorted (diff, a, b) tuples; indices break remaining ties.
    cand = np.lexsort((j, i, b[j], a[i], diff))
    used_a = np.zeros(a.size, bool)
    used_b = np.zeros(b.size, bool)
    out_i: list[int] = []
    out_j: list[int] = []
    for ii, jj in zip(i[cand].tolist(), j[cand].tolist(), strict=True):
        if not used_a[ii] and not used_b[jj]:
            used_a[ii] = True
            used_b[jj] = True
            out_i.append(ii)
            out_j.append(jj)
    pairs = np.stack([np.asarray(out_i, np.int64), np.asarray(out_j, np.int64)], axis=1)
    return pairs[np.argsort(pairs[:, 0], kind="stable")]


def horn_align(model: np.ndarray, data: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rigid (no scale) least-squares alignment: R (3, 3), t (3,) with R @ model + t ~= data.

    model, data: (3, N) with N >= 3. Horn / Umeyama through the SVD of the cross-covariance,
    with the reflection fix, as TUM's ``align()``.
    """
    m = np.asarray(model, np.float64)
    d = np.asarray(data, np.float64)
    if m.ndim != 2 or m.shape[0] != 3 or m.shape != d.shape:
        raise ValueError(f"model and data must both be (3, N), got {m.shape} and {d.shape}")
    if m.shape[1] < 3:
        raise ValueError(f"need at least 3 points to align, got {m.shape[1]}")
    if not (np.all(np.isfinite(m)) and np.all(np.isfinite(d))):
        raise ValueError("model and data must be finite")
    mu_m = m.mean(axis=1)
    mu_d = d.mean(axis=1)
    w = (d - mu_d[:, None]) @ (m - mu_m[:, None]).T  # sum_k data_k model_k^T
    u, _, vh = np.linalg.svd(w)
    s = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vh) < 0:
        s[2, 2] = -1.0
    r = u @ s @ vh
    return r, mu_d - r @ mu_m


def _stats(err: np.ndarray) -> dict[str, float]:
    return {
        "rmse": float(np.sqrt(np.mean(err * err))),
        "mean": float(np.mean(err)),
        "median": float(np.median(err)),
        "std": float(np.std(err)),
        "min": float(np.min(err)),
        "max": float(np.max(err)),
    }


class TrajectoryAlignment(NamedTuple):
    """An estimated trajectory rigidly aligned onto the ground truth as the ATE aligns it.

    est_t (N,) s and est_xyz (3, N) m: every estimated position, aligned (R @ p + t) into the
    ground truth's world frame; gt_t (M,) s and gt_xyz (3, M) m: the ground-truth positions;
    pairs (K, 2): associated (ground-truth index, estimate index), K >= 3; error (K,) m: the
    per-pair position error after alignment (its RMS is the ATE RMSE); R (3, 3), t (3,): the
    alignment, mapping estimate world coordinates into the ground-truth world frame.
    """

    est_t: np.ndarray
    est_xyz: np.ndarray
    gt_t: np.ndarray
    gt_xyz: np.ndarray
    pairs: np.ndarray
    error: np.ndarray
    R: np.ndarray
    t: np.ndarray

    @property
    def rmse(self) -> float:
        """ATE RMSE (m): the root mean square of ``error``."""
        return float(np.sqrt(np.mean(self.error ** 2)))


def align_trajectory(
    gt_t: np.ndarray, gt_poses7: np.ndarray, est_t: np.ndarray, est_poses7: np.ndarray,
    *, max_diff: float = 0.02,
) -> TrajectoryAlignment:
    """Associate an estimate with the ground truth and align it rigidly, as TUM's
    ``evaluate_ate.py`` does (the alignment :func:`ate` measures).

    gt_t (M,), est_t (N,): timestamps in seconds; gt_poses7 (M, 7), est_poses7 (N, 7):
    ``tx ty tz qx qy qz qw`` of T_world_cam (metres), each in its own world frame. Timestamps
    are associated within ``max_diff`` seconds (TUM ``associate.py``), the associated
    estimated positions aligned onto the ground truth by :func:`horn_align` (rigid, no
    scale). ValueError when fewer than 3 poses associate.
    """
    gt_ts, gt_p = _trajectory("ground truth", gt_t, gt_poses7)
    est_ts, est_p = _trajectory("estimate", est_t, est_poses7)
    pairs = associate_timestamps(gt_ts, est_ts, max_diff)
    if pairs.shape[0] < 3:
        raise ValueError(
            f"ATE needs at least 3 associated poses, got {pairs.shape[0]} "
            f"(ground truth {gt_ts.size} poses, estimate {est_ts.size} poses, "
            f"max_diff {max_diff} s): do the timestamps overlap?"
        )
    gt_xyz = gt_p[:, :3].T
    est_raw = est_p[:, :3].T
    R, t = horn_align(est_raw[:, pairs[:, 1]], gt_xyz[:, pairs[:, 0]])
    est_xyz = R @ est_raw + t[:, None]
    error = np.linalg.norm(est_xyz[:, pairs[:, 1]] - gt_xyz[:, pairs[:, 0]], axis=0)
    return TrajectoryAlignment(est_ts, est_xyz, gt_ts, gt_xyz, pairs, error, R, t)


def ate(
    gt_t: np.ndarray,
    gt_poses7: np.ndarray,
    est_t: np.ndarray,
    est_poses7: np.ndarray,
    max_diff: float = 0.02,
) -> dict[str, float | int]:
    """Absolute trajectory error like TUM's ``evaluate_ate.py`` (metres).

    Associates ground truth (first) and estimate (second) within ``max_diff`` seconds, aligns
    the estimated positions onto the ground truth with :func:`horn_align` (rigid, no scale)
    and returns statistics of the translation error norms: ``rmse``, ``mean``, ``median``,
    ``std``, ``min``, ``max`` and ``n`` (associated pairs). ValueError if fewer than 3 pairs.
    """
    al = align_trajectory(gt_t, gt_poses7, est_t, est_poses7, max_diff=max_diff)
    return {**_stats(al.error), "n": int(al.pairs.shape[0])}


def rpe(
    gt_t: np.ndarray,
    gt_poses7: np.ndarray,
    est_t: np.ndarray,
    est_poses7: np.ndarray,
    delta: float = 1.0,
    max_diff: float = 0.02,
) -> dict[str, float | int]:
    """Relative pose error over a fixed interval ``delta`` (seconds), per second.

    Only estimated poses associated to ground truth (within ``max_diff``, as for the ATE) are
    used. For each such pose i, j is the associated estimated pose whose timestamp is nearest
    to ``t_i + delta``; pairs with ``t_j - t_i < delta / 2`` are skipped. With
    E = (G_i^-1 G_j)^-1 (P_i^-1 P_j), returns ``trans_rmse_m_per_s`` (RMSE of
    ``|trans(E)| / (t_j - t_i)``), ``rot_rmse_deg_per_s`` (RMSE of ``angle(E) / (t_j - t_i)``
    in degrees) and ``n`` (pairs). If no pair exists (e.g. the overlap is shorter than
    ``delta / 2``), returns ``n = 0`` and NaN for both errors.
    """
    if not (math.isfinite(delta) and delta > 0):
        raise ValueError(f"delta must be positive and finite, got {delta}")
    gt_ts, gt_ps = _trajectory("ground truth", gt_t, gt_poses7)
    est_ts, est_ps = _trajectory("estimate", est_t, est_poses7)
    pairs = associate_timestamps(gt_ts, est_ts, max_diff)
    nan = {"trans_rmse_m_per_s": math.nan, "rot_rmse_deg_per_s": math.nan, "n": 0}
    if pairs.shape[0] < 2:
        return nan
    pairs = pairs[np.argsort(est_ts[pairs[:, 1]], kind="stable")]
    ts = est_ts[pairs[:, 1]]
    g = poses7_to_matrices(gt_ps[pairs[:, 0]])
    p = poses7_to_matrices(est_ps[pairs[:, 1]])
    # Nearest associated estimate timestamp to t_i + delta.
    target = ts + delta
    k = np.clip(np.searchsorted(ts, target), 1, ts.size - 1)
    j = np.where(np.abs(ts[k - 1] - target) <= np.abs(ts[k] - target), k - 1, k)
    i = np.arange(ts.size)
    dt = ts[j] - ts[i]
    ok = dt >= 0.5 * delta
    if not np.any(ok):
        return nan
    i, j, dt = i[ok], j[ok], dt[ok]
    rel_gt = inverse_np(g[i]) @ g[j]
    rel_est = inverse_np(p[i]) @ p[j]
    e = inverse_np(rel_gt) @ rel_est
    trans = np.linalg.norm(e[:, :3, 3], axis=-1) / dt
    rot = np.degrees(rotation_angle_np(e)) / dt
    return {
        "trans_rmse_m_per_s": float(np.sqrt(np.mean(trans * trans))),
        "rot_rmse_deg_per_s": float(np.sqrt(np.mean(rot * rot))),
        "n": int(i.size),
    }
