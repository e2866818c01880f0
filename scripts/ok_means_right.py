"""How often a frame called OK is wrong: clips at low frame rates from every start offset,
over seeds (issue 56's measure).

Usage::

    python scripts/ok_means_right.py CLIP [CLIP ...] [--steps 3,5,10,20] [--offsets 0-9]
                                     [--seeds 0-2] [--set KEY=VALUE] [--out-json FILE]

Each clip is taken at every k-th frame from each offset of ``--offsets`` (``subsequence(...,
step=k)``: offsets k and over start the same frames later) and run once per seed. Per run:
the frames called OK, WEAK and LOST; the silently wrong ones (``measure.silently_wrong``:
called OK, their motion from the previous written frame, of any state, over 5 cm or 3
degrees off the truth's); the OK frames within 5 cm and 3 degrees of the truth once the run
is aligned on all its frames (``measure.pose_errors``); ATE. Per clip and rate: the totals,
the mean ATE, the share of frames WEAK or LOST pooled over the runs, and the silently wrong
rate among OK frames with, where none was seen, the 95 % upper bound the count allows (3 /
OK frames). Prints a line per clip and rate and writes every run to JSON.
"""

from __future__ import annotations

import sys
import warnings
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from edgevo_jax import Config, enable_batch_exact
from edgevo_jax.datasets.tum import EmptyDepthWarning, load_sequence, subsequence
from edgevo_jax.reports import int_list, script_parser, script_record, write_json
from edgevo_jax.runs.measure import (
    DIVERGED_ROT_DEG,
    DIVERGED_TRANS_M,
    accuracy,
    groundtruth_at,
    pose_errors,
    silently_wrong,
)
from edgevo_jax.runs.run import run_sequence


def score(seq, run) -> dict:
    """One run's counts (module doc)."""
    states = [r.state for r in run.results]
    gt = groundtruth_at(seq, run.timestamps)
    trans, rot = pose_errors(run.poses, gt, range(len(states)))
    within = (trans < DIVERGED_TRANS_M) & (rot < DIVERGED_ROT_DEG)
    return {"frames": len(states), "ok": states.count("OK"), "weak": states.count("WEAK"),
            "lost": states.count("LOST"), "wrong": silently_wrong(run.poses, states, gt),
            "ok_within": int(sum(w and s == "OK" for w, s in zip(within, states, strict=True))),
            "ate_m": accuracy(seq.groundtruth, run.timestamps, run.poses)["ate_rmse_m"]}


def summary(rows: Sequence[dict]) -> dict:
    """The totals of one clip and rate (module doc)."""
    ok = sum(r["ok"] for r in rows)
    wrong = sum(len(r["wrong"]) for r in rows)
    frames = sum(r["frames"] for r in rows)
    return {"runs": len(rows), "frames": frames, "ok": ok, "wrong": wrong,
            "runs_with_wrong": sum(bool(r["wrong"]) for r in rows),
            "ok_within": sum(r["ok_within"] for r in rows),
            "flagged_share": sum(r["weak"] + r["lost"] for r in rows) / max(frames, 1),
            "ate_mean_m": float(np.mean([r["ate_m"] for r in rows])),
            "wrong_rate": wrong / ok if ok else None,
            "wrong_rate_bound": (3.0 / ok if ok else None) if wrong == 0 else None}


def main(argv: Sequence[str] | None = None) -> int:
    """Run the sweep; print and write it."""
    argv = list(sys.argv[1:] if argv is None else argv)
    p = script_parser(__doc__, seeds="0-2")
    p.add_argument("clips", nargs="+", type=Path)
    p.add_argument("--steps", type=int_list, default=[3, 5, 10, 20])
    p.add_argument("--offsets", type=int_list, default=list(range(10)))
    p.add_argument("--out-json", type=Path, default=Path("ok_means_right.json"))
    args = p.parse_args(argv)
    enable_batch_exact()
    warnings.simplefilter("ignore", EmptyDepthWarning)
    runs, rates = [], []
    for clip in args.clips:
        full = load_sequence(clip)
        for step in args.steps:
            rows = []
            for offset in args.offsets:
                seq = subsequence(full, offset, len(full), step=step)
                for seed in args.seeds:
                    config = Config().with_overrides([*args.set, f"seed={seed}"])
                    rows.append({"clip": clip.name, "step": step, "offset": offset,
                                 "seed": seed,
                                 **score(seq, run_sequence(seq, config, progress=False))})
            s = {"clip": clip.name, "step": step, **summary(rows)}
            runs += rows
            rates.append(s)
            bound = "" if s["wrong_rate_bound"] is None else \
                f" (none seen: under {100 * s['wrong_rate_bound']:.2f} %)"
            print(f"{clip.name} every {step}: {s['runs']} runs, {s['frames']} frames, OK "
                  f"{s['ok']}, silently wrong {s['wrong']} in {s['runs_with_wrong']} runs"
                  f"{bound}; OK within {s['ok_within']}; WEAK or LOST "
                  f"{100 * s['flagged_share']:.1f} %; ATE mean {1e3 * s['ate_mean_m']:.1f} mm",
                  flush=True)
    write_json(args.out_json, {
        **script_record("ok_means_right.py", argv),
        "rates": rates, "runs": runs})
    return 0


if __name__ == "__main__":
    sys.exit(main())
