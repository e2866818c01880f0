"""Where does a run's drift come from? Per-frame errors against the ground truth beside what
could explain them.

Usage::

    python scripts/error_anatomy.py SEQ [--frame-step K] [--seed S] [--set KEY=VALUE ...]
                                    [--out-json FILE] [--out-png FILE]

SEQ is any source ``edgevo run`` takes that has ground truth (a TUM or ETH3D folder; a bag
with ``--groundtruth``). The sequence is tracked once (``run_sequence``, the default
``Config`` with ``--set`` overrides) and every frame is compared with the ground truth
interpolated at its timestamp (``groundtruth_pose_at(..., interpolate=True)``: at 75 deg/s
the nearest 100 Hz sample alone is up to 0.4 degrees off). Per frame:

- errors, rotation (degrees) and translation (cm) apart: ``kf`` of the pose relative to the
  keyframe it was tracked against (what one alignment gets wrong), ``step`` of the motion
  from the previous frame, and ``drift``, the pose against the ground truth with the first
  poses made equal (what the errors add up to; ATE aligns the whole trajectory instead);
- beside them: the camera's rotation speed (deg/s, from the ground truth) at the frame and at
  its keyframe and the speed difference between the two (a rolling-shutter camera distorts
  each image by its own speed), image sharpness (variance of the Laplacian of the gray
  image: lower is blurrier), edges detected and edges kept (level-0 inliers), the inlier share,
  keyframe or not and the keyframe's age (frames, seconds), the window's correction of the
  keyframe taken at this frame (cm, degrees), and the rgb-depth time offset (ms).

Writes JSON (the per-frame table, Spearman correlations of the keyframe error with each
variable, the error binned by the frame's and the keyframe's speeds) and a figure; prints a
summary.
"""

from __future__ import annotations

import argparse
import json
import math
import shlex
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from edgevo_jax import Config, enable_batch_exact
from edgevo_jax.datasets import groundtruth_pose_at
from edgevo_jax.datasets.source import open_source
from edgevo_jax.geometry import inverse_np, log_np, rotation_angle_np
from edgevo_jax.io import json_safe, matrices_to_poses7, poses7_to_matrices
from edgevo_jax.metrics import ate
from edgevo_jax.provenance import machine_info

#: time step of the central difference that gives the ground truth's rotation speed (s)
SPEED_STEP_S = 0.01
#: frame- and keyframe-speed bins of the summary (deg/s)
SPEED_BINS = (0.0, 30.0, 60.0, 90.0, math.inf)
EXPLAINERS = ("speed_deg_s", "keyframe_speed_deg_s", "speed_difference_deg_s", "sharpness",
              "edges", "inliers", "inlier_share", "keyframe_age_frames",
              "depth_offset_ms")


def gt_pose(seq: Any, t: float) -> np.ndarray | None:
    """Ground-truth T_world_cam (4, 4) interpolated at ``t``; None outside its span."""
    p = groundtruth_pose_at(seq, t, interpolate=True)
    return None if p is None else poses7_to_matrices(np.asarray(p)[None])[0]


def body_rate(seq: Any, t: float, h: float = SPEED_STEP_S) -> np.ndarray | None:
    """The camera's angular velocity (rad/s, (3,), camera frame) at ``t`` from the ground
    truth: log(T(t - h)^-1 T(t + h)) / 2h; None where the ground truth does not cover it."""
    a, b = gt_pose(seq, t - h), gt_pose(seq, t + h)
    if a is None or b is None:
        return None
    return log_np(inverse_np(a) @ b)[3:] / (2 * h)


def pose_error(est: np.ndarray, gt: np.ndarray) -> tuple[float, float]:
    """(degrees, cm) of E = gt^-1 est for two relative poses (4, 4)."""
    E = inverse_np(gt) @ est
    return float(np.degrees(rotation_angle_np(E))), float(100 * np.linalg.norm(E[:3, 3]))


def spearman(x: np.ndarray, y: np.ndarray) -> float:
    """Spearman's rank correlation over the pairs where both are finite (NaN with < 3)."""
    ok = np.isfinite(x) & np.isfinite(y)
    if ok.sum() < 3:
        return math.nan
    rx = np.argsort(np.argsort(x[ok])).astype(float)
    ry = np.argsort(np.argsort(y[ok])).astype(float)
    if rx.std() == 0 or ry.std() == 0:
        return math.nan
    return float(np.corrcoef(rx, ry)[0, 1])


def record(seq: Any, config: Config) -> tuple[list[dict[str, Any]], Any]:
    """Track ``seq`` and return one dict per frame (module doc) and the run."""
    import cv2

    from edgevo_jax.pipeline.run import run_sequence

    seen: list[dict[str, Any]] = []
    refinements: list = []

    def on_frame(result, rgb, frame, odo) -> None:
        kf = odo.keyframe
        gray = frame.gray if frame.gray is not None else cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
        seen.append({"keyframe_t": None if kf is None else kf[0],
                     "keyframe_pose": None if kf is None else kf[1],
                     "edges": frame.num_edges,
                     "sharpness": float(cv2.Laplacian(gray, cv2.CV_64F).var())})
        refinements[:] = odo.refinements

    run = run_sequence(seq, config, progress=False, on_frame=on_frame)
    ts, poses = run.timestamps, run.poses
    index = {float(t): i for i, t in enumerate(ts)}
    depth_t = getattr(seq, "depth_timestamps", None)
    corrections: dict[int, list[tuple[float, float]]] = {}
    for r in refinements:
        deg, cm = pose_error(r.after, r.before)
        corrections.setdefault(r.frame_index, []).append((cm, deg))
    rows = []
    for i, (res, info) in enumerate(zip(run.results, seen, strict=True)):
        t = float(ts[i])
        g = gt_pose(seq, t)
        k = index.get(float(info["keyframe_t"])) if info["keyframe_t"] is not None else None
        w, wk = body_rate(seq, t), (body_rate(seq, float(ts[k])) if k is not None else None)
        row: dict[str, Any] = {
            "frame": i, "timestamp": t, "state": res.state, "reason": res.reason,
            "keyframe": res.keyframe, "keyframe_index": k,
            "keyframe_age_frames": None if k is None else i - k,
            "keyframe_age_s": None if k is None else t - float(ts[k]),
            "edges": info["edges"], "inliers": res.inliers, "inlier_share": res.inlier_share,
            "sharpness": info["sharpness"],
            "speed_deg_s": None if w is None else float(np.degrees(np.linalg.norm(w))),
            "keyframe_speed_deg_s": None if wk is None
            else float(np.degrees(np.linalg.norm(wk))),
            "speed_difference_deg_s": None if w is None or wk is None
            else float(np.degrees(np.linalg.norm(w - wk))),
            "depth_offset_ms": None if depth_t is None else float(1e3 * (depth_t[i] - t)),
            "window_correction_cm": sum(c for c, _ in corrections.get(i, [])) or None,
            "window_correction_deg": sum(d for _, d in corrections.get(i, [])) or None,
        }
        gk = gt_pose(seq, float(ts[k])) if k is not None else None
        if g is not None and gk is not None and k != i:
            rel_est = inverse_np(info["keyframe_pose"]) @ poses[i]
            row["kf_err_deg"], row["kf_err_cm"] = pose_error(rel_est, inverse_np(gk) @ g)
        gp = gt_pose(seq, float(ts[i - 1])) if i > 0 else None
        if g is not None and gp is not None:
            row["step_err_deg"], row["step_err_cm"] = pose_error(
                inverse_np(poses[i - 1]) @ poses[i], inverse_np(gp) @ g)
        rows.append(row)
    g0 = gt_pose(seq, float(ts[0]))
    if g0 is not None:
        align = g0 @ inverse_np(poses[0])
        for row, p in zip(rows, poses, strict=True):
            g = gt_pose(seq, row["timestamp"])
            if g is not None:
                row["drift_deg"], row["drift_cm"] = pose_error(align @ p, g)
    return rows, run


def column(rows: Sequence[dict[str, Any]], key: str) -> np.ndarray:
    """One field of every row as floats (NaN where missing)."""
    return np.array([np.nan if r.get(key) is None else float(r[key]) for r in rows])


def summarise(rows: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """Correlations of the keyframe errors with each explaining variable, and the keyframe
    errors binned by the frame's and the keyframe's rotation speeds."""
    out: dict[str, Any] = {"spearman_kf_err_cm": {}, "spearman_kf_err_deg": {}}
    for target in ("kf_err_cm", "kf_err_deg"):
        y = column(rows, target)
        for key in EXPLAINERS:
            out[f"spearman_{target}"][key] = spearman(column(rows, key), y)
    y_cm, y_deg = column(rows, "kf_err_cm"), column(rows, "kf_err_deg")
    bins = []
    for key in ("speed_deg_s", "keyframe_speed_deg_s"):
        x = column(rows, key)
        for lo, hi in zip(SPEED_BINS[:-1], SPEED_BINS[1:], strict=True):
            m = (x >= lo) & (x < hi) & np.isfinite(y_cm)
            if m.any():
                bins.append({"by": key, "low": lo, "high": hi, "frames": int(m.sum()),
                             "kf_err_cm_median": float(np.median(y_cm[m])),
                             "kf_err_cm_mean": float(np.mean(y_cm[m])),
                             "kf_err_deg_median": float(np.median(y_deg[m]))})
    out["binned"] = bins
    for key in ("kf_err_cm", "kf_err_deg", "step_err_cm", "step_err_deg"):
        v = column(rows, key)
        v = v[np.isfinite(v)]
        out[f"{key}_median"] = float(np.median(v)) if v.size else math.nan
    return out


def plot(rows: Sequence[dict[str, Any]], title: str, path: Path) -> Path | None:
    """Five panels over the frames: drift, keyframe errors (keyframes marked), rotation
    speeds, sharpness and inlier share, the window's corrections; None without matplotlib."""
    from edgevo_jax.viz._canvas import figure, require_matplotlib, save

    try:
        require_matplotlib()
    except ImportError as err:
        print(f"note: no plot ({err})", flush=True)
        return None
    i = column(rows, "frame")
    fig = figure((11, 12), layout="constrained")
    ax = fig.subplots(5, 1, sharex=True)
    ax[0].plot(i, column(rows, "drift_cm"), label="translation (cm)")
    ax[0].plot(i, column(rows, "drift_deg"), label="rotation (deg)")
    ax[0].set(title=f"{title}: drift (first poses made equal)", ylabel="error")
    ax[1].plot(i, column(rows, "kf_err_cm"), label="translation (cm)")
    ax[1].plot(i, column(rows, "kf_err_deg"), label="rotation (deg)")
    kf = np.array([r["keyframe"] is not None for r in rows])
    ax[1].plot(i[kf], np.zeros(kf.sum()), "k|", markersize=10, label="keyframe")
    bad = np.array([r["state"] != "OK" for r in rows])
    ax[1].plot(i[bad], np.zeros(bad.sum()), "rx", label="WEAK / LOST")
    ax[1].set(title="error of the pose relative to its keyframe", ylabel="error")
    ax[2].plot(i, column(rows, "speed_deg_s"), label="frame")
    ax[2].plot(i, column(rows, "keyframe_speed_deg_s"), label="its keyframe")
    ax[2].plot(i, column(rows, "speed_difference_deg_s"), label="difference (vector)")
    ax[2].set(title="rotation speed (ground truth)", ylabel="deg/s")
    ax[3].plot(i, column(rows, "inlier_share"), label="inlier share")
    sharp = column(rows, "sharpness")
    ax[3].plot(i, sharp / np.nanmax(sharp), label="sharpness (Laplacian variance / max)")
    ax[3].set(title="what the tracker saw", ylabel="ratio")
    ax[4].plot(i, column(rows, "window_correction_cm"), "o", label="translation (cm)")
    ax[4].plot(i, column(rows, "window_correction_deg"), "s", label="rotation (deg)")
    ax[4].set(title="the window's keyframe corrections, where taken", xlabel="frame",
              ylabel="correction")
    for a in ax:
        a.grid(alpha=0.3)
        a.legend(fontsize=8, loc="upper left")
    return save(fig, path)


def main(argv: Sequence[str] | None = None) -> int:
    """Track, write JSON and PNG, print the summary."""
    argv = list(sys.argv[1:] if argv is None else argv)
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("sequence", help="a source with ground truth (TUM or ETH3D folder, bag)")
    p.add_argument("--frame-step", type=int, default=1, help="keep every K-th rgb/depth line")
    p.add_argument("--groundtruth", default=None, help="bags: a TUM trajectory file")
    p.add_argument("--seed", type=int, default=0, help="the edge selection's seed")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a Config field (repeatable)")
    p.add_argument("--out-json", type=Path, default=Path("error_anatomy.json"))
    p.add_argument("--out-png", type=Path, default=Path("error_anatomy.png"))
    args = p.parse_args(argv)
    enable_batch_exact()
    seq = open_source(args.sequence, frame_step=args.frame_step, groundtruth=args.groundtruth)
    if seq.groundtruth is None:
        raise SystemExit(f"{args.sequence}: no ground truth (a folder's groundtruth.txt, or "
                         "--groundtruth for a bag)")
    config = Config(seed=args.seed).with_overrides(args.set)
    rows, run = record(seq, config)
    summary = summarise(rows)
    summary["ate_rmse_m"] = float(ate(seq.groundtruth,
                                      (run.timestamps, matrices_to_poses7(run.poses)))["rmse"])
    summary["keyframes"] = run.num_keyframes
    result = {"command": shlex.join(["python", "scripts/error_anatomy.py", *argv]),
              "machine": machine_info(), "sequence": seq.name, "config_overrides": args.set,
              "summary": summary, "frames": rows}
    args.out_json.parent.mkdir(parents=True, exist_ok=True)
    args.out_json.write_text(json.dumps(json_safe(result), indent=1) + "\n")
    png = plot(rows, seq.name, args.out_png)
    print(f"{seq.name}: {len(rows)} frames, {run.num_keyframes} keyframes, "
          f"ATE {1e3 * summary['ate_rmse_m']:.1f} mm; median error to the keyframe "
          f"{summary['kf_err_cm_median']:.2f} cm {summary['kf_err_deg_median']:.2f} deg, "
          f"frame to frame {summary['step_err_cm_median']:.2f} cm "
          f"{summary['step_err_deg_median']:.2f} deg")
    print("Spearman correlation of the keyframe error (cm, deg) with:")
    for key in EXPLAINERS:
        print(f"  {key:24s} {summary['spearman_kf_err_cm'][key]:+.2f} "
              f"{summary['spearman_kf_err_deg'][key]:+.2f}")
    print("keyframe error (cm, median) by rotation speed:")
    for b in summary["binned"]:
        print(f"  {b['by']:22s} {b['low']:4.0f}-{b['high']:<4.0f} deg/s: {b['frames']:3d} "
              f"frames, {b['kf_err_cm_median']:.2f} cm, {b['kf_err_deg_median']:.2f} deg")
    print(f"wrote {args.out_json}" + (f", {png}" if png else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())
