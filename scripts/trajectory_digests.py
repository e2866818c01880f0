"""Digests of the tracker's trajectories over clips, frame steps and seeds: the check that a
change leaves tracking bit for bit as it was (``digest``: float64 poses and each frame's
state and reasons).

Usage::

    python scripts/trajectory_digests.py CLIP [CLIP ...] [--steps 1,2,3] [--seeds 0-2]
                                         [--batch] [--set KEY=VALUE ...]
                                         [--out F.json] [--check F.json]

Each clip runs with the default Config (with the ``--set`` overrides) at every step and
seed, through the streaming tracker (``run``) or, with ``--batch``, all seeds of a clip and
step in one ``evaluate`` batch.
``--check F.json`` compares with an earlier output and exits 1 on any difference.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from edgevo_jax import Config, enable_batch_exact, evaluate, load_sequence, run
from edgevo_jax.reports import digest, int_list, script_parser


def main(argv: list[str] | None = None) -> int:
    enable_batch_exact()  # the CLI's arithmetic
    p = script_parser(__doc__, seeds="0-2")
    p.add_argument("clips", nargs="+", type=Path)
    p.add_argument("--steps", type=int_list, default=[1, 2, 3])
    p.add_argument("--batch", action="store_true", help="through evaluate (the batch path)")
    p.add_argument("--out", type=Path)
    p.add_argument("--check", type=Path)
    args = p.parse_args(argv)
    digests = {}
    for clip in args.clips:
        for step in args.steps:
            seq = load_sequence(clip, frame_step=step)
            configs = [Config().with_overrides([*args.set, f"seed={s}"]) for s in args.seeds]
            runs = evaluate([seq], configs, progress=False).runs if args.batch else [
                run(seq, c, progress=False) for c in configs]
            for seed, r in zip(args.seeds, runs, strict=True):
                key = f"{clip.name}-step{step}-seed{seed}"
                digests[key] = digest(r)
                print(key, digest(r)[:16], f"{len(r.results)} frames", flush=True)
    if args.out:
        args.out.write_text(json.dumps(digests, indent=1) + "\n")
    if args.check:
        want = json.loads(args.check.read_text())
        diff = sorted(k for k in digests if want.get(k) != digests[k])
        print(f"{len(digests) - len(diff)} of {len(digests)} identical to {args.check}"
              + (f"; different: {', '.join(diff)}" if diff else ""))
        return 1 if diff else 0
    return 0


if __name__ == "__main__":
    sys.exit(main())
