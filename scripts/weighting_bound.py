"""How much could any per-edge weighting lower the learning loss? An oracle bound.

Usage::

    python scripts/weighting_bound.py [SEQ_DIR] [--frames 0:100] [--gaps 1,2,3]
                                      [--num-edges 256] [--thresholds 3,2,1,0.5]
                                      [--out-json docs/learning/weighting_bound.json]

For the training pairs of ``scripts/learn_weights.py`` (the same frames, gaps, edges, seed,
interpolated ground truth and smooth mode with default ``Params``), the mean pair loss
(translation m + 0.1 x rotation rad, the script's training loss) with every selected edge,
and with the edges removed whose distance residual at the TRUE pose exceeds a threshold (px,
level 0): a weighting that knew the answer. A learnt weighting sees only the edges'
features, so it can at best approach these numbers; a loss that does not move under the
oracle cannot be lowered much by any weighting. Also the median pair error, which shows the
floor that depth noise and ground-truth noise set.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from learn_weights import DEFAULT_SEQ, build_data, load_all, make_part, pair_arrays

from edgevo_jax import Config, enable_batch_exact
from edgevo_jax.camera import Intrinsics, unproject
from edgevo_jax.frontend.residuals import warp
from edgevo_jax.geometry import Pose
from edgevo_jax.image.interp import bicubic_with_grad
from edgevo_jax.learn import relative_pose_error, track_smooth
from edgevo_jax.learn.params import Params


def main(argv: list[str] | None = None) -> int:
    enable_batch_exact()
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("sequence", nargs="?", type=Path, default=DEFAULT_SEQ)
    p.add_argument("--frames", default="0:100", help="training frames a:b")
    p.add_argument("--gaps", default="1,2,3")
    p.add_argument("--num-edges", type=int, default=256)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--rot-weight", type=float, default=0.1)
    p.add_argument("--thresholds", default="3,2,1,0.5", help="px at level 0")
    p.add_argument("--out-json", type=Path, default=None)
    args = p.parse_args(argv)
    seqs = load_all([args.sequence])
    if isinstance(seqs, str):
        print(seqs, file=sys.stderr)
        return 2
    config = Config(num_edges=args.num_edges)
    a, b = (int(x) for x in args.frames.split(":"))
    part = make_part(seqs[0], 0, (a, b))
    pairs = part.pairs([int(g) for g in args.gaps.split(",")])
    if not pairs:
        print(f"no pairs with ground truth in frames {a}:{b}", file=sys.stderr)
        return 2
    frames = sorted({f for pr in pairs for f in pr})
    data = build_data(seqs, frames, sorted({i for i, _ in pairs}), config, args.seed)
    ki, fi, T_gt = pair_arrays(pairs, {(0, f): T for f, T in part.gt.items()}, data)
    params = Params.default(config, jnp.float32)

    def one(ki, fi, T, threshold):
        kf = jax.tree.map(lambda x: x[ki], data["kf"])
        intr = Intrinsics(*data["intr"][ki])
        dist = tuple(d[fi] for d in data["dist"])
        em = jax.tree.map(lambda x: x[fi], data["edge_map"])
        uv, _ = warp(intr, Pose.from_matrix(T), unproject(intr, kf.uv, kf.rho))
        r, _, _ = bicubic_with_grad(dist[0], uv)
        kf = kf._replace(valid=kf.valid & (r <= threshold))
        out = track_smooth(kf, dist, em, jnp.eye(4, dtype=jnp.float32), intr, params, config)
        return (*relative_pose_error(out.T_c_k, T), jnp.sum(kf.valid))

    run = jax.jit(jax.vmap(one, in_axes=(0, 0, 0, None)))
    rows = []
    for threshold in [np.inf] + [float(x) for x in args.thresholds.split(",")]:
        t, r, n = (np.asarray(x) for x in run(ki, fi, T_gt, threshold))
        row = {"threshold_px": None if np.isinf(threshold) else threshold,
               "loss": float(np.mean(t + args.rot_weight * r)),
               "t_mean_mm": float(np.mean(t) * 1e3), "t_median_mm": float(np.median(t) * 1e3),
               "edges_mean": float(np.mean(n))}
        rows.append(row)
        change = 100.0 * (row["loss"] / rows[0]["loss"] - 1.0)
        label = "every edge" if np.isinf(threshold) else f"true-pose residual <= {threshold} px"
        print(f"{label:32s} loss {row['loss']:.6f} ({change:+.1f} %), pair t mean "
              f"{row['t_mean_mm']:.2f} mm, median {row['t_median_mm']:.2f} mm, "
              f"{row['edges_mean']:.0f} edges")
    if args.out_json:
        args.out_json.parent.mkdir(parents=True, exist_ok=True)
        args.out_json.write_text(json.dumps({"sequence": str(seqs[0].root), "pairs": len(pairs),
                                             "frames": [a, b], "rows": rows}, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
