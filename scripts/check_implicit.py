"""Is the implicit adjoint exact on real frames? Newton decrement at the final pose and the
implicit gradient against central differences, with and without the smooth options.

Usage::

    python scripts/check_implicit.py [SEQ_DIR] [--pairs 1,2,5] [--num-edges 128]
                                     [--iterations 20,5,5] [--refine 3] [--eps 1e-4]
                                     [--max-rejects 1000]
                                     [--out-json docs/learning/implicit_check.json]

SEQ_DIR defaults to the bundled fr1/xyz clip. Frame 0 is the keyframe (``--num-edges`` edges,
spg, seed 0); each frame k of ``--pairs`` is tracked against it from the identity by
``learn.track_differentiable`` in float64 with soft consistency and non-default Params (every
level-0 parameter has an effect: the weighting model's weights are nonzero), under four
variants: the plain computation (bilinear fields, no refinement: what the tracker does),
bicubic fields, refinement rounds, and both. Config: ``--iterations`` LM tries per level
(level 0 first), no early stop (step_tol 0, ``--max-rejects`` 1000: the tracker's default
of 3 rejected tries in a row stops a level earlier).

For each pair and variant it reports the cost at the final pose, the Newton decrement
g^T H^-1 g there (``learn.newton_decrement`` of ``learn.level_system``: ~0 at a stationary
point of the cost with the decisions of that pose), the implicit gradient of the pose loss
(``learn.pose_loss`` against the ground truth) w.r.t. each parameter that enters level 0,
central differences with step ``--eps``, their largest relative difference over the
parameters that move the loss (those that do not, |FD| <= 1e-10, are listed), and how many
hard decisions (inlier mask, nearest-edge dots at level 0) differ at the FD poses from those
at the pose itself (0: every FD pose lies on the same smooth piece). Printed as a table and
written to ``--out-json``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from functools import partial
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from edgevo_jax import Config, enable_batch_exact
from edgevo_jax.camera import Intrinsics
from edgevo_jax.cli import BUNDLED_CLIP
from edgevo_jax.datasets import groundtruth_pose_at, load_sequence
from edgevo_jax.frontend.selection import keyframe_edges
from edgevo_jax.geometry import inverse_np
from edgevo_jax.image.preprocess import preprocess
from edgevo_jax.io import json_safe, poses7_to_matrices
from edgevo_jax.learn import level_system, newton_decrement, pose_loss, track_differentiable
from edgevo_jax.learn.params import Params, flatten, unflatten

#: parameters checked, all entering level 0 (flattened Params order: log_huber (3), eta,
#: log_temperature, reobs_a, weight_w1 (8 x 6, row by row), weight_b1 (8), weight_w2 (8),
#: weight_b2); not checked: the coarse levels' Huber radii, reobs_a (selection only), the
#: first layer's level-feature column (0 at level 0) and the other hidden units
LEVEL0 = {0: "log_huber0", 3: "eta", 4: "log_temperature", 6: "w1_mag", 7: "w1_depth",
          8: "w1_discontinuity", 9: "w1_residual", 54: "b1_0", 62: "w2_0", 63: "w2_1",
          70: "b2"}
VARIANTS = (("bilinear", 0), ("bicubic", 0), ("bilinear", None), ("bicubic", None))
#: |central difference| at or below this: the parameter does not move the loss (rounding)
ZERO = 1e-10


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("sequence", nargs="?", type=Path, default=BUNDLED_CLIP)
    p.add_argument("--pairs", default="1,2,5", help="frames tracked against frame 0")
    p.add_argument("--num-edges", type=int, default=128)
    p.add_argument("--iterations", default="20,5,5", help="LM tries per level, level 0 first")
    p.add_argument("--refine", type=int, default=3, help="refinement rounds when on")
    p.add_argument("--max-rejects", type=int, default=1000,
                   help="LM stops a level after this many rejected tries in a row")
    p.add_argument("--eps", type=float, default=1e-4, help="central-difference step")
    p.add_argument("--out-json", type=Path, default=Path("docs/learning/implicit_check.json"))
    return p.parse_args(argv)


def nondefault_params(config: Config) -> Params:
    """Non-default Params in which every level-0 parameter moves the pose (float64)."""
    return Params.default(config, jnp.float64)._replace(
        weight_w2=jnp.array([0.1, -0.2, 0.3, 0.05, -0.1, 0.2, 0.1, -0.3]),
        weight_b2=jnp.asarray(0.1), log_huber=jnp.log(jnp.array([1.2, 0.9, 1.1])))


def _pose(v, kf, dist, em, intr, config, interpolation, refine, adjoint):
    params = nondefault_params(config)
    return track_differentiable(kf, dist, em, jnp.eye(4), intr, unflatten(v, params), config,
                                adjoint=adjoint, interpolation=interpolation,
                                refine=refine).T_c_k


@partial(jax.jit, static_argnames=("config", "interpolation", "refine"))
def _forward(v, kf, dist, em, T_gt, intr, config, interpolation, refine):
    """Pose loss, the hard decisions and the Newton decrement at the final pose, the cost."""
    T = _pose(v, kf, dist, em, intr, config, interpolation, refine, "implicit")
    system, mask, dots = level_system(kf, dist, em, T, intr,
                                      unflatten(v, nondefault_params(config)), config,
                                      interpolation=interpolation)
    return pose_loss(T, T_gt), mask, dots, newton_decrement(system), system.cost


@partial(jax.jit, static_argnames=("config", "interpolation", "refine"))
def _implicit_grad(v, kf, dist, em, T_gt, intr, config, interpolation, refine):
    return jax.grad(lambda v: pose_loss(
        _pose(v, kf, dist, em, intr, config, interpolation, refine, "implicit"), T_gt))(v)


def check_pair(kf, dist, em, T_gt, intr, config, interpolation, refine, eps) -> dict:
    """One pair under one variant: decrement, implicit gradient vs central differences."""
    t0 = time.perf_counter()
    args = (kf, dist, em, T_gt, Intrinsics(*(jnp.asarray(x, jnp.float64) for x in intr)))
    static = {"config": config, "interpolation": interpolation, "refine": refine}
    v = flatten(nondefault_params(config))
    _, mask, dots, decrement, cost = _forward(v, *args, **static)
    grad = np.asarray(_implicit_grad(v, *args, **static))
    rows, flipped = {}, 0
    for i, name in LEVEL0.items():
        e = np.zeros(v.size)
        e[i] = eps
        (lp, mp, dp, _, _), (lm, mm, dm, _, _) = (_forward(v + e, *args, **static),
                                                  _forward(v - e, *args, **static))
        flipped += sum(int(np.sum(np.asarray(m) != np.asarray(mask)))
                       + int(np.sum(np.asarray(d) != np.asarray(dots)))
                       for m, d in ((mp, dp), (mm, dm)))
        fd = (float(lp) - float(lm)) / (2 * eps)
        rows[name] = {"implicit": float(grad[i]), "fd": fd,
                      "rel_diff": abs(float(grad[i]) - fd) / max(abs(fd), 1e-300)}
    moving = [r["rel_diff"] for r in rows.values() if abs(r["fd"]) > ZERO]
    return {"cost": float(cost), "newton_decrement": float(decrement),
            "max_rel_diff": max(moving, default=0.0),
            "no_effect": [k for k, r in rows.items() if abs(r["fd"]) <= ZERO],
            "decisions_flipped_at_fd_poses": flipped, "gradients": rows,
            "seconds": time.perf_counter() - t0}


def main(argv: list[str] | None = None) -> int:
    enable_batch_exact()  # the CLI's arithmetic: trajectories as `edgevo run` gives them
    args = parse_args(argv)
    jax.config.update("jax_enable_x64", True)
    seq = load_sequence(args.sequence)
    iterations = tuple(int(x) for x in args.iterations.split(","))
    config = Config(num_edges=args.num_edges, iterations=iterations, step_tol=0.0,
                    max_rejects=args.max_rejects)
    frame0 = preprocess(*seq.load_frame(0), config)
    edges = keyframe_edges(frame0, config, seed=0, intr=seq.intrinsics)
    kf = jax.tree.map(lambda a: jnp.asarray(a, jnp.float64) if a.dtype.kind == "f"
                      else jnp.asarray(a), edges)
    gt0 = poses7_to_matrices(groundtruth_pose_at(seq, seq.timestamps[0])[None])[0]
    results = []
    for k in (int(x) for x in args.pairs.split(",")):
        frame = preprocess(*seq.load_frame(k), config)
        dist = tuple(jnp.asarray(d, jnp.float64) for d in frame.dist)
        em = jax.tree.map(jnp.asarray, frame.edge_map)
        gtk = poses7_to_matrices(groundtruth_pose_at(seq, seq.timestamps[k])[None])[0]
        T_gt = jnp.asarray(inverse_np(gtk) @ gt0)
        for interpolation, refine in VARIANTS:
            refine = args.refine if refine is None else refine
            r = check_pair(kf, dist, em, T_gt, seq.intrinsics, config, interpolation, refine,
                           args.eps)
            r.update(pair=[0, k], interpolation=interpolation, refine=refine)
            results.append(r)
            print(f"pair (0, {k}) {interpolation:8s} refine {refine}: cost {r['cost']:9.4f} "
                  f"decrement {r['newton_decrement']:.2e}  implicit vs FD: max rel diff "
                  f"{r['max_rel_diff']:.1e}, decisions flipped at FD poses "
                  f"{r['decisions_flipped_at_fd_poses']}"
                  + (f", no effect: {', '.join(r['no_effect'])}" if r["no_effect"] else ""),
                  flush=True)
    report = {"sequence": seq.name, "num_edges": args.num_edges, "iterations": iterations,
              "max_rejects": args.max_rejects,
              "eps": args.eps, "dtype": "float64", "consistency": "soft",
              "params": {k: np.asarray(v).tolist() for k, v in
                         zip(Params._fields, nondefault_params(config), strict=True)},
              "results": results}
    args.out_json.parent.mkdir(parents=True, exist_ok=True)
    args.out_json.write_text(json.dumps(json_safe(report), indent=2) + "\n")
    print(f"wrote {args.out_json}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
