"""Huber-weighted Gauss-Newton (Levenberg-Marquardt) alignment of keyframe edges to a frame's
distance fields, coarse to fine over the pyramid, with the covariance (J^T W J)^-1 at the end.

Per level l: residuals above ``max_residual[l]`` and matches with g(p).g(p') < eta are
rejected, the rest weighted by Huber (radius ``huber_delta[l]``), and the left update
xi = -(J^T W J + lam diag)^-1 J^T W r applied as T <- exp(xi) T when it lowers the robust cost.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np

from .camera import Intrinsics, unproject
from .config import Config
from .geometry import retract_left
from .interp import EdgeMap
from .residuals import consistency_dots_at_level, residual_jacobian_grad, warp
from .robust import EdgeWeighting, edge_weights, huber_cost, huber_weights


class KeyframeEdges(NamedTuple):
    """Fixed-size edge set of a keyframe (struct of arrays): uv (2, K) level-0 pixels,
    rho (K,) inverse depth (1/m), grad (2, K) normalised image gradient, valid (K,) bool
    (padding slots are False and hold rho = 1), and mag (K,) the gradient magnitude (0 in
    padding slots; None when not known: only the per-edge weighting model reads it)."""

    uv: jnp.ndarray
    rho: jnp.ndarray
    grad: jnp.ndarray
    valid: jnp.ndarray
    mag: jnp.ndarray | None = None


class SolveKnobs(NamedTuple):
    """The numeric settings of the solve as arrays (a pytree), so that one compiled program
    serves many configurations (``batch.py`` vmaps over them): per level huber_delta (L,) and
    max_residual (L,) in that level's pixels, iterations (L,) int32; eta () and step_tol ().
    ``weighting``: the learnable per-edge weighting model (``robust.EdgeWeighting``, from
    ``params.solve_knobs_of``), or None (the plain tracker; a None compiles without it)."""

    huber_delta: jnp.ndarray
    max_residual: jnp.ndarray
    eta: jnp.ndarray
    iterations: jnp.ndarray
    step_tol: jnp.ndarray
    weighting: EdgeWeighting | None = None


def solve_knobs(config: Config) -> SolveKnobs:
    """The ``SolveKnobs`` of a Config (numpy arrays, float32 and int32)."""
    return SolveKnobs(
        huber_delta=np.asarray(config.huber_delta, np.float32),
        max_residual=np.asarray(config.max_residual, np.float32),
        eta=np.asarray(config.eta, np.float32),
        iterations=np.asarray(config.iterations, np.int32),
        step_tol=np.asarray(config.step_tol, np.float32),
    )


def solve_structure(config: Config) -> Config:
    """The static part of the solve once ``SolveKnobs`` carry its numbers: the number of
    pyramid levels, as a default Config with that many levels, so that configurations that
    differ in numbers only share one compiled program."""
    n = config.num_levels
    return Config(iterations=(10,) * n, huber_delta=(1.0,) * n, max_residual=(5.0,) * n)


class LevelSystem(NamedTuple):
    """Weighted normal equations at one pose: H = J^T W J (6, 6), g = J^T W r (6,), the
    truncated robust cost (see ``normal_equations``), inlier count, residuals r (K,) and the
    inlier mask (K,)."""

    H: jnp.ndarray
    g: jnp.ndarray
    cost: jnp.ndarray
    inliers: jnp.ndarray
    r: jnp.ndarray
    mask: jnp.ndarray


class TrackResult(NamedTuple):
    """Output of one alignment: the pose T_cur_kf (4, 4), its covariance (6, 6) over a left
    twist [v, w], level-0 inliers, mean inlier residual (px), the RMS optical flow of the
    visible edges with and without rotation (px), how many edges warp into the image, and
    the level-0 robust cost (Huber, the gate's cost for each rejected edge)."""

    T_c_k: jnp.ndarray
    covariance: jnp.ndarray
    inliers: jnp.ndarray
    mean_residual: jnp.ndarray
    flow: jnp.ndarray
    flow_t: jnp.ndarray
    visible: jnp.ndarray
    cost: jnp.ndarray


def level_to_0(uv_l: jnp.ndarray, level: int) -> jnp.ndarray:
    """Level-l pixel coordinates to level 0 (pixel-centre origin)."""
    return (uv_l + 0.5) * (2.0**level) - 0.5


def normal_equations(
    T: jaxlie.SE3,
    pts_k: jnp.ndarray,
    kf: KeyframeEdges,
    field: jnp.ndarray,
    edge_map: EdgeMap,
    intr: Intrinsics,
    level: int,
    knobs: SolveKnobs,
) -> LevelSystem:
    """Gated, Huber-weighted normal equations of the distance residuals at pose T.

    pts_k (3, K): the keyframe edges back-projected. The cost that Levenberg-Marquardt
    compares is a proper function of the pose: the Huber cost of each inlier, and for every
    other valid keyframe edge (gated, inconsistent or out of view) the Huber cost of the gate,
    so that rejecting a match never lowers the cost.
    """
    r, J, ok, uv_c, grad = residual_jacobian_grad(field, intr.at_level(level), T, pts_k)
    consistent = consistency_dots_at_level(kf.grad, edge_map, uv_c, r, grad, level) >= knobs.eta
    delta, gate = knobs.huber_delta[level], knobs.max_residual[level]
    mask = kf.valid & ok & (r <= gate) & consistent
    if knobs.weighting is None:
        return robust_system(r, J, mask, kf.valid, delta, gate)
    if kf.mag is None:
        raise ValueError("the per-edge weighting model needs KeyframeEdges.mag")
    weight, slope = edge_weights(knobs.weighting, kf.mag, kf.rho, r, gate, level)
    return robust_system(r, J, mask, kf.valid, delta, gate, weight=weight, weight_slope=slope)


def robust_system(
    r: jnp.ndarray,
    J: jnp.ndarray,
    mask: jnp.ndarray,
    valid: jnp.ndarray,
    delta: float | jnp.ndarray,
    gate: float | jnp.ndarray,
    weight: jnp.ndarray | None = None,
    reject: jnp.ndarray | None = None,
    weight_slope: jnp.ndarray | None = None,
) -> LevelSystem:
    """Huber-weighted normal equations of residuals r (K,) with Jacobian J (6, K) over the
    inliers ``mask``; every other ``valid`` edge costs the gate's Huber cost.

    Optional (the differentiable path of ``learn.py``): ``weight`` (K,) scales each inlier's
    Huber weight and cost; ``reject`` (K,) in [0, 1] adds that fraction of the gate's cost to
    an inlier (a soft rejection); ``weight_slope`` (K,) is d weight / dr when the weight
    depends on the residual, so that g stays the gradient of the cost (the term
    weight_slope * Huber cost joins J^T W r; H keeps the Gauss-Newton weights). Without them
    this is the plain tracker's system.
    """
    w = huber_weights(r, delta)
    inlier_cost = huber_cost(r, delta)
    if weight is not None:
        w, inlier_cost = weight * w, weight * inlier_cost
    if reject is not None:
        inlier_cost = inlier_cost + reject * huber_cost(gate, delta)
    w = jnp.where(mask, w, 0.0)
    Jw = J * w
    g = Jw @ r
    if weight_slope is not None:
        g = g + J @ jnp.where(mask, weight_slope * huber_cost(r, delta), 0.0)
    outside = jnp.where(valid, huber_cost(gate, delta), 0.0)
    cost = jnp.sum(jnp.where(mask, inlier_cost, outside))
    # dots, not sums of products: XLA's dots give a run the same result whatever the batch
    # size (its vectorised reductions do not), which batch.py's equality relies on
    return LevelSystem(H=Jw @ J.T, g=g, cost=cost, inliers=jnp.sum(mask), r=r, mask=mask)


def damped_step(system: LevelSystem, lam: jnp.ndarray) -> jnp.ndarray:
    """Levenberg-Marquardt step xi = -(H + lam diag(H))^-1 g; zero when not finite."""
    H = system.H
    eye = jnp.eye(6, dtype=H.dtype)
    A = H + lam * H * eye + 1e-9 * (jnp.trace(H) + 1.0) * eye
    xi = -jnp.linalg.solve(A, system.g)
    ok = jnp.all(jnp.isfinite(xi)) & (system.inliers >= 6)
    return jnp.where(ok, xi, jnp.zeros_like(xi))


def lm_iteration(
    system_at: Callable[[jaxlie.SE3], LevelSystem],
    T: jaxlie.SE3,
    system: LevelSystem,
    lam: jnp.ndarray,
) -> tuple[jaxlie.SE3, LevelSystem, jnp.ndarray, jnp.ndarray]:
    """One Levenberg-Marquardt try from pose T with its normal equations ``system``: the
    damped step is kept when ``system_at`` says it lowers the robust cost; lam shrinks 10x
    after a kept step and grows 10x after a rejected one. Returns the pose, its system, the
    new lam and the step's norm (a rejected step this short only shrinks further)."""
    xi = damped_step(system, lam)
    T_new = retract_left(T, xi)
    sys_new = system_at(T_new)
    better = sys_new.cost < system.cost
    T, system = jax.tree.map(
        lambda a, b: jnp.where(better, a, b), (T_new, sys_new), (T, system)
    )
    lam = jnp.clip(jnp.where(better, lam * 0.1, lam * 10.0), 1e-6, 1e4)
    return T, system, lam, jnp.linalg.norm(xi)


def align_level(
    T: jaxlie.SE3,
    pts_k: jnp.ndarray,
    kf: KeyframeEdges,
    field: jnp.ndarray,
    edge_map: EdgeMap,
    intr: Intrinsics,
    level: int,
    knobs: SolveKnobs,
) -> tuple[jaxlie.SE3, LevelSystem]:
    """Levenberg-Marquardt on the Huber-weighted (Gauss-Newton) normal equations at one level;
    returns the pose and the normal equations at it.

    A step is kept only when it lowers the robust cost (the coarse, non-smooth distance fields
    make plain Gauss-Newton oscillate); lam shrinks 10x after a kept step and grows 10x after
    a rejected one. lax.while_loop: fixed shapes, stop after ``knobs.iterations[level]`` tries
    or once a step, kept or not, is shorter than ``knobs.step_tol``.
    """

    def system_at(T):
        return normal_equations(T, pts_k, kf, field, edge_map, intr, level, knobs)

    def cond(state):
        i, _, _, _, step = state
        return (i < knobs.iterations[level]) & (step >= knobs.step_tol)

    def body(state):
        i, T, sys, lam, _ = state
        T, sys, lam, step = lm_iteration(system_at, T, sys, lam)
        return i + 1, T, sys, lam, step

    dtype = pts_k.dtype
    init = (jnp.asarray(0), T, system_at(T), jnp.asarray(1e-4, dtype), jnp.asarray(jnp.inf, dtype))
    _, T, system, _, _ = jax.lax.while_loop(cond, body, init)
    return T, system


def rms_flow(uv_from: jnp.ndarray, uv_to: jnp.ndarray, mask: jnp.ndarray) -> jnp.ndarray:
    """Root mean squared pixel displacement (2, K) -> scalar over the masked points."""
    sq = jnp.sum((uv_to - uv_from) ** 2, axis=0)
    return jnp.sqrt(jnp.sum(jnp.where(mask, sq, 0.0)) / jnp.maximum(jnp.sum(mask), 1))


def track(
    kf: KeyframeEdges,
    dist: tuple[jnp.ndarray, ...],
    edge_map: EdgeMap,
    T_init: jnp.ndarray,
    intr: Intrinsics,
    config: Config,
    knobs: SolveKnobs | None = None,
) -> TrackResult:
    """Align keyframe edges to the frame's distance-field pyramid, coarsest level first.

    dist: one field per level (H / 2**l, W / 2**l); edge_map: the frame's ``interp.EdgeMap``;
    T_init: (4, 4) initial T_cur_kf. Jit with ``config`` static; its numbers are read from
    ``knobs`` (default: ``solve_knobs(config)``), which may be traced.
    """
    knobs = solve_knobs(config) if knobs is None else knobs
    pts_k = unproject(intr, kf.uv, kf.rho)
    T = jaxlie.SE3.from_matrix(T_init)
    for level in reversed(range(config.num_levels)):
        T, final = align_level(T, pts_k, kf, dist[level], edge_map, intr, level, knobs)
    return track_result(T, final, pts_k, kf, dist[0].shape, intr)


def track_result(
    T: jaxlie.SE3,
    final: LevelSystem,
    pts_k: jnp.ndarray,
    kf: KeyframeEdges,
    shape: tuple[int, int],
    intr: Intrinsics,
) -> TrackResult:
    """The TrackResult of an alignment that ended at pose T with level-0 normal equations
    ``final``: covariance, inlier statistics and the optical flow of the visible edges;
    shape (H, W) of level 0."""
    H = final.H + 1e-9 * (jnp.trace(final.H) + 1.0) * jnp.eye(6, dtype=final.H.dtype)
    # optical flow of the edges that stay in view, with and without rotation (keyframe rule)
    uv_c, pts_c = warp(intr, T, pts_k)
    h, w = shape
    visible = (
        kf.valid & (pts_c[2] > 1e-6) & (uv_c[0] >= 0) & (uv_c[0] <= w - 1)
        & (uv_c[1] >= 0) & (uv_c[1] <= h - 1)
    )
    uv_t, _ = warp(intr, jaxlie.SE3.from_translation(T.translation()), pts_k)
    return TrackResult(
        T_c_k=T.as_matrix(),
        covariance=jnp.linalg.inv(H),
        inliers=final.inliers,
        mean_residual=jnp.sum(jnp.where(final.mask, final.r, 0.0)) / jnp.maximum(final.inliers, 1),
        flow=rms_flow(kf.uv, uv_c, visible),
        flow_t=rms_flow(kf.uv, uv_t, visible),
        visible=jnp.sum(visible),
        cost=final.cost,
    )
