"""A hand over the lens: a clip with some frames covered, tracked with and without the
keyframe map, against the same clip uncovered (issue 48's "found again" measurement).

Usage::

    python scripts/lost_and_found.py CLIP [--cover 100-129] [--seeds 0-4] [--set KEY=VALUE]
                                     [--keep DIR] [--out-json FILE]

The covered copy is made as a user would make one (``datasets.cover.covered_copy``: black
colour images and empty depth images at the ``--cover`` frames, everything else linked) in
``--keep`` (default: a temporary folder); the folder keeps the clip's name with
``_covered`` after it, so that its camera is found as the clip's. Each seed runs the
uncovered clip and the covered copy with the default Config (the ``--set`` overrides on
both). Per covered run: the covered frames called OK (none should be), the first frame after
the cover within 2 cm and 2 degrees of the truth once the estimate is aligned on the frames
before the cover (``measure.pose_errors``) and how long after the cover it comes, the OK
frames after it that are not within that, the OK frames after the cover farther than 5 cm or
3 degrees from the truth (``ok_wrong_after_cover``), how the map placed frames (found again,
revisits), and ATE over every frame and over the frames not covered, with the uncovered
run's beside it; the mean and median ms a frame of both (``measure.frame_stats``: a chain
made at a guess asks the map, and that must not cost the frame). Prints a line per seed and
writes everything to JSON.
"""

from __future__ import annotations

import sys
import tempfile
import warnings
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from edgevo_jax import Config, enable_batch_exact
from edgevo_jax.datasets.cover import covered_copy
from edgevo_jax.datasets.tum import EmptyDepthWarning, load_sequence
from edgevo_jax.reports import digest, int_list, script_parser, script_record, write_json
from edgevo_jax.runs.measure import (
    DIVERGED_ROT_DEG,
    DIVERGED_TRANS_M,
    accuracy,
    frame_stats,
    groundtruth_at,
    pose_errors,
)
from edgevo_jax.runs.run import run_sequence

#: a frame is placed right within these of the truth (m, degrees)
WITHIN_M, WITHIN_DEG = 0.02, 2.0


def covered_run(seq, run, cover: list[int], gt: np.ndarray) -> dict:
    """The covered run's measures (module doc)."""
    states = [r.state for r in run.results]
    trans, rot = pose_errors(run.poses, gt, range(cover[0]))
    good = (trans < WITHIN_M) & (rot < WITHIN_DEG)
    end = cover[-1]
    first = next((i for i in range(end + 1, len(states)) if good[i]), None)
    off = [] if first is None else [i for i in range(first, len(states))
                                    if states[i] == "OK" and not good[i]]
    kept = [i for i in range(len(states)) if i not in set(cover)]
    placed = [r.placed for r in run.results if r.placed]
    return {
        "covered_ok": sum(states[i] == "OK" for i in cover),
        "first_within": first,
        "first_within_s": None if first is None
        else float(seq.timestamps[first] - seq.timestamps[end]),
        "ok_off_after": off,
        "ok_wrong_after_cover": [
            i for i in range(end + 1, len(states)) if states[i] == "OK"
            and not (trans[i] < DIVERGED_TRANS_M and rot[i] < DIVERGED_ROT_DEG)],
        "found_again": sum(p.startswith("found again") for p in placed),
        "revisits": sum(p.startswith("revisit") for p in placed),
        "ate_m": accuracy(seq.groundtruth, run.timestamps, run.poses)["ate_rmse_m"],
        "ate_not_covered_m": accuracy(seq.groundtruth, run.timestamps[kept],
                                      run.poses[kept])["ate_rmse_m"],
        "ms": frame_stats(run.frame_ms),
        "frames": [{"i": i, "state": s, "reason": r.reason, "placed": r.placed,
                    "err_m": float(trans[i]), "err_deg": float(rot[i])}
                   for i, (s, r) in enumerate(zip(states, run.results, strict=True))],
    }


def main(argv: Sequence[str] | None = None) -> int:
    """Make the covered copy, run every seed; print and write the measures."""
    argv = list(sys.argv[1:] if argv is None else argv)
    p = script_parser(__doc__, seeds="0-4")
    p.add_argument("clip", type=Path)
    p.add_argument("--cover", type=int_list, default=list(range(100, 130)))
    p.add_argument("--keep", type=Path, default=None, help="where the covered copy goes")
    p.add_argument("--out-json", type=Path, default=Path("lost_and_found.json"))
    args = p.parse_args(argv)
    enable_batch_exact()
    warnings.simplefilter("ignore", EmptyDepthWarning)  # the covered frames, by design
    with tempfile.TemporaryDirectory() as tmp:
        folder = (args.keep or Path(tmp)) / f"{args.clip.name}_covered"
        if not folder.exists():
            covered_copy(args.clip, folder, args.cover)
        plain, covered = load_sequence(args.clip), load_sequence(folder)
        gt = groundtruth_at(plain, plain.timestamps)
        runs = []
        for seed in args.seeds:
            config = Config().with_overrides([*args.set, f"seed={seed}"])
            before = run_sequence(plain, config, progress=False)
            after = run_sequence(covered, config, progress=False)
            row = {"seed": seed, **covered_run(covered, after, args.cover, gt),
                   "uncovered_ms": frame_stats(before.frame_ms),
                   "digest": digest(after), "uncovered_digest": digest(before),
                   "uncovered_ate_m": accuracy(plain.groundtruth, before.timestamps,
                                               before.poses)["ate_rmse_m"],
                   # the map's memory over the uncovered clip: keyframes, bytes, seconds
                   "uncovered_map": [before.map_keyframes, before.map_bytes,
                                     float(plain.timestamps[-1] - plain.timestamps[0])]}
            runs.append(row)
            print(f"seed {seed}: covered frames OK {row['covered_ok']}; first within "
                  f"{100 * WITHIN_M:.0f} cm / {WITHIN_DEG:.0f} deg: frame "
                  f"{row['first_within']} ({row['first_within_s']} s after the cover); OK "
                  f"frames off after it {len(row['ok_off_after'])}, over 5 cm / 3 deg after "
                  f"the cover {len(row['ok_wrong_after_cover'])}; found again "
                  f"{row['found_again']}; ATE {1e3 * row['ate_m']:.1f} mm (not covered "
                  f"{1e3 * row['ate_not_covered_m']:.1f}), uncovered "
                  f"{1e3 * row['uncovered_ate_m']:.1f} mm; ms a frame {row['ms']['mean']:.1f} "
                  f"(median {row['ms']['median']:.1f}), uncovered "
                  f"{row['uncovered_ms']['mean']:.1f} ({row['uncovered_ms']['median']:.1f})",
                  flush=True)
    ratio = [r["ate_m"] / r["uncovered_ate_m"] for r in runs]
    kept = [r["ate_not_covered_m"] / r["uncovered_ate_m"] for r in runs]
    slow = [r["ms"]["mean"] / r["uncovered_ms"]["mean"] for r in runs]
    print(f"ATE covered / uncovered: {min(ratio):.2f}-{max(ratio):.2f} (frames not covered: "
          f"{min(kept):.2f}-{max(kept):.2f}); mean ms a frame covered / uncovered "
          f"{min(slow):.2f}-{max(slow):.2f}")
    write_json(args.out_json, {
        **script_record("lost_and_found.py", argv),
        "clip": str(args.clip), "cover": args.cover,
        "runs": runs})
    return 0


if __name__ == "__main__":
    sys.exit(main())
