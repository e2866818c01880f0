"""Synthetic pose graphs to measure and test ``pose_graph`` on, with their true poses, and the
graph's cost of any poses on the host.

- ``laps``: a keyframe map. Keyframes every 0.1 m along laps around a room (an ellipse of
  1.5 m x 1.0 m semi-axes whose size and height vary from lap to lap, the camera looking
  along the path with a little pitch and roll), node 0 fixed at the truth. Tracking edges
  (k-1 -> k) and window edges (k-2 -> k) measure the true relative poses with noise drawn
  from a plausible tracking covariance (5 mm and 3 mrad per keyframe, a little correlated);
  their information is that covariance's inverse. Every ~N/10 keyframes a robust loop edge
  ties the keyframe to the nearest one of an earlier lap (2 cm / 10 mrad noise).
- ``sphere``: the classic "sphere2500" construction (Kaess et al., iSAM): ``rings`` rings of
  ``per_ring`` poses on a sphere, travelled ring after ring (x along the motion, z out of
  the sphere), an odometry edge k-1 -> k and a loop edge k-per_ring -> k, none robust, every
  edge's error drawn from one diagonal covariance.

In both the start is the chain of odometry edges (k-1 -> k) from the true node 0: it
drifts. Every relative pose is Z_ab = T_a^-1 T_b exp(-r), r the edge's drawn error (6,) =
[v (m), w (rad)], so the error at the truth is r (``pose_graph``'s convention). Host
float64 throughout; seeded, so the same arguments give the same graph.
"""

from __future__ import annotations

import numpy as np

from ..geometry import exp_np, inverse_np, log_np
from .pose_graph import ROBUST_SCALE, PoseGraph, graph

SPACING = 0.1  # m between the keyframes of ``laps``

#: an edge as ``pose_graph.graph`` takes it: (i, j, Z_ij (4, 4), information (6, 6), robust)
Edge = tuple[int, int, np.ndarray, np.ndarray, bool]


def _covariance(rng: np.random.Generator, sigma_t: float, sigma_r: float) -> np.ndarray:
    """A 6x6 covariance with these standard deviations (m, rad), mildly correlated."""
    L = np.diag([sigma_t] * 3 + [sigma_r] * 3) @ (np.eye(6) + 0.2 * rng.normal(size=(6, 6)))
    return L @ L.T


def _edge(rng: np.random.Generator, truth: np.ndarray, a: int, b: int, cov: np.ndarray,
          robust: bool) -> Edge:
    """Edge a -> b with an error drawn from ``cov``, its information cov^-1."""
    r = rng.multivariate_normal(np.zeros(6), cov)
    return a, b, inverse_np(truth[a]) @ truth[b] @ exp_np(-r), np.linalg.inv(cov), robust


def _chain(truth: np.ndarray, edges: list[Edge]) -> np.ndarray:
    """The start (n, 4, 4): the true node 0, then each node k from k-1 by its edge k-1 -> k."""
    steps = {b: Z for a, b, Z, _, _ in edges if a == b - 1}
    out = [truth[0]]
    for k in range(1, len(truth)):
        out.append(out[-1] @ steps[k])
    return np.stack(out)


def laps_truth(n: int) -> np.ndarray:
    """n true keyframe poses T_world_cam (n, 4, 4) along the laps (module doc)."""
    s = SPACING * np.arange(n)
    phase = 2.0 * np.pi * s / 7.9  # the ellipse's perimeter is ~7.9 m
    lap = s / 7.9
    scale = 1.0 + 0.08 * np.sin(1.3 * lap)
    pos = np.stack([1.5 * scale * np.cos(phase), 1.0 * scale * np.sin(phase),
                    1.2 + 0.1 * np.sin(0.7 * lap + phase)], -1)
    out = np.zeros((n, 4, 4))
    for k in range(n):
        yaw = np.arctan2(1.0 * scale[k] * np.cos(phase[k]), -1.5 * scale[k] * np.sin(phase[k]))
        pitch, roll = 0.05 * np.sin(3.0 * phase[k]), 0.03 * np.cos(5.0 * phase[k])
        out[k] = exp_np(np.array([0.0, 0.0, 0.0, 0.0, 0.0, yaw])) @ exp_np(
            np.array([0.0, 0.0, 0.0, pitch, roll, 0.0]))
        out[k, :3, 3] = pos[k]
    return out


def laps(n: int, seed: int = 0, **kw) -> tuple[PoseGraph, np.ndarray, int]:
    """The keyframe graph of n keyframes (module doc), its true poses (n, 4, 4) and its number
    of loop edges. ``kw`` goes to ``pose_graph.graph`` (slots, dtype; float32 by default)."""
    rng = np.random.default_rng(seed)
    truth = laps_truth(n)
    edges = []
    for k in range(1, n):
        edges.append(_edge(rng, truth, k - 1, k, _covariance(rng, 0.005, 0.003), False))
        if k >= 2:
            edges.append(_edge(rng, truth, k - 2, k, _covariance(rng, 0.008, 0.004), False))
    loops = 0
    every = max(n // 10, 1)
    for k in range(every, n, every):
        earlier = np.arange(max(k - 40, 0))
        if earlier.size:
            gaps = np.linalg.norm(truth[earlier, :3, 3] - truth[k, :3, 3], axis=1)
            if gaps.min() < 0.5:
                near = int(earlier[np.argmin(gaps)])
                edges.append(_edge(rng, truth, near, k, _covariance(rng, 0.02, 0.01), True))
                loops += 1
    return graph(_chain(truth, edges), edges, fixed=[0], **kw), truth, loops


def sphere_truth(rings: int = 50, per_ring: int = 50, radius: float = 50.0) -> np.ndarray:
    """The true poses (rings * per_ring, 4, 4) of ``sphere``: ring r at the polar angle
    pi (r + 0.5) / rings (m), pose m of it at the azimuth 2 pi m / per_ring; x along the
    motion (east), z out of the sphere."""
    k = np.arange(rings * per_ring)
    polar = np.pi * (k // per_ring + 0.5) / rings
    azimuth = 2.0 * np.pi * (k % per_ring) / per_ring
    up = np.stack([np.sin(polar) * np.cos(azimuth), np.sin(polar) * np.sin(azimuth),
                   np.cos(polar)], -1)
    east = np.stack([-np.sin(azimuth), np.cos(azimuth), np.zeros_like(azimuth)], -1)
    out = np.zeros((k.size, 4, 4))
    out[:, :3, 0], out[:, :3, 2] = east, up
    out[:, :3, 1] = np.cross(up, east)
    out[:, :3, 3] = radius * up
    out[:, 3, 3] = 1.0
    return out


def sphere(rings: int = 50, per_ring: int = 50, radius: float = 50.0, sigma_t: float = 0.05,
           sigma_r: float = 0.01, seed: int = 0, **kw) -> tuple[PoseGraph, np.ndarray]:
    """The sphere graph (module doc; the defaults: 2,500 poses, 4,949 edges, like
    "sphere2500"), each edge's error of standard deviations ``sigma_t`` (m) and ``sigma_r``
    (rad), and its true poses. ``kw`` goes to ``pose_graph.graph``."""
    rng = np.random.default_rng(seed)
    truth = sphere_truth(rings, per_ring, radius)
    cov = np.diag([sigma_t**2] * 3 + [sigma_r**2] * 3)
    edges = [_edge(rng, truth, k - 1, k, cov, False) for k in range(1, len(truth))]
    edges += [_edge(rng, truth, k - per_ring, k, cov, False)
              for k in range(per_ring, len(truth))]
    return graph(_chain(truth, edges), edges, fixed=[0], **kw), truth


def cost(g: PoseGraph, poses: np.ndarray, robust_scale: float = ROBUST_SCALE) -> float:
    """The graph's cost (``pose_graph``'s: sum over valid edges of 0.5 rho(r^T Omega r)) at
    ``poses`` (>= the graph's nodes, 4, 4) T_world_node, in float64 on the host."""
    valid = np.asarray(g.valid)
    i, j = np.asarray(g.i)[valid], np.asarray(g.j)[valid]
    P = np.asarray(poses, np.float64)
    Z = np.asarray(g.measured, np.float64)[valid]
    r = log_np(inverse_np(Z) @ inverse_np(P[i]) @ P[j])
    chi2 = np.einsum("ea,eab,eb->e", r, np.asarray(g.information, np.float64)[valid], r)
    c2 = robust_scale**2
    rho = np.where(np.asarray(g.robust)[valid], c2 * np.log1p(chi2 / c2), chi2)
    return float(0.5 * np.sum(rho))


def ate(poses: np.ndarray, truth: np.ndarray) -> float:
    """RMS position error (m) of the first len(truth) poses against the truth (the graphs'
    node 0 is fixed at the truth: no alignment)."""
    d = np.asarray(poses)[: len(truth), :3, 3] - truth[:, :3, 3]
    return float(np.sqrt(np.mean(np.sum(d * d, axis=1))))
