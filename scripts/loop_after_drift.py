"""A loop after real drift: a clip there and back on frames the two passes do not share (its
even frames forward, its odd frames backward: ``datasets.there_and_back``), the way back
seen through a biased depth sensor (``perturb.perturbed_copy(depth_scale=...)``: depth read
a few per cent short), so the chain comes back to its start drifted; tracked with loops
closed and without (``loops=false``), over seeds.

Usage::

    python scripts/loop_after_drift.py CLIP [--depth-scale 1.06] [--seeds 0-4]
                                       [--set KEY=VALUE] [--out-json FILE]

Per seed: the chain's error at the revisit (the online pose of the last frame against the
first, relative to the truth's: cm, degrees, and the pixels of edge motion that error
predicts at the clip's median depth), ATE with loops and without, the loops closed,
rejected and wrong (``measure.wrong_loops``), and the digests of both runs.
"""

from __future__ import annotations

import sys
import tempfile
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from edgevo_jax import Config, enable_batch_exact
from edgevo_jax.datasets import load_sequence, there_and_back
from edgevo_jax.datasets.perturb import perturbed_copy
from edgevo_jax.reports import digest, script_parser, script_record, write_json
from edgevo_jax.runs.measure import accuracy, end_to_end_error, groundtruth_at, wrong_loops
from edgevo_jax.runs.run import run_sequence

#: the median depth the pixels of predicted edge motion are taken at (m): teddy's scene
MEDIAN_DEPTH_M = 1.5


def revisit_error(poses: np.ndarray, gt: np.ndarray, fx: float) -> tuple[float, float, float]:
    """The chain's error at the revisit (``measure.end_to_end_error``): cm, degrees, and the
    edge motion it predicts (px, at ``MEDIAN_DEPTH_M``)."""
    t, angle = end_to_end_error(poses, gt)
    return 100 * t, float(np.degrees(angle)), fx * (t / MEDIAN_DEPTH_M + angle)


def main(argv: Sequence[str] | None = None) -> int:
    """Build the sequence, run every seed with loops and without; print and write."""
    argv = list(sys.argv[1:] if argv is None else argv)
    p = script_parser(__doc__, seeds="0-4")
    p.add_argument("clip", type=Path)
    p.add_argument("--depth-scale", type=float, default=1.06,
                   help="the way back's true depth over the depth read (1: unbiased)")
    p.add_argument("--out-json", type=Path, default=Path("loop_after_drift.json"))
    args = p.parse_args(argv)
    enable_batch_exact()
    clip = load_sequence(args.clip)
    with tempfile.TemporaryDirectory() as tmp:
        biased = Path(tmp) / args.clip.name  # the name keeps the camera
        perturbed_copy(args.clip, biased, depth_scale=args.depth_scale)
        seq = there_and_back(clip, load_sequence(biased))
        gt = groundtruth_at(seq, seq.timestamps)
        rows = [one_seed(seq, gt, seed, args.set) for seed in args.seeds]
    ratio = [r["loops"]["ate_m"] / r["map_only"]["ate_m"] for r in rows]
    print(f"ATE loops / map only: mean {np.mean(ratio):.2f} ({min(ratio):.2f}-"
          f"{max(ratio):.2f}); closed in {sum(r['loops']['loops_closed'] > 0 for r in rows)} "
          f"of {len(rows)} seeds; wrong loops {sum(r['loops']['loops_wrong'] for r in rows)}")
    write_json(args.out_json, {
        **script_record("loop_after_drift.py", argv),
        "clip": str(args.clip), "frames": len(seq),
        "depth_scale": args.depth_scale, "runs": rows})
    return 0


def one_seed(seq, gt: np.ndarray, seed: int, sets: list[str]) -> dict:
    """One seed's runs with loops and without (module doc)."""
    config = Config().with_overrides([*sets, f"seed={seed}"])
    row: dict = {"seed": seed}
    for name, cfg in (("loops", config), ("map_only", config.replace(loops=False))):
        run = run_sequence(seq, cfg, progress=False)
        online = run.online_poses if run.online_poses is not None else run.poses
        cm, deg, px = revisit_error(online, gt, seq.intrinsics.fx)
        loops = run.loops or {"closed": [], "rejected": [], "solves": []}
        row[name] = m = {
            "ate_m": accuracy(seq.groundtruth, run.timestamps, run.poses)["ate_rmse_m"],
            "revisit_cm": cm, "revisit_deg": deg, "revisit_px": px,
            "loops_closed": len(loops["closed"]), "loops_rejected": len(loops["rejected"]),
            "loops_wrong": wrong_loops(run.loops, seq),
            "notes": [e["note"] for e in loops["closed"]],
            "digest": digest(run)}
        print(f"seed {seed} {name:8s}: ATE {1e3 * m['ate_m']:.1f} mm, chain at the revisit "
              f"{cm:.1f} cm {deg:.2f} deg ({px:.0f} px), loops {m['loops_closed']} closed "
              f"{m['loops_rejected']} rejected {m['loops_wrong']} wrong", flush=True)
    return row


if __name__ == "__main__":
    sys.exit(main())
