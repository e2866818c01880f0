"""Robustness of tracking to the frame rate: a measuring stick for issue 19.

Usage::

    python scripts/robustness_bench.py [SEQ_DIR ...] [--steps 1,2,3,5] [--seeds 0-4]
                                       [--peers cv2_rgb,cv2_rgbd] [--max-frames N]
                                       [--set KEY=VALUE ...]
                                       [--out-json docs/robustness/robustness.json]
                                       [--out-md docs/robustness/robustness.md]
                                       [--out-png docs/robustness/robustness.png]

For every sequence (default: fr3_teddy's first 200 frames) and frame step k, the sequence is
played at 1/k of its frame rate as the benchmark's lists would be recorded: every k-th line
of rgb.txt and of depth.txt, then associated (``load_sequence(..., frame_step=k)``; where the
lists have gaps, pairs drop out and the motion between tracked frames spans more than k
frames; ``--max-frames`` keeps the frames up to the full sequence's frame N) and tracked

- by edgevo_jax in this process (``run_sequence``, the default ``Config`` with the
  ``--set`` overrides but for the selection seed: one run per ``--seeds`` seed; the first
  run of the process is preceded by an untimed warm-up run on ``--warmup-frames`` frames,
  so that every timed run finds the tracker's and the window's programs compiled), and
- by each ``--peers`` method (``edgevo_jax.peers``, as in ``scripts/bench.py``: frame to
  frame from edgevo's first pose; deterministic, so one run per k).

Per run: ATE RMSE (m, ``metrics.ate``), RPE (``metrics.rpe_per_second`` over 1 s: m/s and
deg/s; null when the clip spans under 1 s), the frames per state (edgevo: OK / WEAK / LOST;
peers: a pair whose ``compute`` fails is LOST, every other frame OK), the **silently
diverged** frames (``measure.diverged_frames``) and the mean / median ms per frame over
warm frames (the first two skipped; image decoding excluded, as in bench.py). Per
(sequence, method, k) over the seeds: mean, min and max ATE and max / min. Writes JSON (with
machine information and the command line), a markdown table and a plot of ATE against the
frame step (skipped with a note when matplotlib is missing); prints one progress line per run
and the table.
"""

from __future__ import annotations

import argparse
import math
import os
import shlex
import sys
import warnings
from collections import Counter
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from edgevo_jax import Config, enable_batch_exact
from edgevo_jax.datasets.tum import SHARED_TUM, EmptyDepthWarning, TumSequence
from edgevo_jax.peers import PEERS, PeerMissing
from edgevo_jax.provenance import machine_info
from edgevo_jax.reports import fmt, int_list, markdown_table, write_json, write_text
from edgevo_jax.runs import measure
from edgevo_jax.runs.measure import (
    DIVERGED_ROT_DEG,
    DIVERGED_TRANS_M,
    GT_MAX_DIFF_S,
    WARMUP_FRAMES,
    accuracy,
    diverged_frames,
    finite_stats,
    frame_stats,
    groundtruth_at,
    load_clip,
)
from edgevo_jax.viz import plot_frame_rates, require_matplotlib

DEFAULT_SEQUENCE = SHARED_TUM / "rgbd_dataset_freiburg3_teddy_first200"
DEFAULT_OUT = Path("docs/robustness")
DEFAULT_PEERS = ("cv2_rgb", "cv2_rgbd")
EDGEVO = "edgevo"
STATES = ("OK", "WEAK", "LOST")
DIVERGED_NOTE = (
    "diverged: frames the method called OK, following a frame it also called OK, whose "
    f"motion from that frame differs from the ground truth's over the same timestamps by more "
    f"than {DIVERGED_TRANS_M * 100:.0f} cm or {DIVERGED_ROT_DEG:.0f} deg (ground truth nearest "
    f"within {GT_MAX_DIFF_S} s of each frame)"
)


def score_run(timestamps: np.ndarray, poses: np.ndarray, states: Sequence[str],
              frame_ms: Sequence[float], groundtruth: tuple[np.ndarray, np.ndarray] | None,
              gt_poses: np.ndarray) -> dict[str, Any]:
    """The measurements of one run (timestamps (N,), T_world_cam poses (N, 4, 4), states,
    per-frame ms) against the ground truth trajectory ``(gt_t, gt_poses7)`` and
    ``gt_poses`` at the frames (``measure.groundtruth_at``): ATE RMSE (m), RPE over 1 s
    (``measure.accuracy``), counts per state, the diverged frames
    (``measure.diverged_frames``) and the warm mean / median ms per frame (the first
    ``WARMUP_FRAMES`` frames skipped)."""
    counts = Counter(states)
    unknown = set(counts) - set(STATES)
    if unknown:
        raise ValueError(f"unknown states {sorted(unknown)} (expected {STATES})")
    div = diverged_frames(poses, states, gt_poses)
    acc = accuracy(groundtruth, timestamps, poses)
    warm = frame_stats(frame_ms)
    out: dict[str, Any] = {
        "frames": len(states),
        **{s.lower(): int(counts.get(s, 0)) for s in STATES},
        "diverged": len(div),
        "diverged_frames": div,
        **{k: acc[k] for k in ("ate_rmse_m", "rpe_m_per_s", "rpe_deg_per_s")},
        "mean_ms": warm["mean"], "median_ms": warm["median"],
    }
    if "accuracy_note" in acc:
        out["accuracy_note"] = acc["accuracy_note"]
    return out


def aggregate(runs: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """One row per (sequence, method, step) over its runs (the seeds): mean / min / max ATE,
    max / min, mean RPE, mean diverged / weak / lost frames per run and the median of the
    runs' median ms. Rows keep the order in which their first run appears; runs with
    ``missing`` set are skipped."""
    groups: dict[tuple[str, str, int], list[dict[str, Any]]] = {}
    for r in runs:
        if "missing" not in r:
            groups.setdefault((r["sequence"], r["method"], r["step"]), []).append(r)
    rows = []
    for (seq, method, step), rs in groups.items():
        ate = finite_stats([r["ate_rmse_m"] for r in rs])
        mean = {k: finite_stats([r[k] for r in rs])["mean"] for k in (
            "rpe_m_per_s", "rpe_deg_per_s", "diverged", "weak", "lost", "mean_ms")}
        rows.append({
            "sequence": seq, "method": method, "step": step, "runs": len(rs),
            "seeds": [r["seed"] for r in rs if r.get("seed") is not None],
            "frames": rs[0]["frames"],
            "ate_mean_m": ate["mean"], "ate_min_m": ate["min"], "ate_max_m": ate["max"],
            "ate_max_over_min": ate["max"] / ate["min"] if ate["min"] > 0 else math.nan,
            "rpe_m_per_s_mean": mean["rpe_m_per_s"],
            "rpe_deg_per_s_mean": mean["rpe_deg_per_s"],
            "diverged_mean": mean["diverged"], "diverged_max": max(r["diverged"] for r in rs),
            "weak_mean": mean["weak"], "lost_mean": mean["lost"],
            "median_ms": float(np.median([r["median_ms"] for r in rs])),
            "mean_ms": mean["mean_ms"],
        })
    return rows


TABLE_HEAD = ("sequence", "method", "step k", "frames", "runs", "ATE mean (mm)", "min", "max",
              "max/min", "RPE (mm/s)", "RPE (deg/s)", "diverged / run (max)", "weak / run",
              "lost / run", "ms median", "ms mean")


def table(rows: Sequence[dict[str, Any]]) -> str:
    """The aggregate rows as a markdown table."""
    return markdown_table(TABLE_HEAD, [[
        r["sequence"], r["method"], str(r["step"]), str(r["frames"]), str(r["runs"]),
        fmt(1e3 * r["ate_mean_m"], ".2f"), fmt(1e3 * r["ate_min_m"], ".2f"),
        fmt(1e3 * r["ate_max_m"], ".2f"), fmt(r["ate_max_over_min"], ".2f"),
        fmt(1e3 * r["rpe_m_per_s_mean"], ".1f"), fmt(r["rpe_deg_per_s_mean"], ".2f"),
        f"{fmt(r['diverged_mean'], '.1f')} ({r['diverged_max']})",
        fmt(r["weak_mean"], ".1f"), fmt(r["lost_mean"], ".1f"),
        fmt(r["median_ms"], ".1f"), fmt(r["mean_ms"], ".1f")] for r in rows])


# --------------------------------------------------------------------------------------------
# running (the tracker and the peers)


def run_peer(method: str, seq: TumSequence) -> dict[str, Any]:
    """Track ``seq`` with the peer ``method`` (``measure.run_peer``); frame 0 and every frame
    with a usable motion are OK, the others LOST (their pose repeats the previous motion).
    Returns the scored run, or ``{"missing": reason}``."""
    try:
        track = measure.run_peer(method, seq)
    except PeerMissing as err:
        return {"missing": str(err)}
    ts = np.asarray(seq.timestamps, np.float64)
    poses = np.asarray(track.poses).reshape(-1, 4, 4)
    out = score_run(ts, poses, track.states, track.frame_ms, seq.groundtruth,
                    groundtruth_at(seq, ts))
    out["api"] = track.description
    if track.failures:
        out["failures"] = track.failures
    return out


def run_edgevo(seq: TumSequence, seed: int, base: Config | None = None) -> dict[str, Any]:
    """Track ``seq`` with edgevo_jax, ``base`` (default ``Config()``) with the selection
    seed ``seed``; the scored run plus keyframes."""
    from edgevo_jax.runs.run import run_sequence

    config = (base or Config()).replace(seed=seed)
    with warnings.catch_warnings():  # a depthless frame is a WEAK frame, not a failure
        warnings.simplefilter("ignore", EmptyDepthWarning)
        run = run_sequence(seq, config, progress=False)
    states = [r.state for r in run.results]
    out = score_run(run.timestamps, run.poses, states, run.frame_ms, seq.groundtruth,
                    groundtruth_at(seq, run.timestamps))
    out["keyframes"] = int(run.num_keyframes)
    return out


def warm_up(seq: TumSequence, frames: int, base: Config | None = None) -> None:
    """An untimed edgevo run on the first ``frames`` frames, so that the timed runs find the
    programs compiled (the window's compile when it first fills and marginalises)."""
    from edgevo_jax.runs.run import run_sequence

    if frames > 0:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", EmptyDepthWarning)
            run_sequence(seq, base or Config(), progress=False, max_frames=frames)


def _progress(run: dict[str, Any]) -> str:
    if "missing" in run:
        return f"{run['sequence']} k={run['step']} {run['method']}: missing ({run['missing']})"
    seed = f" seed {run['seed']}" if run.get("seed") is not None else ""
    return (f"{run['sequence']} k={run['step']} {run['method']}{seed}: "
            f"ATE {fmt(1e3 * run['ate_rmse_m'], '.2f')} mm, {run['frames']} frames, "
            f"weak {run['weak']}, lost {run['lost']}, diverged {run['diverged']}, "
            f"{fmt(run['median_ms'], '.1f')} ms median")


def plot(rows: Sequence[dict[str, Any]], path: Path) -> Path | None:
    """``viz.plot_frame_rates`` of the aggregate rows; None (and a printed note) when
    matplotlib is missing."""
    try:
        require_matplotlib()
    except ImportError as err:
        print(f"note: no plot ({err})", flush=True)
        return None
    return plot_frame_rates(rows, path)


def run_all(seq_dirs: Sequence[Path], steps: Sequence[int], seeds: Sequence[int],
            peers: Sequence[str], max_frames: int | None, warmup_frames: int,
            config: Config | None = None) -> list[dict[str, Any]]:
    """Every run, in order: per sequence and step, edgevo per seed, then each peer. Prints a
    progress line per run."""
    runs: list[dict[str, Any]] = []
    warmed = False
    for seq_dir in seq_dirs:
        full = load_clip(seq_dir, max_frames=max_frames)
        if not warmed:
            warm_up(full, warmup_frames, config)
            warmed = True
        for k in steps:  # each over the same span of time as the full sequence's cut
            seq = load_clip(seq_dir, frame_step=k, max_frames=max_frames)
            base = {"sequence": full.name, "step": k, "path": str(seq_dir)}
            jobs: list[tuple[str, int | None]] = [(EDGEVO, s) for s in seeds]
            jobs += [(p, None) for p in peers]
            for method, seed in jobs:
                row = {**base, "method": method, "seed": seed}
                row.update(run_edgevo(seq, seed, config) if seed is not None
                           else run_peer(method, seq))
                print(_progress(row), flush=True)
                runs.append(row)
    return runs


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("sequences", nargs="*", type=Path, metavar="SEQ_DIR",
                   help=f"TUM sequence folders (default: {DEFAULT_SEQUENCE})")
    p.add_argument("--steps", default="1,2,3,5", help="frame steps k (default 1,2,3,5)")
    p.add_argument("--seeds", default="0-4", help="edgevo selection seeds (0-4 or 0,1,2)")
    p.add_argument("--peers", default=",".join(DEFAULT_PEERS),
                   help=f"peers (as bench.py's), comma-separated, '' for none ({', '.join(PEERS)})")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a Config field of edgevo's runs (repeatable)")
    p.add_argument("--max-frames", type=int, default=None,
                   help="cut each sequence to its first N frames before the sweep")
    p.add_argument("--warmup-frames", type=int, default=40,
                   help="frames of the untimed warm-up run (0: none; default 40)")
    p.add_argument("--out-json", type=Path, default=DEFAULT_OUT / "robustness.json")
    p.add_argument("--out-md", type=Path, default=DEFAULT_OUT / "robustness.md")
    p.add_argument("--out-png", type=Path, default=DEFAULT_OUT / "robustness.png")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Run the sweep, write JSON / markdown / PNG, print the table."""
    enable_batch_exact()  # before any JAX computation
    argv = list(sys.argv[1:] if argv is None else argv)
    args = _parser().parse_args(argv)
    steps = int_list(args.steps)
    if min(steps) < 1:
        raise SystemExit(f"--steps must be positive, got {args.steps!r}")
    seeds = int_list(args.seeds)
    peers = [p.strip() for p in args.peers.split(",") if p.strip()]
    seq_dirs = args.sequences or [DEFAULT_SEQUENCE]
    base = Config().with_overrides(args.set)
    runs = run_all(seq_dirs, steps, seeds, peers, args.max_frames, args.warmup_frames, base)
    rows = aggregate(runs)
    text = table(rows)
    command = shlex.join(["python", os.path.relpath(__file__), *argv])
    missing = {f"{r['method']}": r["missing"] for r in runs if "missing" in r}
    result = {
        "command": command, "machine": machine_info(), "steps": steps, "seeds": seeds,
        "peers": peers, "max_frames": args.max_frames, "warmup_frames": args.warmup_frames,
        "thresholds": {"diverged_trans_m": DIVERGED_TRANS_M, "diverged_rot_deg":
                       DIVERGED_ROT_DEG, "groundtruth_max_diff_s": GT_MAX_DIFF_S},
        "notes": [DIVERGED_NOTE, f"ms: warm frames (the first {WARMUP_FRAMES} skipped), image "
                  "decoding excluded; peers: a failed pair is a LOST frame"],
        "missing": missing, "aggregates": rows, "runs": runs,
    }
    write_json(args.out_json, result, indent=1)
    md = (f"# Robustness: frame-rate sweep\n\n`{command}`\n\n{text}\n\n{DIVERGED_NOTE}. "
          f"ms: warm frames, decoding excluded. Machine: {result['machine'].get('platform')}, "
          f"{result['machine'].get('cpus_usable')} CPUs, {result['machine'].get('date')}.\n")
    if missing:
        md += "".join(f"\nmissing: {m}: {why}" for m, why in missing.items()) + "\n"
    write_text(args.out_md, md)
    png = plot(rows, args.out_png)
    print(text)
    print(f"\nwrote {args.out_json}, {args.out_md}" + (f", {png}" if png else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())
