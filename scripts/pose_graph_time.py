"""Time ``backend.pose_graph.optimise`` on synthetic keyframe graphs (one line per size, and a
JSON file).

The graph: keyframes every 0.1 m along laps around a room (an ellipse of 1.5 m x 1.0 m
semi-axes whose size and height vary from lap to lap, the camera looking along the path with
a little pitch and roll), node 0 fixed at the truth. Tracking edges (k-1 -> k) and window
edges (k-2 -> k) measure the true relative poses with noise drawn from a plausible tracking
covariance (5 mm and 3 mrad per keyframe, a little correlated); their information is that
covariance's inverse. The start is the chain of tracking edges (it drifts). Every ~N/10
keyframes a robust loop edge ties the keyframe to the nearest one of an earlier lap
(2 cm / 10 mrad noise). Reported: compile time, warm time (mean and median of ``--repeats``
calls), LM tries, and the ATE (RMS position error, m) of the start and of the solution
against the truth.

    python scripts/pose_graph_time.py --keyframes 100,1000 --repeats 5
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import jax
import numpy as np

from edgevo_jax.geometry import exp_np, inverse_np
from edgevo_jax.map.pose_graph import PoseGraph, graph, optimise

SPACING = 0.1  # m between keyframes


def trajectory(n: int) -> np.ndarray:
    """n true poses T_world_cam (n, 4, 4) along the laps (module doc)."""
    s = SPACING * np.arange(n)
    # the ellipse's perimeter is ~7.9 m; the angle is close enough to arc length / radius
    phase = 2.0 * np.pi * s / 7.9
    lap = s / 7.9
    scale = 1.0 + 0.08 * np.sin(1.3 * lap)
    pos = np.stack([1.5 * scale * np.cos(phase), 1.0 * scale * np.sin(phase),
                    1.2 + 0.1 * np.sin(0.7 * lap + phase)], -1)
    out = np.zeros((n, 4, 4))
    for k in range(n):
        yaw = np.arctan2(1.0 * scale[k] * np.cos(phase[k]), -1.5 * scale[k] * np.sin(phase[k]))
        tilt = [0.05 * np.sin(3.0 * phase[k]), 0.03 * np.cos(5.0 * phase[k]), yaw]
        out[k] = exp_np(np.array([0.0, 0.0, 0.0, 0.0, 0.0, tilt[2]])) @ exp_np(
            np.array([0.0, 0.0, 0.0, tilt[0], tilt[1], 0.0]))
        out[k, :3, 3] = pos[k]
    return out


def covariance(rng: np.random.Generator, sigma_t: float, sigma_r: float) -> np.ndarray:
    """A 6x6 covariance with these standard deviations, mildly correlated."""
    L = np.diag([sigma_t] * 3 + [sigma_r] * 3) @ (np.eye(6) + 0.2 * rng.normal(size=(6, 6)))
    return L @ L.T


def synthetic(n: int, seed: int = 0) -> tuple[PoseGraph, np.ndarray, int]:
    """The graph (module doc), its true poses and its number of loop edges."""
    rng = np.random.default_rng(seed)
    truth = trajectory(n)
    edges = []

    def edge(a: int, b: int, cov: np.ndarray, robust: bool) -> np.ndarray:
        r = rng.multivariate_normal(np.zeros(6), cov)
        Z = inverse_np(truth[a]) @ truth[b] @ exp_np(-r)  # T_a^-1 T_b = Z exp(r)
        edges.append((a, b, Z, np.linalg.inv(cov), robust))
        return Z

    start = [truth[0]]
    for k in range(1, n):
        start.append(start[-1] @ edge(k - 1, k, covariance(rng, 0.005, 0.003), False))
        if k >= 2:
            edge(k - 2, k, covariance(rng, 0.008, 0.004), False)
    loops = 0
    for k in range(max(n // 10, 1), n, max(n // 10, 1)):
        earlier = np.arange(max(k - 40, 0))
        if earlier.size:
            gaps = np.linalg.norm(truth[earlier, :3, 3] - truth[k, :3, 3], axis=1)
            near = earlier[np.argmin(gaps)]
            if np.linalg.norm(truth[near, :3, 3] - truth[k, :3, 3]) < 0.5:
                edge(int(near), k, covariance(rng, 0.02, 0.01), True)
                loops += 1
    return graph(np.stack(start), edges, fixed=[0]), truth, loops


def ate(poses: np.ndarray, truth: np.ndarray) -> float:
    """RMS position error (m) of the first len(truth) poses (node 0 is the common gauge)."""
    d = np.asarray(poses)[: len(truth), :3, 3] - truth[:, :3, 3]
    return float(np.sqrt(np.mean(np.sum(d * d, axis=1))))


def bench(n: int, repeats: int) -> dict:
    """Compile and time ``optimise`` on the synthetic graph of n keyframes."""
    g, truth, loops = synthetic(n)
    t0 = time.perf_counter()
    sol = jax.block_until_ready(optimise(g))
    compile_s = time.perf_counter() - t0
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        sol = jax.block_until_ready(optimise(g))
        times.append(1e3 * (time.perf_counter() - t0))
    return {"keyframes": n, "edges": int(g.valid.sum()), "loop_edges": loops,
            "node_slots": int(g.fixed.shape[0]), "edge_slots": int(g.valid.shape[0]),
            "compile_s": round(compile_s, 3), "mean_ms": round(statistics.mean(times), 2),
            "median_ms": round(statistics.median(times), 2), "repeats": repeats,
            "iterations": int(sol.iterations), "ate_start_m": round(ate(g.poses, truth), 4),
            "ate_solution_m": round(ate(sol.poses, truth), 4)}


def main(argv: list[str] | None = None) -> None:
    """Parse the arguments, time each size, print one line each and write the JSON."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--keyframes", default="100,1000", help="comma-separated sizes")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--out", type=Path, default=Path("docs/map/pose_graph_time.json"))
    args = parser.parse_args(argv)
    rows = []
    for n in (int(v) for v in args.keyframes.split(",")):
        row = bench(n, args.repeats)
        rows.append(row)
        print(f"N={n:5d} edges={row['edges']:5d} loops={row['loop_edges']:3d} "
              f"compile {row['compile_s']:.2f} s  warm mean {row['mean_ms']:.1f} ms "
              f"median {row['median_ms']:.1f} ms  LM tries {row['iterations']:3d}  "
              f"ATE {row['ate_start_m']:.3f} -> {row['ate_solution_m']:.3f} m", flush=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"device": jax.devices()[0].device_kind, "sizes": rows},
                                   indent=2) + "\n")


if __name__ == "__main__":
    main()
