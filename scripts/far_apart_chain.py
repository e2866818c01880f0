"""How well a chain of pairwise solves could track a far-apart clip: the ceiling of a
frame-to-frame tracker (issue 38).

Usage::

    python scripts/far_apart_chain.py PAIRS_JSON CLIP --step K [--solve orb_edges]
                                      [--trials 50] [--seed 0]

PAIRS_JSON is ``scripts/far_apart_pairs.py``'s output for CLIP with ``--gap K``: per pair
(i, i + K) the error (cm, degrees) of each solve. For every start offset whose frames all
have ground truth (and whose pairs were measured), the clip at every K-th frame is tracked
in simulation: each frame's pose is the previous one's composed with the true motion and an
error of the measured size for that pair (``--solve``, default the edge solve from the ORB
start) in a random direction; a pair without that solve gets 5 cm and 2 degrees. Prints
per offset the ATE of standing still, the mean ATE of ``--trials`` such chains and the share
of chains worse than standing still; then the same with the errors halved.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from edgevo_jax.datasets.tum import load_sequence, subsequence
from edgevo_jax.geometry import exp_np, inverse_np
from edgevo_jax.pipeline.measure import accuracy, groundtruth_at

#: the error given to a pair the solve did not solve (cm, degrees)
UNSOLVED = (5.0, 2.0)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("pairs", type=Path)
    p.add_argument("clip", type=Path)
    p.add_argument("--step", type=int, required=True)
    p.add_argument("--solve", default="orb_edges")
    p.add_argument("--trials", type=int, default=50)
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    pairs = json.loads(args.pairs.read_text())["pairs"]
    err = {q["i"]: q.get(args.solve) for q in pairs}
    full = load_sequence(args.clip)
    rng = np.random.default_rng(args.seed)

    def unit() -> np.ndarray:
        v = rng.normal(size=3)
        return v / np.linalg.norm(v)

    for scale in (1.0, 0.5):
        rows = []
        for offset in range(args.step):
            idx = list(range(offset, len(full), args.step))
            seq = subsequence(full, offset, len(full), step=args.step)
            G = groundtruth_at(seq, seq.timestamps)
            if not np.all(np.isfinite(G)) or any(i not in err for i in idx[:-1]):
                continue
            still = accuracy(seq.groundtruth, seq.timestamps,
                             np.repeat(np.eye(4)[None], len(seq), axis=0))["ate_rmse_m"]
            ates = []
            for _ in range(args.trials):
                P = [G[0]]
                for k in range(len(seq) - 1):
                    cm, deg = err[idx[k]] or UNSOLVED
                    xi = np.r_[unit() * scale * cm / 100, unit() * np.radians(scale * deg)]
                    P.append(P[-1] @ inverse_np(G[k]) @ G[k + 1] @ exp_np(xi))
                ates.append(accuracy(seq.groundtruth, seq.timestamps, np.stack(P))["ate_rmse_m"])
            worse = float(np.mean(np.array(ates) > still))
            rows.append((offset, still, float(np.mean(ates)), worse))
        print(f"errors x {scale:g}: mean ATE {1e3 * np.mean([r[2] for r in rows]):.1f} mm, "
              f"standing still {1e3 * np.mean([r[1] for r in rows]):.1f} mm, chains worse than "
              f"standing still {np.mean([r[3] for r in rows]):.2f} ({len(rows)} offsets)")
        for offset, still, ate, worse in rows:
            print(f"  offset {offset:2d}: standing still {1e3 * still:6.1f} mm, chains "
                  f"{1e3 * ate:6.1f} mm, worse {worse:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
