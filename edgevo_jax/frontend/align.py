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
import numpy as np

from ..camera import Intrinsics, unproject
from ..config import Config
from ..derive import SolveKnobs, SolveStructure, solve_knobs
from ..geometry import Pose
from ..image.preprocess import EdgeMap
from ..solvers import DAMPING, LMState, lower_cost
from .depth import depth_valid, point_to_plane
from .residuals import consistency_dots_at_level, residual_jacobian_grad, warp
from .robust import edge_weights, huber_cost, huber_weights
from .selection import KeyframeEdges
from .shutter import Shutter, row_motion

#: Layout of ``LevelSystem.sums``: the upper triangle of H row by row (21), g (6), the robust
#: cost, the inlier count and the sum of the inliers' residuals.
NUM_SUMS = 30
_H_INDEX = np.zeros((6, 6), np.int32)
_H_INDEX[np.triu_indices(6)] = np.arange(21)
_H_INDEX = np.maximum(_H_INDEX, _H_INDEX.T)


class LevelSystem(NamedTuple):
    """Weighted normal equations at one pose, as the NUM_SUMS sums over edges they are made
    of (``sums``, one array, so that a Levenberg-Marquardt try selects one array, not six):
    H = J^T W J (6, 6), g = J^T W r (6,), the truncated robust cost (see
    ``normal_equations``), the inlier count and the sum of the inliers' residuals."""

    sums: jnp.ndarray

    @property
    def H(self) -> jnp.ndarray:
        """J^T W J (6, 6)."""
        return jnp.take(self.sums, _H_INDEX)

    @property
    def g(self) -> jnp.ndarray:
        """J^T W r (6,)."""
        return self.sums[21:27]

    @property
    def cost(self) -> jnp.ndarray:
        """The robust cost."""
        return self.sums[27]

    @property
    def inliers(self) -> jnp.ndarray:
        """The inlier count (float)."""
        return self.sums[28]

    @property
    def residual_sum(self) -> jnp.ndarray:
        """The sum of the inliers' residuals (px)."""
        return self.sums[29]


class TrackResult(NamedTuple):
    """Output of one alignment: the pose T_cur_kf (4, 4), its covariance (6, 6) over a left
    twist [v, w], level-0 inliers, mean inlier residual (px), the RMS optical flow of the
    visible edges with and without rotation (px), how many edges warp into the image, the
    level-0 robust cost (Huber, the gate's cost for each rejected edge), and ``moved``: the
    RMS distance (level-0 px) between the visible edges' projections at the start pose and
    at the solution (how far the solve went from where it started)."""

    T_c_k: jnp.ndarray
    covariance: jnp.ndarray
    inliers: jnp.ndarray
    mean_residual: jnp.ndarray
    flow: jnp.ndarray
    flow_t: jnp.ndarray
    visible: jnp.ndarray
    cost: jnp.ndarray
    moved: jnp.ndarray


def normal_equations(
    T: Pose,
    pts_k: jnp.ndarray,
    kf: KeyframeEdges,
    field: jnp.ndarray,
    edge_map: EdgeMap,
    intr: Intrinsics,
    level: int,
    knobs: SolveKnobs,
    shutter: Shutter | None = None,
) -> LevelSystem:
    """Gated, Huber-weighted normal equations of the distance residuals at pose T.

    pts_k (3, K): the keyframe edges back-projected; ``shutter``: the frame's rolling
    shutter (``shutter.Shutter``; None: a global shutter). With the keyframe's depth points
    and the frame's depth map, the depth residual joins at level 0 (``depth_system``; the
    depth image is read as a global shutter's at the frame's time: moving its points by the
    colour camera's shutter or by the rgb-depth time offset raised the ATE on fr1_rpy, see
    docs/decisions.md). The cost that Levenberg-Marquardt
    compares is a proper function of the pose: the Huber cost of each inlier, and for every
    other valid keyframe edge (gated, inconsistent or out of view) the Huber cost of the gate,
    so that rejecting a match never lowers the cost.
    """
    rows = None if shutter is None else row_motion(T, shutter, level, field.shape[0])
    r, J, ok, uv_c, grad = residual_jacobian_grad(field, intr.at_level(level), T, pts_k, rows)
    consistent = consistency_dots_at_level(kf.grad, edge_map, uv_c, r, grad, level) >= knobs.eta
    delta, gate = knobs.huber_delta[level], knobs.max_residual[level]
    mask = kf.valid & ok & (r <= gate) & consistent
    if kf.depth_pts is not None and edge_map.depth is not None and level == 0:
        extra = knobs.depth_weight * depth_system(T, kf, edge_map.depth, intr, level, delta,
                                                  gate)
    else:
        extra = None
    if knobs.weighting is None:
        system = robust_system(r, J, mask, kf.valid, delta, gate)
        return system if extra is None else LevelSystem(system.sums + extra)
    if kf.mag is None or kf.disc is None:
        raise ValueError("the per-edge weighting model needs KeyframeEdges.mag and .disc")
    weight, slope = edge_weights(knobs.weighting, kf.mag, kf.rho, kf.disc, r, gate, level)
    system = robust_system(r, J, mask, kf.valid, delta, gate, weight=weight,
                           weight_slope=slope)
    return system if extra is None else LevelSystem(system.sums + extra)


def depth_system(T: Pose, kf: KeyframeEdges, depth: jnp.ndarray, intr: Intrinsics,
                 level: int, delta: jnp.ndarray, gate: jnp.ndarray) -> jnp.ndarray:
    """The depth residual's part of the sums (``depth.point_to_plane``, gated and
    Huber-weighted like the edges at ``level``): H, g and cost; zero inlier count and
    residual sum, which stay the edges'."""
    r, J, ok = point_to_plane(T, kf.depth_pts, kf.depth_normals, depth, intr, level)
    valid = depth_valid(kf.depth_normals)
    sums = robust_system(r, J, ok & (jnp.abs(r) <= gate), valid, delta, gate).sums
    return sums.at[28:].set(0.0)


def sum_rows(rows: list[jnp.ndarray]) -> jnp.ndarray:
    """The sums of equally shaped arrays (K,) as one (len(rows),) array, from one variadic
    reduction: XLA evaluates each edge's terms once and adds them in order, whatever the
    batch size of a vmapped caller (a run gives the same result alone and in a batch, which
    ``batch.py`` relies on; XLA's dots and vectorised sums do not, and its batched dots are
    slow on CPU for thousands of edges)."""
    return _sum_rows(tuple(rows))


@jax.custom_jvp
def _sum_rows(rows: tuple[jnp.ndarray, ...]) -> jnp.ndarray:
    zero = jnp.zeros((), rows[0].dtype)
    out = jax.lax.reduce(rows, (zero,) * len(rows),
                         lambda a, b: tuple(x + y for x, y in zip(a, b, strict=True)), (0,))
    return jnp.stack(out)


@_sum_rows.defjvp
def _sum_rows_jvp(primals, tangents):
    # the sum is linear: its tangent is the sum of the tangents (plain sums, which JAX can
    # transpose; its generic rule for a variadic reduce fails on symbolic zero tangents)
    (rows,), (dots,) = primals, tangents
    return _sum_rows(rows), jnp.stack([jnp.sum(t) for t in dots])


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
    *,
    ordered: bool = True,
) -> LevelSystem:
    """Huber-weighted normal equations of residuals r (K,) with Jacobian J (6, K) over the
    inliers ``mask``; every other ``valid`` edge costs the gate's Huber cost.

    Optional (the differentiable path of ``learn.differentiable``): ``weight`` (K,) scales
    each inlier's Huber weight and cost; ``reject`` (K,) in [0, 1] adds that fraction of the
    gate's cost to an inlier (a soft rejection); ``weight_slope`` (K,) is d weight / dr when
    the weight depends on the residual, so that g stays the gradient of the cost (the term
    weight_slope * Huber cost joins J^T W r; H keeps the Gauss-Newton weights). Without them
    this is the plain tracker's system.

    ``ordered``: each sum added edge by edge in a fixed order (``sum_rows``: the same bits
    alone and in a batch); False forms H and g as matrix products, which reverse mode
    differentiates several times faster (the smooth training mode, ``learn.smooth``) and
    whose rounding XLA chooses.
    """
    w = huber_weights(r, delta)
    inlier_cost = huber_cost(r, delta)
    if weight is not None:
        w, inlier_cost = weight * w, weight * inlier_cost
    if reject is not None:
        inlier_cost = inlier_cost + reject * huber_cost(gate, delta)
    w = jnp.where(mask, w, 0.0)
    wr = w * r
    if weight_slope is not None:
        wr = wr + jnp.where(mask, weight_slope * huber_cost(r, delta), 0.0)
    outside = jnp.where(valid, huber_cost(gate, delta), 0.0)
    tail = [jnp.where(mask, inlier_cost, outside), mask.astype(r.dtype),
            jnp.where(mask, r, 0.0)]
    if not ordered:
        H = (J * w) @ J.T
        sums = [H[np.triu_indices(6)], J @ wr, jnp.sum(jnp.stack(tail), axis=1)]
        return LevelSystem(jnp.concatenate(sums))
    rows = [J[i] * w * J[j] for i in range(6) for j in range(i, 6)]
    rows += [J[i] * wr for i in range(6)]
    return LevelSystem(sum_rows(rows + tail))


def solve_spd(A: jnp.ndarray, B: jnp.ndarray) -> jnp.ndarray:
    """A^-1 B for a symmetric positive definite A (n, n) and B (n, m): Gauss-Jordan
    elimination without pivoting (stable for SPD matrices), a handful of fused kernels
    where LAPACK's solve is several library calls (the solve's inner loop pays per kernel)."""
    n = A.shape[0]
    M = jnp.concatenate([A, B], axis=1)
    rows = jnp.arange(n)
    for k in range(n):
        pivot = M[k] / M[k, k]
        M = M - M[:, k:k + 1] * pivot[None, :] * (rows != k)[:, None]
    return M[:, n:] / jnp.diagonal(M[:, :n])[:, None]


def _trace6(H: jnp.ndarray) -> jnp.ndarray:
    """The trace, added in a fixed order (see ``sum_rows``)."""
    return H[0, 0] + H[1, 1] + H[2, 2] + H[3, 3] + H[4, 4] + H[5, 5]


def damped_step(system: LevelSystem, lam: jnp.ndarray) -> jnp.ndarray:
    """Levenberg-Marquardt step xi = -(H + lam diag(H))^-1 g; zero when not finite."""
    H = system.H
    eye = jnp.eye(6, dtype=H.dtype)
    A = H + lam * H * eye + 1e-9 * (_trace6(H) + 1.0) * eye
    xi = -solve_spd(A, system.g[:, None])[:, 0]
    ok = jnp.all(jnp.isfinite(xi)) & (system.inliers >= 6)
    return jnp.where(ok, xi, jnp.zeros_like(xi))


def pose_try(
    system_at: Callable[[Pose], LevelSystem],
    state: LMState,
    accept: Callable[[LevelSystem, LevelSystem], jnp.ndarray] = lower_cost,
) -> LMState:
    """One Levenberg-Marquardt try of the pose (``solvers.DAMPING``): the damped step
    ``damped_step``, applied as T <- exp(xi) T, kept when ``accept`` (old system, new system)
    holds, by default when ``system_at`` says it lowers the robust cost."""
    state, _ = DAMPING.step(
        state,
        solve=lambda T, system, lam: damped_step(system, lam),
        apply=lambda T, xi: T.retract(xi),
        evaluate=lambda T, system: system_at(T),
        accept=accept,
    )
    return state


def pose_start(T: Pose, system: LevelSystem) -> LMState:
    """The pose solve's state before the first try from pose T with its system."""
    return DAMPING.init(T, system, system.sums.dtype)


def pose_continues(state: LMState, knobs: SolveKnobs) -> jnp.ndarray:
    """Whether a level tries again after ``state``: its step was at least ``step_tol`` and
    fewer than ``max_rejects`` tries in a row were rejected (each rejection only grows lam
    tenfold, the pose stays). The iteration budget is the caller's."""
    return DAMPING.continues(state, knobs.step_tol, knobs.max_rejects)


def align_level(
    T: Pose,
    pts_k: jnp.ndarray,
    kf: KeyframeEdges,
    field: jnp.ndarray,
    edge_map: EdgeMap,
    intr: Intrinsics,
    level: int,
    knobs: SolveKnobs,
    shutter: Shutter | None = None,
) -> tuple[Pose, LevelSystem]:
    """Levenberg-Marquardt on the Huber-weighted (Gauss-Newton) normal equations at one level;
    returns the pose and the normal equations at it.

    A step is kept only when it lowers the robust cost (the coarse, non-smooth distance fields
    make plain Gauss-Newton oscillate); lam shrinks 10x after a kept step and grows 10x after
    a rejected one (``solvers.DAMPING``). lax.while_loop: fixed shapes, at most
    ``knobs.iterations[level]`` tries, stopped earlier by ``pose_continues``.

    The normal equations at the start pose are the loop's first pass (``fresh``: no step,
    ``pose_start``'s state after it), not a copy of them before the loop: the program
    holds them once per level, and the numbers are those of a separate first evaluation.
    """

    def system_at(T):
        return normal_equations(T, pts_k, kf, field, edge_map, intr, level, knobs, shutter)

    def cond(carry):
        i, state, fresh = carry
        return fresh | ((i < knobs.iterations[level]) & pose_continues(state, knobs))

    def body(carry):
        i, state, fresh = carry

        def start_or_retract(T, xi):
            return jax.tree.map(lambda a, b: jnp.where(fresh, a, b), T, T.retract(xi))

        tried, _ = DAMPING.step(
            state, solve=lambda T, system, lam: damped_step(system, lam),
            apply=start_or_retract, evaluate=lambda T, system: system_at(T),
            accept=lambda old, new: fresh | lower_cost(old, new))
        # the first pass only evaluates: the state pose_start makes from its system
        tried = tried._replace(lam=jnp.where(fresh, state.lam, tried.lam),
                               step=jnp.where(fresh, state.step, tried.step))
        return jnp.where(fresh, i, i + 1), tried, jnp.asarray(False)

    unset = LevelSystem(jnp.zeros(NUM_SUMS, pts_k.dtype))  # replaced by the first pass
    init = _alike(T.t[0], (jnp.asarray(0), pose_start(T, unset), jnp.asarray(True)))
    _, state, _ = jax.lax.while_loop(cond, body, init)
    return state.x, state.system


def _alike(ref: jnp.ndarray, tree):
    """``tree`` as it is, each leaf passed through ``where(ref == ref, x, x)``: under ``vmap``
    (the tracker's batched solve, ``chunk.batch_of_one``) every leaf is then batched like
    ``ref``, so that JAX batches a while loop started from ``tree`` once, not again for each
    carry its body turns batched (docs/results.md). XLA folds the select away: the results
    are the same to the bit."""
    same = ref == ref
    return jax.tree.map(lambda x: jnp.where(same, x, x), tree)


def rms_flow(uv_from: jnp.ndarray, uv_to: jnp.ndarray, mask: jnp.ndarray) -> jnp.ndarray:
    """Root mean squared pixel displacement (2, K) -> scalar over the masked points."""
    d = uv_to - uv_from
    sq, n = sum_rows([jnp.where(mask, d[0] * d[0] + d[1] * d[1], 0.0), mask.astype(d.dtype)])
    return jnp.sqrt(sq / jnp.maximum(n, 1.0))


def track(
    kf: KeyframeEdges,
    dist: tuple[jnp.ndarray, ...],
    edge_map: EdgeMap,
    T_init: jnp.ndarray,
    intr: Intrinsics,
    config: Config | SolveStructure,
    knobs: SolveKnobs | None = None,
    shutter: Shutter | None = None,
) -> TrackResult:
    """Align keyframe edges to the frame's distance-field pyramid, coarsest level first.

    dist: one field per level (H / 2**l, W / 2**l); edge_map: the frame's ``preprocess.EdgeMap``;
    T_init: (4, 4) initial T_cur_kf. ``config`` (static) gives the number of levels: a
    ``derive.SolveStructure`` (``derive.solve_structure``) or a Config; the numbers are read
    from ``knobs`` (traced; default ``derive.solve_knobs(config)``, which needs a Config).
    ``shutter``: the frame's rolling shutter (``shutter.Shutter``; None: a global shutter,
    and a program without it).
    """
    knobs = solve_knobs(config) if knobs is None else knobs
    pts_k = unproject(intr, kf.uv, kf.rho)
    T = start = Pose.from_matrix(jnp.asarray(T_init, pts_k.dtype))
    for level in reversed(range(config.num_levels)):
        T, final = align_level(T, pts_k, kf, dist[level], edge_map, intr, level, knobs,
                               shutter)
    return track_result(T, final, pts_k, kf, dist[0].shape, intr, start)


def track_result(
    T: Pose,
    final: LevelSystem,
    pts_k: jnp.ndarray,
    kf: KeyframeEdges,
    shape: tuple[int, int],
    intr: Intrinsics,
    start: Pose,
) -> TrackResult:
    """The TrackResult of an alignment that started at pose ``start`` and ended at pose T
    with level-0 normal equations ``final``: covariance, inlier statistics, the optical flow
    of the visible edges and how far they moved from the start; shape (H, W) of level 0."""
    H = final.H + 1e-9 * (_trace6(final.H) + 1.0) * jnp.eye(6, dtype=final.H.dtype)
    # optical flow of the edges that stay in view, with and without rotation (keyframe rule)
    uv_c, pts_c = warp(intr, T, pts_k)
    h, w = shape
    visible = (
        kf.valid & (pts_c[2] > 1e-6) & (uv_c[0] >= 0) & (uv_c[0] <= w - 1)
        & (uv_c[1] >= 0) & (uv_c[1] <= h - 1)
    )
    uv_t, _ = warp(intr, Pose(jnp.eye(3, dtype=T.t.dtype), T.t), pts_k)
    inliers = final.inliers
    return TrackResult(
        T_c_k=T.as_matrix(),
        covariance=solve_spd(H, jnp.eye(6, dtype=H.dtype)),
        inliers=inliers.astype(jnp.int32),
        mean_residual=final.residual_sum / jnp.maximum(inliers, 1.0),
        flow=rms_flow(kf.uv, uv_c, visible),
        flow_t=rms_flow(kf.uv, uv_t, visible),
        visible=jnp.sum(visible),
        cost=final.cost,
        moved=rms_flow(warp(intr, start, pts_k)[0], uv_c, visible),
    )
