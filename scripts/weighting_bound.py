"""How much could any per-edge weighting lower the pair error? An oracle bound.

Usage::

    python scripts/weighting_bound.py [SEQ_DIR] [--frame-step 1] [--frames 0:100]
                                      [--gaps 1,2,3] [--num-edges 256]
                                      [--thresholds 3,2,1,0.5]
                                      [--runs smooth:identity,tracker:velocity]
                                      [--readout-s S] [--no-depth-residual]
                                      [--out-json docs/learning/weighting_bound.json]

Pairs (i, i + k), k in ``--gaps``, of the frames ``--frames`` of the sequence loaded with
``--frame-step`` (every k-th frame: k = 2 is 15 Hz from 30 Hz), as ``scripts/learn_weights.py``
makes them (the same edges, seed and interpolated ground truth), keeping those whose keyframe's
previous frame and the frame two before the target have ground truth too (the tracker's
velocity needs them). For each pair the mean pair loss (translation m + ``--rot-weight`` x
rotation rad, the training loss of ``learn_weights.py``) with every selected edge, and with
the edges removed whose distance residual at the TRUE pose exceeds a threshold (px, level 0):
a weighting that knew the answer. A learnt weighting sees only the edges' features, so it can
at best approach these numbers; a loss that does not move under the oracle cannot be lowered
much by any weighting. The bound is the largest drop of the mean loss over the thresholds;
beside it the same for the median pair loss (the mean is moved by a few failed pairs, the
median by the typical pair, whose floor depth noise and ground-truth noise set), and the pairs
whose translation error exceeds 1 cm.

Each of ``--runs`` is a solver and a start, ``solver:start``. The solvers:

- ``smooth``: the smooth training mode (``learn.track_smooth``, default ``Params``), what
  learning differentiates: a global shutter and no depth residual; the residual at the true
  pose is read as it reads it (bicubic, global shutter).
- ``tracker``: the tracker's own solve (``frontend.align.track``: Levenberg-Marquardt, hard
  decisions, the depth residual at level 0 when ``Config.depth_residual``, the rolling
  shutter with the camera's readout time unless ``--readout-s`` sets one). Its rolling
  shutter is driven by the ground truth where the tracker uses its own estimates: the
  keyframe's edges unrolled with its true motion from the frame before it, the target's
  shutter with the true pose of the frame before it; the residual at the true pose is read
  as the tracker reads it (bilinear, with that shutter). The oracle removes edges only (the
  depth points stay).

The starts: where each pair's solve starts, ``identity`` (as ``learn_weights.py`` trains) or
``velocity`` (the tracker's constant-velocity prediction, from the true poses of the two
frames before the target); ``refine`` (tracker only): each oracle solve starts where the
solve with every edge from the constant-velocity start ended (an oracle that acts only once the
pose is near, so that fewer edges do not narrow the basin).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from learn_weights import DEFAULT_SEQ, _positive, build_data, load_all, make_part, pair_arrays

from edgevo_jax import Config, enable_batch_exact
from edgevo_jax.camera import Intrinsics, unproject
from edgevo_jax.derive import solve_knobs, solve_structure
from edgevo_jax.frontend.align import track
from edgevo_jax.frontend.depth import depth_points
from edgevo_jax.frontend.residuals import residual_jacobian_grad, warp
from edgevo_jax.frontend.selection import KeyframeEdges
from edgevo_jax.frontend.shutter import Shutter, row_motion, shutter_rate, unroll_edges
from edgevo_jax.geometry import Pose, inverse_np, log_np
from edgevo_jax.image.interp import bicubic_with_grad
from edgevo_jax.learn import relative_pose_error, track_smooth
from edgevo_jax.learn.params import Params

SOLVERS = ("smooth", "tracker")
STARTS = ("identity", "velocity", "refine")


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("sequence", nargs="?", type=Path, default=DEFAULT_SEQ)
    p.add_argument("--frame-step", type=_positive, default=1,
                   help="keep every k-th frame (k = 2: 15 Hz from 30 Hz); --frames counts "
                        "the kept frames")
    p.add_argument("--frames", default="0:100", help="frames a:b (of the kept frames)")
    p.add_argument("--gaps", default="1,2,3")
    p.add_argument("--num-edges", type=int, default=256)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--rot-weight", type=float, default=0.1)
    p.add_argument("--thresholds", default="3,2,1,0.5", help="px at level 0")
    p.add_argument("--runs", default="smooth:identity",
                   help=f"comma-separated solver:start, solver of {', '.join(SOLVERS)}, "
                        f"start of {', '.join(STARTS)}")
    p.add_argument("--readout-s", type=float, default=None,
                   help="the tracker's rolling-shutter readout time (s; default: the "
                        "camera's)")
    p.add_argument("--no-depth-residual", action="store_true",
                   help="the tracker without its depth residual (edges alone)")
    p.add_argument("--out-json", type=Path, default=None)
    return p.parse_args(argv)


def _starts(pairs, gt: dict, start: str) -> np.ndarray:
    """T_init (P, 4, 4) = T_target_kf of each pair: identity or constant velocity."""
    out = []
    for (s, i), (_, j) in pairs:
        if start == "identity":
            out.append(np.eye(4))
            continue
        prev, before = gt[(s, j - 1)], gt[(s, j - 2)]
        predicted = prev @ inverse_np(before) @ prev  # T_world_target, constant velocity
        out.append(inverse_np(predicted) @ gt[(s, i)])
    return np.stack(out).astype(np.float32)


def smooth_rows(data, ki, fi, T_gt, T_init, thresholds, config) -> list[tuple]:
    """(t, r, edges) per threshold of the smooth mode."""
    params = Params.default(config, jnp.float32)

    def one(ki, fi, T, T0, threshold):
        kf = jax.tree.map(lambda x: x[ki], data["kf"])
        intr = Intrinsics(*data["intr"][ki])
        dist = tuple(d[fi] for d in data["dist"])
        em = jax.tree.map(lambda x: x[fi], data["edge_map"])
        uv, _ = warp(intr, Pose.from_matrix(T), unproject(intr, kf.uv, kf.rho))
        r, _, _ = bicubic_with_grad(dist[0], uv)
        kf = kf._replace(valid=kf.valid & (r <= threshold))
        out = track_smooth(kf, dist, em, T0, intr, params, config)
        return (*relative_pose_error(out.T_c_k, T), jnp.sum(kf.valid))

    run = jax.jit(jax.vmap(one, in_axes=(0, 0, 0, 0, None)))
    return [tuple(np.asarray(x) for x in run(ki, fi, T_gt, jnp.asarray(T_init), th))
            for th in thresholds]


def tracker_rows(seq, pairs, gt, frames, data, T_init, thresholds, config,
                 readout_s: float, refine: bool = False) -> list[tuple]:
    """(t, r, edges) per threshold of the tracker's solve (module docstring); ``refine``:
    the solves of the finite thresholds start from the first threshold's result."""
    intr = Intrinsics(*(float(v) for v in seq.intrinsics))
    structure, knobs = solve_structure(config), solve_knobs(config)
    solve = jax.jit(track, static_argnames="config")

    @jax.jit
    def residuals(kf, field, T, shutter):
        pose = Pose.from_matrix(T)
        rows = row_motion(pose, shutter, 0, field.shape[0])
        r, _, ok, _, _ = residual_jacobian_grad(field, intr, pose,
                                                unproject(intr, kf.uv, kf.rho), rows)
        return jnp.where(ok, r, jnp.inf)

    def rate(f: int) -> float:
        dt = float(seq.timestamps[f] - seq.timestamps[f - 1])
        return shutter_rate(readout_s, frames[(0, f)].shape[0], dt)

    keyframes: dict = {}
    out = [([], [], []) for _ in thresholds]
    for p, ((s, i), (_, j)) in enumerate(pairs):
        if (s, i) not in keyframes:
            frame = frames[(s, i)]
            k = data["kf_index"][(s, i)]
            edges = KeyframeEdges(*(np.asarray(getattr(data["kf"], f)[k]) for f in
                                    ("uv", "rho", "grad", "valid", "mag")),
                                  disc=np.asarray(data["kf"].disc[k]))
            if readout_s > 0:
                twist = rate(i) * log_np(inverse_np(gt[(s, i - 1)]) @ gt[(s, i)])
                edges = unroll_edges(edges, twist, intr, frame.shape[0])
            if config.depth_residual and frame.depth is not None:
                edges = edges._replace(**dict(zip(("depth_pts", "depth_normals"), depth_points(
                    frame.depth, intr, config.depth_points, min_depth=config.min_depth,
                    max_depth=config.max_depth, seed=config.seed + i), strict=True)))
            keyframes[(s, i)] = KeyframeEdges(*jax.tree.map(jnp.asarray, edges))
        kf, frame = keyframes[(s, i)], frames[(s, j)]
        T_true = (inverse_np(gt[(s, j)]) @ gt[(s, i)]).astype(np.float32)
        shutter = Shutter(jnp.asarray(inverse_np(gt[(s, j - 1)]) @ gt[(s, i)], jnp.float32),
                          jnp.float32(rate(j)))
        r = np.asarray(residuals(kf, frame.dist[0], T_true, shutter))
        start = T_init[p]
        for row, th in zip(out, thresholds, strict=True):
            masked = kf._replace(valid=kf.valid & jnp.asarray(r <= th))
            res = solve(masked, frame.dist, frame.edge_map, start, intr, config=structure,
                        knobs=knobs, shutter=shutter if readout_s > 0 else None)
            if refine and np.isinf(th):
                start = np.asarray(res.T_c_k)
            t_err, r_err = relative_pose_error(res.T_c_k, jnp.asarray(T_true))
            row[0].append(float(t_err))
            row[1].append(float(r_err))
            row[2].append(int(np.sum(masked.valid)))
    return [tuple(np.asarray(x) for x in row) for row in out]


def main(argv: list[str] | None = None) -> int:
    enable_batch_exact()
    args = parse_args(argv)
    runs = [tuple(r.split(":")) for r in args.runs.split(",")]
    if any(len(r) != 2 or r[0] not in SOLVERS or r[1] not in STARTS for r in runs):
        print(f"--runs takes comma-separated solver:start, solver of {', '.join(SOLVERS)}, "
              f"start of {', '.join(STARTS)}; got {args.runs}", file=sys.stderr)
        return 2
    seqs = load_all([args.sequence], args.frame_step)
    if isinstance(seqs, str):
        print(seqs, file=sys.stderr)
        return 2
    seq = seqs[0]
    config = Config(num_edges=args.num_edges, depth_residual=not args.no_depth_residual)
    readout_s = (args.readout_s if args.readout_s is not None else
                 config.readout_s if config.readout_s is not None else
                 float(getattr(seq, "readout_s", 0.0) or 0.0))
    a, b = (int(x) for x in args.frames.split(":"))
    part = make_part(seq, 0, (a, b))
    gt = {(0, f): T for f, T in part.gt.items()}
    pairs = [pr for pr in part.pairs([int(g) for g in args.gaps.split(",")])
             if (0, pr[0][1] - 1) in gt and (0, pr[1][1] - 2) in gt]
    if not pairs:
        print(f"no pairs with ground truth in frames {a}:{b} (the keyframe's previous frame "
              "and the frame two before the target need it too)", file=sys.stderr)
        return 2
    t0 = time.perf_counter()
    frames: dict = {}
    used = sorted({f for pr in pairs for f in pr})
    data = build_data(seqs, used, sorted({i for i, _ in pairs}), config, args.seed,
                      keep=frames)
    ki, fi, T_gt = pair_arrays(pairs, gt, data)
    thresholds = [np.inf] + [float(x) for x in args.thresholds.split(",")]
    print(f"{seq.name}: {len(pairs)} pairs in frames {part.frames[0]}:{part.frames[1]}, "
          f"readout {readout_s * 1e3:g} ms (tracker)", flush=True)
    report = {"sequence": str(seq.root), "name": seq.name, "frame_step": args.frame_step,
              "frames": list(part.frames), "gaps": args.gaps, "pairs": len(pairs),
              "num_edges": args.num_edges, "seed": args.seed, "rot_weight": args.rot_weight,
              "command": "python scripts/weighting_bound.py "
              + " ".join(sys.argv[1:] if argv is None else argv), "runs": {}}
    for solver, start in runs:
        if start == "refine" and solver != "tracker":
            print("the refine start is the tracker's (tracker:refine)", file=sys.stderr)
            return 2
        T_init = _starts(pairs, gt, "velocity" if start == "refine" else start)
        if solver == "smooth":
            rows = smooth_rows(data, ki, fi, T_gt, T_init, thresholds, config)
            note = ("learn.track_smooth, default Params: global shutter, no depth residual; "
                    "oracle residual bicubic, global shutter")
        else:
            rows = tracker_rows(seq, pairs, gt, frames, data, T_init, thresholds, config,
                                readout_s, refine=start == "refine")
            note = (f"frontend.align.track (LM, hard decisions), depth residual "
                    f"{config.depth_residual}, rolling shutter {readout_s * 1e3:g} ms driven "
                    "by the ground truth; oracle residual bilinear with that shutter")
        table = []
        for threshold, (t, r, n) in zip(thresholds, rows, strict=True):
            loss = t + args.rot_weight * r
            row = {"threshold_px": None if np.isinf(threshold) else threshold,
                   "loss": float(np.mean(loss)), "loss_median": float(np.median(loss)),
                   "pairs_over_1cm": int(np.sum(t > 0.01)),
                   "t_mean_mm": float(np.mean(t) * 1e3),
                   "t_median_mm": float(np.median(t) * 1e3),
                   "r_mean_deg": float(np.degrees(np.mean(r))),
                   "edges_mean": float(np.mean(n))}
            for key, base in (("change_pct", "loss"), ("median_change_pct", "loss_median")):
                row[key] = 100.0 * (row[base] / table[0][base] - 1.0) if table else 0.0
            table.append(row)
            label = ("every edge" if np.isinf(threshold)
                     else f"true-pose residual <= {threshold} px")
            print(f"{solver}:{start} {label:32s} loss {row['loss']:.6f} ({row['change_pct']:+.1f} "
                  f"%; median {row['median_change_pct']:+.1f} %), pair t mean "
                  f"{row['t_mean_mm']:.2f} mm, median {row['t_median_mm']:.2f} mm, r mean "
                  f"{row['r_mean_deg']:.3f} deg, {row['edges_mean']:.0f} edges, "
                  f"{row['pairs_over_1cm']} pairs over 1 cm", flush=True)
        best = min(row["change_pct"] for row in table)
        best_median = min(row["median_change_pct"] for row in table)
        print(f"{solver}:{start}: oracle bound {-best:.1f} % of the mean loss, "
              f"{-best_median:.1f} % of the median", flush=True)
        report["runs"][f"{solver}:{start}"] = {"note": note, "rows": table, "bound_pct": -best,
                                               "median_bound_pct": -best_median}
    report["seconds"] = time.perf_counter() - t0
    if args.out_json:
        args.out_json.parent.mkdir(parents=True, exist_ok=True)
        args.out_json.write_text(json.dumps(report, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
