"""Trajectory metrics (host side, numpy float64): the absolute and relative pose errors as evo
computes them (``evo_ape`` / ``evo_rpe``, Grupp 2017), and the TUM RGB-D benchmark's drift
per second that the run summaries report.

Every metric takes the ground truth and the estimate as TUM trajectories: a
``(timestamps (N,) s, poses7 (N, 7))`` pair (``tx ty tz qx qy qz qw`` of T_world_cam, metres,
each trajectory in its own world frame; what ``io.read_trajectory`` returns) or the path of a
TUM trajectory file. Poses are associated by time as TUM's ``associate.py`` does
(:func:`associate_timestamps`: greedy, one to one, ``|t_gt - (t_est + offset)| < max_diff``).
evo matches each pose of the shorter trajectory to the nearest pose of the longer one within
``max_diff`` (``<=``; a pose may be matched twice); the two pick the same pairs whenever each
pose's nearest partner inside the window is unique to it, as with a 100 Hz ground truth and a
30 Hz camera. ``max_diff`` defaults to TUM's 0.02 s (``evo_ape``'s ``--t_max_diff`` defaults
to 0.01 s).
"""

from __future__ import annotations

import math
import os
from typing import NamedTuple

import numpy as np

from .geometry import inverse_np, rotation_angle_np
from .io import poses7_to_matrices, read_trajectory

__all__ = ["ALIGNMENTS", "DELTA_UNITS", "TrajectoryAlignment", "align_trajectory",
           "associate_timestamps", "ate", "horn_align", "rpe", "rpe_per_second", "umeyama"]

ALIGNMENTS = ("se3", "sim3", "origin", "none")
DELTA_UNITS = ("frames", "seconds", "metres")

Trajectory = tuple[np.ndarray, np.ndarray]
TrajectoryLike = Trajectory | str | os.PathLike


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


def _as_trajectory(name: str, value: TrajectoryLike) -> tuple[np.ndarray, np.ndarray]:
    """(timestamps, poses7) of a TUM trajectory given as a pair or as a file path."""
    if isinstance(value, str | os.PathLike):
        return read_trajectory(value)
    try:
        t, poses7 = value
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a (timestamps, poses7) pair or the path of a TUM "
                         f"trajectory file, got {type(value).__name__}") from None
    return _trajectory(name, t, poses7)


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


def umeyama(model: np.ndarray, data: np.ndarray, *,
            with_scale: bool = False) -> tuple[np.ndarray, np.ndarray, float]:
    """Least-squares similarity: R (3, 3), t (3,), s with s R @ model + t ~= data.

    model, data: (3, N) with N >= 3. Umeyama (1991) through the SVD of the cross-covariance,
    with the reflection fix (TUM's ``align()``, evo's ``umeyama_alignment``); ``s`` is 1.0
    unless ``with_scale``. ValueError for fewer than 3 points, non-finite points, or (with
    scale) a model whose points all coincide.
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
    mc = m - mu_m[:, None]
    w = (d - mu_d[:, None]) @ mc.T  # sum_k data_k model_k^T
    u, sv, vh = np.linalg.svd(w)
    s = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vh) < 0:
        s[2, 2] = -1.0
    r = u @ s @ vh
    scale = 1.0
    if with_scale:
        spread = float(np.sum(mc * mc))
        if spread == 0.0:
            raise ValueError("a scaled alignment needs model points that do not all coincide")
        scale = float(np.sum(sv * np.diag(s)) / spread)
    return r, mu_d - scale * r @ mu_m, scale


def horn_align(model: np.ndarray, data: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rigid (no scale) least-squares alignment: R (3, 3), t (3,) with R @ model + t ~= data.

    model, data: (3, N) with N >= 3: :func:`umeyama` without scale (Horn's closed form, as
    TUM's ``align()``).
    """
    r, t, _ = umeyama(model, data)
    return r, t


def _stats(err: np.ndarray, prefix: str = "") -> dict[str, float]:
    if err.size == 0:
        return {prefix + k: math.nan for k in ("rmse", "mean", "median", "std", "min", "max")}
    return {
        prefix + "rmse": float(np.sqrt(np.mean(err * err))),
        prefix + "mean": float(np.mean(err)),
        prefix + "median": float(np.median(err)),
        prefix + "std": float(np.std(err)),
        prefix + "min": float(np.min(err)),
        prefix + "max": float(np.max(err)),
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
    ``evaluate_ate.py`` does (the alignment ``ate(..., align="se3")`` measures).

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


def _check_option(name: str, value: str, choices: tuple[str, ...]) -> None:
    if value not in choices:
        raise ValueError(f"{name} must be one of {', '.join(choices)}, got {value!r}")


def _associated(groundtruth: TrajectoryLike, estimate: TrajectoryLike, max_diff: float,
                offset: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Associated poses in the estimate's time order: ground truth G (K, 4, 4), estimate
    P (K, 4, 4), the estimate's timestamps (K,) s."""
    gt_t, gt_p = _as_trajectory("groundtruth", groundtruth)
    est_t, est_p = _as_trajectory("estimate", estimate)
    pairs = associate_timestamps(gt_t, est_t, max_diff, offset)
    pairs = pairs[np.argsort(est_t[pairs[:, 1]], kind="stable")]
    return (poses7_to_matrices(gt_p[pairs[:, 0]]), poses7_to_matrices(est_p[pairs[:, 1]]),
            est_t[pairs[:, 1]])


def _aligned(G: np.ndarray, P: np.ndarray, align: str) -> tuple[np.ndarray, float]:
    """The estimate P (K, 4, 4) moved into the ground truth's world frame by ``align``, and
    the scale applied (1.0 but for sim3)."""
    if align == "none":
        return P, 1.0
    if align == "origin":  # evo's align_origin: the first poses made equal
        return G[0] @ inverse_np(P[0]) @ P, 1.0
    r, t, s = umeyama(P[:, :3, 3].T, G[:, :3, 3].T, with_scale=align == "sim3")
    out = P.copy()
    out[:, :3, :3] = r @ P[:, :3, :3]
    out[:, :3, 3] = (s * P[:, :3, 3]) @ r.T + t
    return out, s


def _enough(what: str, align: str, k: int, least: int, max_diff: float, offset: float) -> None:
    """ValueError unless k associated poses are enough for ``what`` aligned by ``align`` (the
    Umeyama alignments need 3 points)."""
    need = max(least, 3 if align in ("se3", "sim3") else 0)
    if k < need:
        raise ValueError(
            f"{what} with align={align!r} needs at least {need} associated poses, got {k} "
            f"(max_diff {max_diff} s, offset {offset} s): do the timestamps overlap?")


def ate(groundtruth: TrajectoryLike, estimate: TrajectoryLike, *, align: str = "se3",
        max_diff: float = 0.02, offset: float = 0.0) -> dict[str, float | int]:
    """Absolute trajectory error: evo's APE of the translation part, in metres.

    ``groundtruth``, ``estimate``: TUM trajectories, ``(timestamps (N,) s, poses7 (N, 7))`` or
    a file path (the module doc). Poses are associated within ``max_diff`` seconds after
    ``offset`` seconds are added to the estimate's timestamps (evo's ``--t_max_diff``,
    ``--t_offset``); the estimate is then aligned onto the ground truth by ``align``:

    - ``"se3"``: rigid Umeyama alignment of the associated positions (TUM's ATE,
      ``evaluate_ate.py``; ``evo_ape -a``),
    - ``"sim3"``: the same with scale (``evo_ape -as``),
    - ``"origin"``: the first associated poses made equal (``evo_ape --align_origin``),
    - ``"none"``: both in one world frame already (``evo_ape``'s default).

    Returns statistics of the per-pose position errors |p_est - p_gt| (m), evo's names:
    ``rmse``, ``mean``, ``median``, ``std``, ``min``, ``max``; ``n`` (associated pairs) and
    ``scale`` (the sim3 scale applied to the estimate; 1.0 otherwise). ValueError when fewer
    than 3 poses associate (se3 / sim3; 1 for origin / none).
    """
    _check_option("align", align, ALIGNMENTS)
    G, P, _ = _associated(groundtruth, estimate, max_diff, offset)
    _enough("ATE", align, G.shape[0], 1, max_diff, offset)
    A, s = _aligned(G, P, align)
    err = np.linalg.norm(A[:, :3, 3] - G[:, :3, 3], axis=-1)
    return {**_stats(err), "n": int(err.size), "scale": s}


def _pairs_by_distance(d: np.ndarray, delta: float, tol: float,
                       all_pairs: bool) -> list[tuple[int, int]]:
    """evo's pair filters on a monotone distance d (K,) along the trajectory (path length or
    time): consecutive pairs, each the first pose at least ``delta`` on from the last; or,
    with ``all_pairs``, for every pose the later pose nearest ``delta`` on, within ``tol``."""
    if all_pairs:
        pairs = []
        for i in range(d.size - 1):
            ahead = d[i + 1:] - d[i]
            k = int(np.argmin(np.abs(ahead - delta)))
            if abs(ahead[k] - delta) <= tol:
                pairs.append((i, i + 1 + k))
        return pairs
    ids = [0]
    for i in range(1, d.size):
        if d[i] - d[ids[-1]] >= delta:
            ids.append(i)
    return list(zip(ids, ids[1:], strict=False))


def _path_pairs(xyz: np.ndarray, delta: float, tol: float,
                all_pairs: bool) -> list[tuple[int, int]]:
    """evo's ``filter_pairs_by_path`` on positions (K, 3), with its float summation order."""
    steps = np.linalg.norm(xyz[1:] - xyz[:-1], axis=1)
    if all_pairs:
        return _pairs_by_distance(np.concatenate([[0.0], np.cumsum(steps)]), delta, tol, True)
    ids, path = [0], 0.0
    for i, step in enumerate(steps.tolist(), start=1):
        path += step
        if path >= delta:
            ids.append(i)
            path = 0.0
    return list(zip(ids, ids[1:], strict=False))


def rpe(groundtruth: TrajectoryLike, estimate: TrajectoryLike, *, delta: float = 1.0,
        unit: str = "frames", align: str = "none", max_diff: float = 0.02, offset: float = 0.0,
        all_pairs: bool = False, delta_tol: float = 0.1) -> dict[str, float | int]:
    """Relative pose error: evo's RPE, translation (m) and rotation angle (degrees).

    ``groundtruth``, ``estimate``, ``max_diff``, ``offset`` and ``align`` as for :func:`ate`
    (the associated estimate is aligned first: only ``"sim3"`` changes an RPE, by scaling the
    estimate's translations). Pose pairs (i, j) are taken among the associated poses, in the
    estimate's time order, ``delta`` apart in ``unit``:

    - ``"frames"``: j = i + delta associated poses (delta a positive integer; evo's ``f``),
    - ``"metres"``: the estimate's path length from i to j (evo's ``m``),
    - ``"seconds"``: the estimate's time from i to j (not in evo: its ``m`` rule with time in
      place of path length; TUM's ``evaluate_rpe.py --delta_unit s`` has all pairs).

    Consecutive pairs by default (each j the first pose at least delta on from the last
    pair's, evo's default); ``all_pairs``: every i with the j nearest delta on (frames:
    exactly), kept when within ``delta_tol * delta`` of it (evo's ``--all_pairs``,
    ``--delta_tol``). With E = (G_i^-1 G_j)^-1 (P_i^-1 P_j), returns the statistics of
    |trans(E)| in metres (``rmse``, ``mean``, ``median``, ``std``, ``min``, ``max``: evo's
    ``--pose_relation trans_part``), of angle(E) in degrees (the same names prefixed ``rot_``:
    evo's ``angle_deg``), ``n`` (pairs) and ``scale`` (as :func:`ate`). Errors are per pair,
    not per second (:func:`rpe_per_second` is). No pair (a trajectory shorter than delta, or
    no pose associated): ``n`` 0 and NaN statistics; ValueError when 1 or 2 poses associate
    and ``align`` is se3 or sim3.
    """
    _check_option("unit", unit, DELTA_UNITS)
    _check_option("align", align, ALIGNMENTS)
    if not (math.isfinite(delta) and delta > 0):
        raise ValueError(f"delta must be positive and finite, got {delta}")
    if unit == "frames" and delta != int(delta):
        raise ValueError(f"delta must be a whole number of frames with unit='frames', "
                         f"got {delta}")
    if not (math.isfinite(delta_tol) and delta_tol >= 0):
        raise ValueError(f"delta_tol must be >= 0 and finite, got {delta_tol}")
    G, P, ts = _associated(groundtruth, estimate, max_diff, offset)
    k = G.shape[0]
    s = 1.0
    if align != "none" and k:
        _enough("RPE", align, k, 0, max_diff, offset)
        P, s = _aligned(G, P, align)
    if unit == "frames":
        step = int(delta)
        ids = np.arange(k) if all_pairs else np.arange(0, k, step)
        pairs = ([(int(i), int(i) + step) for i in ids if i + step < k] if all_pairs
                 else list(zip(ids.tolist(), ids[1:].tolist(), strict=False)))
    elif unit == "metres":
        pairs = _path_pairs(P[:, :3, 3], delta, delta * delta_tol, all_pairs) if k else []
    else:
        pairs = _pairs_by_distance(ts, delta, delta * delta_tol, all_pairs) if k else []
    if not pairs:
        return {**_stats(np.zeros(0)), **_stats(np.zeros(0), "rot_"), "n": 0, "scale": s}
    i, j = np.asarray(pairs).T
    e = _relative_error(G[i], G[j], P[i], P[j])
    trans = np.linalg.norm(e[:, :3, 3], axis=-1)
    rot = np.degrees(rotation_angle_np(e))
    return {**_stats(trans), **_stats(rot, "rot_"), "n": int(i.size), "scale": s}


def _relative_error(g_i: np.ndarray, g_j: np.ndarray, p_i: np.ndarray,
                    p_j: np.ndarray) -> np.ndarray:
    """E = (G_i^-1 G_j)^-1 (P_i^-1 P_j) (..., 4, 4): the estimate's motion from i to j seen
    from the ground truth's (Sturm et al. 2012; evo's ``rpe_base``)."""
    return inverse_np(inverse_np(g_i) @ g_j) @ (inverse_np(p_i) @ p_j)


def rpe_per_second(groundtruth: TrajectoryLike, estimate: TrajectoryLike, *,
                   delta: float = 1.0, max_diff: float = 0.02) -> dict[str, float | int]:
    """Drift per second over ``delta`` seconds, as the TUM benchmark's online evaluation
    reports its RPE (m/s, deg/s); the run summaries' ``rpe_rmse_m_per_s``.

    Trajectories and ``max_diff`` as for :func:`ate`. For every associated estimated pose
    i, j is the associated pose whose timestamp is nearest to ``t_i + delta``; pairs with
    ``t_j - t_i < delta / 2`` are skipped. With E as in :func:`rpe`, returns
    ``trans_rmse_m_per_s`` (RMSE of ``|trans(E)| / (t_j - t_i)``), ``rot_rmse_deg_per_s``
    (RMSE of ``angle(E) / (t_j - t_i)`` in degrees) and ``n`` (pairs). No pair (e.g. an
    overlap shorter than ``delta / 2``): ``n`` 0 and NaN for both.
    """
    if not (math.isfinite(delta) and delta > 0):
        raise ValueError(f"delta must be positive and finite, got {delta}")
    g, p, ts = _associated(groundtruth, estimate, max_diff, 0.0)
    nan = {"trans_rmse_m_per_s": math.nan, "rot_rmse_deg_per_s": math.nan, "n": 0}
    if ts.size < 2:
        return nan
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
    e = _relative_error(g[i], g[j], p[i], p[j])
    trans = np.linalg.norm(e[:, :3, 3], axis=-1) / dt
    rot = np.degrees(rotation_angle_np(e)) / dt
    return {
        "trans_rmse_m_per_s": float(np.sqrt(np.mean(trans * trans))),
        "rot_rmse_deg_per_s": float(np.sqrt(np.mean(rot * rot))),
        "n": int(i.size),
    }
