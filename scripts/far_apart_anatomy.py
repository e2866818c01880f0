"""Anatomy of far-apart frames: a clip at 1/k of its frame rate from every start offset,
frame by frame, against the ground truth (issue 38, part 1).

Usage::

    python scripts/far_apart_anatomy.py CLIP [--step 10] [--offsets 0-9] [--seeds 0-2]
                                        [--out-json FILE]

Sequence ``o`` is the clip's associated frames o, o + k, o + 2k, ... (``subsequence``).
Each runs with the default Config per seed. Per run: ATE against standing still (the first
pose held), and per frame: its state and reason, whether it was called OK while its motion
from the previous frame is off the ground truth's by more than 5 cm or 3 degrees
(``measure.diverged_frames``: silently wrong), its true motion from the previous frame
(degrees, cm) and its motion error, and whether it became a keyframe. Prints a line per
run, the silently wrong frames with their true motion, and how the frames that went wrong
are spread over the true motion; writes everything to JSON.
"""

from __future__ import annotations

import sys
from collections import Counter
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from edgevo_jax import Config, enable_batch_exact
from edgevo_jax.datasets.tum import load_sequence, subsequence
from edgevo_jax.geometry import inverse_np, rotation_angle_np
from edgevo_jax.reports import int_list, script_parser, script_record, write_json
from edgevo_jax.runs.measure import (
    accuracy,
    diverged_frames,
    groundtruth_at,
    motion_errors,
)
from edgevo_jax.runs.run import run_sequence


def true_motion(gt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per frame i >= 1 the ground truth's motion from frame i - 1: (degrees, metres)."""
    rel = inverse_np(gt[:-1]) @ gt[1:]
    return (np.degrees(np.asarray(rotation_angle_np(rel), np.float64).reshape(-1)),
            np.linalg.norm(rel[:, :3, 3], axis=-1))


def main(argv: Sequence[str] | None = None) -> int:
    """Run every offset and seed; print and write the anatomy."""
    argv = list(sys.argv[1:] if argv is None else argv)
    p = script_parser(__doc__, seeds="0-2")
    p.add_argument("clip", type=Path)
    p.add_argument("--step", type=int, default=10)
    p.add_argument("--offsets", type=int_list, default=None, help="default: 0 to step-1")
    p.add_argument("--out-json", type=Path, default=Path("far_apart_anatomy.json"))
    args = p.parse_args(argv)
    enable_batch_exact()
    full = load_sequence(args.clip)
    offsets = list(range(args.step)) if args.offsets is None else args.offsets
    runs = []
    for offset in offsets:
        seq = subsequence(full, offset, len(full), step=args.step)
        gt = groundtruth_at(seq, seq.timestamps)
        deg, metres = true_motion(gt)
        still = accuracy(seq.groundtruth, seq.timestamps,
                         np.repeat(np.eye(4)[None], len(seq), axis=0))["ate_rmse_m"]
        for seed in args.seeds:
            config = Config().with_overrides([*args.set, f"seed={seed}"])
            run = run_sequence(seq, config, progress=False)
            states = [r.state for r in run.results]
            ate = accuracy(seq.groundtruth, run.timestamps, run.poses)["ate_rmse_m"]
            wrong = diverged_frames(run.poses, states, gt)
            err_t, err_r = motion_errors(run.poses, gt)
            frames = [{"i": i, "state": r.state, "reason": r.reason, "placed": r.placed,
                       "keyframe": r.keyframe,
                       "true_deg": float(deg[i - 1]) if i else 0.0,
                       "true_m": float(metres[i - 1]) if i else 0.0,
                       "err_m": float(err_t[i - 1]) if i else 0.0,
                       "err_deg": float(err_r[i - 1]) if i else 0.0,
                       "silently_wrong": i in wrong}
                      for i, r in enumerate(run.results)]
            runs.append({"offset": offset, "seed": seed, "frames_n": len(seq), "ate_m": ate,
                         "standing_still_m": still, "silently_wrong": wrong,
                         "frames": frames})
            print(f"offset {offset} seed {seed}: ATE {1e3 * ate:7.1f} mm (still "
                  f"{1e3 * still:5.1f}) {dict(Counter(states))} silently wrong {wrong}",
                  flush=True)
    print("\nsilently wrong frames (offset, seed, frame): true motion, error, state before")
    for r in runs:
        for i in r["silently_wrong"]:
            f = r["frames"][i]
            print(f"  {r['offset']} {r['seed']} {i}: true {f['true_deg']:.1f} deg "
                  f"{100 * f['true_m']:.1f} cm; error {f['err_deg']:.1f} deg "
                  f"{100 * f['err_m']:.1f} cm")
    all_frames = [f for r in runs for f in r["frames"] if f["i"] > 0]
    bins = [0, 2, 4, 6, 8, 10, 15, 90]
    print("\ntrue rotation from the previous frame (deg): frames / off by > 5 cm or 3 deg "
          "(any state) / of those called OK")
    for lo, hi in zip(bins[:-1], bins[1:], strict=True):
        sel = [f for f in all_frames if lo <= f["true_deg"] < hi]
        bad = [f for f in sel if f["err_m"] > 0.05 or f["err_deg"] > 3.0]
        ok_bad = [f for f in bad if f["state"] == "OK"]
        print(f"  {lo:3d}-{hi:<3d} {len(sel):4d} {len(bad):4d} {len(ok_bad):4d}")
    worse = sum(r["ate_m"] > r["standing_still_m"] for r in runs)
    mean_ate = float(np.mean([r["ate_m"] for r in runs]))
    print(f"\nruns worse than standing still: {worse} of {len(runs)}; mean ATE "
          f"{1e3 * mean_ate:.1f} mm; silently wrong frames "
          f"{sum(len(r['silently_wrong']) for r in runs)}")
    write_json(args.out_json, {
        **script_record("far_apart_anatomy.py", argv),
        "clip": str(args.clip), "step": args.step, "runs": runs})
    return 0


if __name__ == "__main__":
    sys.exit(main())
