"""Huber-weighted Gauss-Newton (Levenberg-Marquardt) alignment of keyframe edges to a frame's
distance fields, coarse to fine over the pyramid, with the covariance (J^T W J)^-1 at the end.

Per level l: residuals above ``max_residual[l]`` and matches with g(p).g(p') < eta are
rejected, the rest weighted by Huber (radius ``huber_delta[l]``), and the left update
xi = -(J^T W J + lam diag)^-1 J^T W r applied as T <- exp(xi) T when it lowers the robust cost.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import jaxlie

from .camera import Intrinsics, unproject
from .config import Config
from .geometry import retract_left
from .residuals import gradient_consistent, residual_and_jacobian, warp
from .robust import huber_cost, huber_weights


class KeyframeEdges(NamedTuple):
    """Fixed-size edge set of a keyframe (struct of arrays): uv (2, K) level-0 pixels,
    rho (K,) inverse depth (1/m), grad (2, K) normalised image gradient, valid (K,) bool
    (padding slots are False and hold rho = 1)."""

    uv: jnp.ndarray
    rho: jnp.ndarray
    grad: jnp.ndarray
    valid: jnp.ndarray


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
    nearest_grad: jnp.ndarray,
    intr: Intrinsics,
    level: int,
    config: Config,
) -> LevelSystem:
    """Gated, Huber-weighted normal equations of the distance residuals at pose T.

    pts_k (3, K): the keyframe edges back-projected. The cost that Levenberg-Marquardt
    compares is a proper function of the pose: the Huber cost of each inlier, and for every
    other valid keyframe edge (gated, inconsistent or out of view) the Huber cost of the gate,
    so that rejecting a match never lowers the cost.
    """
    r, J, ok, uv_c = residual_and_jacobian(field, intr.at_level(level), T, pts_k)
    consistent = gradient_consistent(kf.grad, nearest_grad, level_to_0(uv_c, level), config.eta)
    delta, gate = config.huber_delta[level], config.max_residual[level]
    mask = kf.valid & ok & (r <= gate) & consistent
    w = jnp.where(mask, huber_weights(r, delta), 0.0)
    Jw = J * w
    outside = jnp.where(kf.valid, huber_cost(gate, delta), 0.0)
    cost = jnp.sum(jnp.where(mask, huber_cost(r, delta), outside))
    return LevelSystem(H=Jw @ J.T, g=Jw @ r, cost=cost, inliers=jnp.sum(mask), r=r, mask=mask)


def damped_step(system: LevelSystem, lam: jnp.ndarray) -> jnp.ndarray:
    """Levenberg-Marquardt step xi = -(H + lam diag(H))^-1 g; zero when not finite."""
    H = system.H
    eye = jnp.eye(6, dtype=H.dtype)
    A = H + lam * H * eye + 1e-9 * (jnp.trace(H) + 1.0) * eye
    xi = -jnp.linalg.solve(A, system.g)
    ok = jnp.all(jnp.isfinite(xi)) & (system.inliers >= 6)
    return jnp.where(ok, xi, jnp.zeros_like(xi))


def align_level(
    T: jaxlie.SE3,
    pts_k: jnp.ndarray,
    kf: KeyframeEdges,
    field: jnp.ndarray,
    nearest_grad: jnp.ndarray,
    intr: Intrinsics,
    level: int,
    config: Config,
) -> tuple[jaxlie.SE3, LevelSystem]:
    """Levenberg-Marquardt on the Huber-weighted (Gauss-Newton) normal equations at one level;
    returns the pose and the normal equations at it.

    A step is kept only when it lowers the robust cost (the coarse, non-smooth distance fields
    make plain Gauss-Newton oscillate); lam shrinks 10x after a kept step and grows 10x after
    a rejected one. lax.while_loop: fixed shapes, stop after ``iterations[level]`` tries or
    once a step, kept or not, is shorter than ``step_tol``.
    """

    def system_at(T):
        return normal_equations(T, pts_k, kf, field, nearest_grad, intr, level, config)

    def cond(state):
        i, _, _, _, step = state
        return (i < config.iterations[level]) & (step >= config.step_tol)

    def body(state):
        i, T, sys, lam, _ = state
        xi = damped_step(sys, lam)
        T_new = retract_left(T, xi)
        sys_new = system_at(T_new)
        better = sys_new.cost < sys.cost
        T, sys = jax.tree.map(lambda a, b: jnp.where(better, a, b), (T_new, sys_new), (T, sys))
        step = jnp.linalg.norm(xi)  # a rejected step this short only shrinks further
        lam = jnp.clip(jnp.where(better, lam * 0.1, lam * 10.0), 1e-6, 1e4)
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
    nearest_grad: jnp.ndarray,
    T_init: jnp.ndarray,
    intr: Intrinsics,
    config: Config,
) -> TrackResult:
    """Align keyframe edges to the frame's distance-field pyramid, coarsest level first.

    dist: one field per level (H / 2**l, W / 2**l); nearest_grad (H, W, 2) int8;
    T_init: (4, 4) initial T_cur_kf. Jit with ``config`` static.
    """
    pts_k = unproject(intr, kf.uv, kf.rho)
    T = jaxlie.SE3.from_matrix(T_init)
    for level in reversed(range(config.num_levels)):
        T, final = align_level(T, pts_k, kf, dist[level], nearest_grad, intr, level, config)
    H = final.H + 1e-9 * (jnp.trace(final.H) + 1.0) * jnp.eye(6, dtype=final.H.dtype)
    # optical flow of the edges that stay in view, with and without rotation (keyframe rule)
    uv_c, pts_c = warp(intr, T, pts_k)
    h, w = dist[0].shape
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
