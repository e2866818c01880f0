"""Time ``map.pose_graph.optimise`` beside GTSAM 4.3 on the same graphs (one line per graph and
solver, and a JSON file).

The graphs (``map.synthetic_graphs``): keyframe laps around a room of each ``--keyframes``
size (tracking and window edges, a robust loop edge every ~N/10 keyframes) and, with
``--sphere``, the sphere2500-like sphere (50 rings of 50 poses, odometry and loop edges),
each solved from its drifted odometry chain with node 0 fixed. Ours: cold (the first call:
tracing, compiling and one solve) and warm (mean and median of ``--repeats`` calls) with
each ``--solvers`` linear solver; GTSAM (when installed; a peer only, never a dependency of
edgevo_jax): ``LevenbergMarquardtOptimizer`` with its default parameters, the first call and
``--repeats`` more, in float64. With ``--gradient``, also reverse mode through ours (the
gradient of the optimised positions' sum of squares in every edge's measurement and
information: the implicit derivative), cold and warm. Both final costs on one definition
(``synthetic_graphs.cost``, float64: sum of 0.5 rho(r^T Omega r), Cauchy on the robust
edges; GTSAM's ``BetweenFactorPose3`` error is the same twist, rotation first), LM tries,
and the ATE (RMS position error, m) of the start and of each solution against the truth.

    python scripts/pose_graph_time.py --keyframes 100,1000,5000 --sphere --solvers direct,cg
    python scripts/pose_graph_time.py --keyframes 100,1000,5000 --sphere --dtype float64
"""

from __future__ import annotations

import argparse
import importlib.metadata
import json
import statistics
import sys
import time
from pathlib import Path

import jax
import numpy as np

from edgevo_jax.map import synthetic_graphs as sg
from edgevo_jax.map.pose_graph import ROBUST_SCALE, PoseGraph, optimise

ROTATION_FIRST = [3, 4, 5, 0, 1, 2]  # our twist [v, w] -> GTSAM's Pose3 tangent [w, v]


def timed(call, repeats: int) -> tuple[float, list[float], object]:
    """The first call's seconds, the next ``repeats`` calls' milliseconds, the last output."""
    t0 = time.perf_counter()
    out = call()
    cold = time.perf_counter() - t0
    warm = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = call()
        warm.append(1e3 * (time.perf_counter() - t0))
    return cold, warm, out


def summary(cold: float, warm: list[float], g: PoseGraph, poses, truth, tries: int) -> dict:
    """One row's numbers: times, LM tries, the cost (float64) and the ATE of ``poses``."""
    return {"cold_s": round(cold, 3), "mean_ms": round(statistics.mean(warm), 2),
            "median_ms": round(statistics.median(warm), 2), "repeats": len(warm),
            "iterations": tries, "cost": round(sg.cost(g, poses), 6),
            "ate_m": round(sg.ate(poses, truth), 5)}


def ours(g: PoseGraph, truth: np.ndarray, solver: str, repeats: int) -> dict:
    """``optimise`` with ``linear_solver=solver``, compiled afresh."""
    jax.clear_caches()
    cold, warm, sol = timed(lambda: jax.block_until_ready(optimise(g, linear_solver=solver)),
                            repeats)
    return {"solver": solver, **summary(cold, warm, g, sol.poses, truth, int(sol.iterations))}


def gradient(g: PoseGraph, solver: str, repeats: int) -> dict:
    """Reverse mode through ``optimise`` (``linear_solver=solver``): the gradient of the sum of
    the optimised positions' squares in every edge's measurement and information."""
    def loss(measured, information):
        sol = optimise(g._replace(measured=measured, information=information),
                       linear_solver=solver)
        return (sol.poses[:, :3, 3] ** 2).sum()

    jax.clear_caches()
    grad = jax.jit(jax.grad(loss, argnums=(0, 1)))
    cold, warm, _ = timed(lambda: jax.block_until_ready(grad(g.measured, g.information)),
                          repeats)
    return {"solver": f"{solver} gradient", "cold_s": round(cold, 3),
            "mean_ms": round(statistics.mean(warm), 2),
            "median_ms": round(statistics.median(warm), 2), "repeats": len(warm)}


def gtsam_problem(gtsam, g: PoseGraph):
    """The same graph for GTSAM: its factor graph, start values and node indices."""
    valid, fixed = np.asarray(g.valid), np.asarray(g.fixed)
    i, j = np.asarray(g.i)[valid], np.asarray(g.j)[valid]
    nodes = sorted(set(i.tolist()) | set(j.tolist()))
    P = np.asarray(g.poses, np.float64)
    graph, start = gtsam.NonlinearFactorGraph(), gtsam.Values()
    for k in nodes:
        start.insert(k, gtsam.Pose3(P[k]))
        if fixed[k]:
            graph.add(gtsam.NonlinearEqualityPose3(k, gtsam.Pose3(P[k])))
    info = np.asarray(g.information, np.float64)[valid][:, ROTATION_FIRST][:, :, ROTATION_FIRST]
    for a, b, Z, om, rob in zip(i, j, np.asarray(g.measured, np.float64)[valid], info,
                                np.asarray(g.robust)[valid], strict=True):
        model = gtsam.noiseModel.Gaussian.Information(om)
        if rob:
            kernel = gtsam.noiseModel.mEstimator.Cauchy.Create(ROBUST_SCALE)
            model = gtsam.noiseModel.Robust.Create(kernel, model)
        graph.add(gtsam.BetweenFactorPose3(int(a), int(b), gtsam.Pose3(Z), model))
    return graph, start, nodes


def peer(g: PoseGraph, truth: np.ndarray, repeats: int) -> dict | None:
    """GTSAM's Levenberg-Marquardt on the graph, or None (with a message) without GTSAM."""
    try:
        import gtsam
    except ImportError:
        print("GTSAM is not installed (pip install gtsam): its rows are skipped", flush=True)
        return None
    graph, start, nodes = gtsam_problem(gtsam, g)

    def solve():
        optimiser = gtsam.LevenbergMarquardtOptimizer(graph, start,
                                                      gtsam.LevenbergMarquardtParams())
        return optimiser.optimize(), optimiser.iterations()

    cold, warm, (values, tries) = timed(solve, repeats)
    poses = np.asarray(g.poses, np.float64).copy()
    for k in nodes:
        poses[k] = values.atPose3(k).matrix()
    return {"solver": f"gtsam {importlib.metadata.version('gtsam')}",
            **summary(cold, warm, g, poses, truth, int(tries))}


def graphs(args: argparse.Namespace, dtype):
    """(name, graph, truth, loop edges) of each graph asked for."""
    for n in (int(v) for v in args.keyframes.split(",") if v):
        g, truth, loops = sg.laps(n, dtype=dtype)
        yield f"laps {n}", g, truth, loops
    if args.sphere:
        g, truth = sg.sphere(dtype=dtype)
        yield "sphere2500", g, truth, int(np.sum(np.asarray(g.j) - np.asarray(g.i) > 1))


def main(argv: list[str] | None = None) -> None:
    """Parse the arguments, time each graph, print one line per solver and write the JSON."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--keyframes", default="100,1000", help="comma-separated sizes")
    parser.add_argument("--sphere", action="store_true", help="also the sphere2500-like graph")
    parser.add_argument("--solvers", default="direct", help="ours: direct and/or cg")
    parser.add_argument("--no-gtsam", action="store_true", help="skip the GTSAM peer")
    parser.add_argument("--gradient", action="store_true", help="also time jax.grad (ours)")
    parser.add_argument("--dtype", default="float32", choices=["float32", "float64"])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--out", type=Path, default=Path("docs/map/pose_graph_scales.json"))
    args = parser.parse_args(argv)
    jax.config.update("jax_enable_x64", args.dtype == "float64")
    rows = []
    for name, g, truth, loops in graphs(args, np.dtype(args.dtype)):
        head = {"graph": name, "nodes": len(truth), "edges": int(np.sum(np.asarray(g.valid))),
                "loop_edges": loops, "node_slots": int(g.fixed.shape[0]),
                "edge_slots": int(g.valid.shape[0]), "dtype": args.dtype,
                "start_cost": round(sg.cost(g, g.poses), 3),
                "ate_start_m": round(sg.ate(g.poses, truth), 5)}
        solvers = args.solvers.split(",")
        found = [ours(g, truth, s, args.repeats) for s in solvers]
        found += [] if args.no_gtsam else [peer(g, truth, args.repeats)]
        found += [gradient(g, s, args.repeats) for s in solvers if args.gradient]
        for row in filter(None, found):
            rows.append({**head, **row})
            print(f"{name:11s} {row['solver']:15s} cold {row['cold_s']:6.2f} s  warm mean "
                  f"{row['mean_ms']:8.1f} ms median {row['median_ms']:8.1f} ms", end="")
            print("" if "cost" not in row else f"  tries {row['iterations']:3d}  cost "
                  f"{row['cost']:.4f}  ATE {head['ate_start_m']:.3f} -> {row['ate_m']:.4f} m",
                  flush=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    command = " ".join(["python scripts/pose_graph_time.py", *(argv or sys.argv[1:])])
    args.out.write_text(json.dumps({"device": jax.devices()[0].device_kind, "command": command,
                                    "rows": rows}, indent=2) + "\n")


if __name__ == "__main__":
    main()
