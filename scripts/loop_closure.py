"""Loops closed: a clip played forward and back (``datasets.pingpong``, back at its start),
tracked with loops closed and without (``loops=false``: the map alone), over seeds; and the
same with a false loop forced in (issue 49's measurements).

Usage::

    python scripts/loop_closure.py CLIP [--passes 4] [--seeds 0-4] [--set KEY=VALUE]
                                   [--false-loop N] [--out-json FILE]

Per seed and run: ATE over every frame, the end-to-start error (the last frame is the
first one again: the estimated motion between them, in cm and degrees), the loops closed
and rejected, the loops accepted wrong (``measure.wrong_loops``: a kept loop edge more than
5 cm or 3 degrees from the truth's relative pose of its two keyframes), the pose graph's solves
(keyframes, ms), the run's mean time per frame and the digests of its written and online
trajectories (``reports.digest``: equal digests, equal trajectories to the bit).
``--false-loop N``: a third run in which the N-th loop found is handed to the pose graph
against a wrong keyframe (the keyframe of the map farthest from the right one, with the
right one's measurement), past the alignment's verification: whether the graph rejects it,
and its ATE against the run without it. Prints a line per seed and run and writes it all to
JSON.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from edgevo_jax import Config, enable_batch_exact
from edgevo_jax.datasets.pingpong import pingpong
from edgevo_jax.datasets.tum import load_sequence
from edgevo_jax.reports import digest, script_parser, script_record, write_json
from edgevo_jax.runs.measure import accuracy, end_to_end_error, groundtruth_at, wrong_loops
from edgevo_jax.runs.run import run_sequence
from edgevo_jax.tracking import places as relocalise


def forcing_false_loop(n: int):
    """``relocalise.Places.loop`` replaced: its ``n``-th loop found comes back against the
    anchored keyframe of the map farthest from the right one (module doc)."""
    original = relocalise.Places.loop
    count = [0]

    def loop(self, solver, state, frame, kf, exclude, timestamp):
        verify = original(self, solver, state, frame, kf, exclude, timestamp)
        if verify is None:
            return None
        ids = [k for k in self.map.ids if self.map[k].anchored and k != kf.id]
        entries = {k: self.map[k] for k in ids}  # the map as it is now (entries are frozen)

        def forced():
            found = verify()
            if found is None:
                return None
            count[0] += 1  # the searches run one at a time, in order
            if count[0] != n:
                return found
            right = found.keyframe.pose[:3, 3]
            far = max(ids, key=lambda k: np.linalg.norm(entries[k].pose[:3, 3] - right))
            return found._replace(keyframe=relocalise._keyframe(entries[far]),
                                  note=f"false loop: keyframe {kf.id} to keyframe {far} "
                                  f"(forced; right: {found.keyframe.id})")
        return forced
    return original, loop


def measured(run, seq, gt: np.ndarray, false_loop: bool = False) -> dict:
    """One run's measures (module doc)."""
    m, rad = end_to_end_error(run.poses, gt)
    cm, deg = 100 * m, float(np.degrees(rad))
    loops = run.loops or {"closed": [], "rejected": [], "solves": []}
    return {
        "ate_m": accuracy(seq.groundtruth, run.timestamps, run.poses)["ate_rmse_m"],
        "online_ate_m": accuracy(seq.groundtruth, run.timestamps,
                                 run.online_poses if run.online_poses is not None
                                 else run.poses)["ate_rmse_m"],
        "end_to_start_cm": cm, "end_to_start_deg": deg,
        "loops_closed": len(loops["closed"]), "loops_rejected": len(loops["rejected"]),
        "loops_wrong": wrong_loops(run.loops, seq),
        "false_loop_rejected": None if not false_loop else any(
            e["note"].startswith("false loop") for e in loops["rejected"]),
        "solves": [(s["keyframes"], round(s["ms"], 1)) for s in loops["solves"]],
        "keyframes": run.num_keyframes,
        "ms_per_frame_mean": float(np.mean(run.frame_ms[1:])),
        "ms_per_frame_median": float(np.median(run.frame_ms[1:])),
        "digest": digest(run), "online_digest": digest(run, run.online_poses),
    }


def main(argv: Sequence[str] | None = None) -> int:
    """Run every seed with loops and without (and with a false loop); print and write."""
    argv = list(sys.argv[1:] if argv is None else argv)
    p = script_parser(__doc__, seeds="0-4")
    p.add_argument("clip", type=Path)
    p.add_argument("--passes", type=int, default=4, help="forward, back, ...: 4 ends at "
                   "the start")
    p.add_argument("--false-loop", type=int, default=None, metavar="N")
    p.add_argument("--out-json", type=Path, default=Path("loop_closure.json"))
    args = p.parse_args(argv)
    enable_batch_exact()
    clip = load_sequence(args.clip)
    seq = pingpong(clip, args.passes * (len(clip) - 1) + 1)
    gt = groundtruth_at(seq, seq.timestamps)
    rows = []
    for seed in args.seeds:
        config = Config().with_overrides([*args.set, f"seed={seed}"])
        row = {"seed": seed}
        kinds = [("loops", config), ("map_only", config.replace(loops=False))]
        if args.false_loop is not None:
            kinds.append(("false_loop", config))
        for name, cfg in kinds:
            original = None
            if name == "false_loop":
                original, relocalise.Places.loop = forcing_false_loop(args.false_loop)
            try:
                run = run_sequence(seq, cfg, progress=False)
            finally:
                if original is not None:
                    relocalise.Places.loop = original
            row[name] = m = measured(run, seq, gt, name == "false_loop")
            print(f"seed {seed} {name:10s}: ATE {1e3 * m['ate_m']:.1f} mm (online "
                  f"{1e3 * m['online_ate_m']:.1f}), end to start {m['end_to_start_cm']:.1f} cm "
                  f"{m['end_to_start_deg']:.2f} deg, loops {m['loops_closed']} closed "
                  f"{m['loops_rejected']} rejected {m['loops_wrong']} wrong"
                  + ("" if m["false_loop_rejected"] is None
                     else f", false loop rejected: {m['false_loop_rejected']}")
                  + f", {m['ms_per_frame_mean']:.1f} ms/frame", flush=True)
        rows.append(row)
    for name in ("loops", "false_loop"):
        if name in rows[0]:
            ratio = [r[name]["ate_m"] / r["map_only"]["ate_m"] for r in rows]
            print(f"ATE {name} / map only: mean {np.mean(ratio):.2f} "
                  f"({min(ratio):.2f}-{max(ratio):.2f})")
    if "false_loop" in rows[0]:
        ratio = [r["false_loop"]["ate_m"] / r["loops"]["ate_m"] for r in rows]
        print(f"ATE with the false loop / without: {min(ratio):.3f}-{max(ratio):.3f}")
    write_json(args.out_json, {
        **script_record("loop_closure.py", argv),
        "clip": str(args.clip), "frames": len(seq),
        "runs": rows})
    return 0


if __name__ == "__main__":
    sys.exit(main())
