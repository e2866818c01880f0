"""Differentiable alignment (gradients of the pose w.r.t. ``Params``), two adjoints, and
relative-pose losses.

``track_differentiable`` runs the tracker's coarse-to-fine Levenberg-Marquardt
(``solve.lm_iteration`` on ``solve.robust_system``) with the learnable parameters in place
of the config's: Huber radius per level ``exp(log_huber[l])``, the gradient-consistency test
made soft, sigmoid((g(p) . g(p') - eta) / tau) (``consistency="hard"`` keeps the plain
tracker's g(p) . g(p') >= eta), and each inlier's Huber weight scaled by the per-edge
weighting model (``params.edge_weight``). A soft-rejected fraction 1 - s of an edge adds that
fraction of the gate's cost, as the plain tracker's cost does for a rejected edge.

Two adjoints, one switch:

- ``adjoint="unrolled"``: reverse mode through every LM try of every level (``lax.scan``
  over ``Config.iterations``; ``checkpoint=True`` recomputes each try in the backward pass
  instead of storing it). Exact derivative of what the forward pass computed, converged or
  not; memory and time grow with the iteration count.
- ``adjoint="implicit"``: the forward pass runs without gradients; at the final pose T* the
  Gauss-Newton stationarity F(T*, theta) = J^T W r = 0 (tangent space, left twist) holds, and
  the implicit function theorem gives dT*/dtheta = -(dF/dxi)^-1 dF/dtheta, with dF/dxi the
  exact (autodiff) 6x6 derivative of F (``jax.custom_vjp``). Cost independent of the
  iteration count; exact only at a converged pose, and blind to the coarse levels (the
  converged pose does not depend on them) and to ``T_init``. With fewer than 6 inliers at
  T* (no step was taken) the gradient is zero. Caveat: the cost is only piecewise smooth
  (bilinear fields, nearest-edge consistency), and on real frames LM often ends on a kink
  rather than at a stationary point (g^T H^-1 g not ~0); there the implicit gradient is an
  approximation (on one converged bundled pair it differed from finite differences by 7e-3
  relative, and the pose still moved with the coarse levels' radii). The unrolled adjoint
  is the exact one.

Hard decisions are constants in the backward pass, in both adjoints: the residual gate
(r <= max_residual), visibility, the validity of edges, which keyframe and which edges were
selected, the nearest edge p' whose gradient enters the consistency test (a nearest-pixel
lookup), and whether LM kept or rejected each step (and its damping). The gradients are those
of the smooth function that these decisions select; a finite-difference step that flips one
of them leaves that function.

``Params.reobs_a`` only enters edge selection (a discrete greedy, not differentiated); its
effect on the selection's soft scores is ``selection_scores``.
"""

from __future__ import annotations

from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .camera import Intrinsics, unproject
from .config import Config
from .geometry import Rigid
from .params import Params, edge_features, edge_weight
from .preprocess import Frame
from .residuals import consistency_dots_at_level, residual_and_jacobian, residual_jacobian_grad
from .selection import reobservation_probability
from .solve import (
    KeyframeEdges,
    LevelSystem,
    SolveKnobs,
    TrackResult,
    lm_continues,
    lm_iteration,
    lm_start,
    robust_system,
    solve_knobs,
    track_result,
)

ADJOINTS = ("unrolled", "implicit")
CONSISTENCY = ("soft", "hard")


class _EdgeData(NamedTuple):
    """What the level systems need besides the pose (all float: it crosses custom_vjp)."""

    pts_k: jnp.ndarray  # (3, K) keyframe points
    rho: jnp.ndarray  # (K,)
    mag: jnp.ndarray  # (K,) gradient magnitude (0 = unknown)
    field: jnp.ndarray  # (H_l, W_l) distance field of the level
    intr: Intrinsics  # level-0 intrinsics (arrays)


def _system(
    T: Rigid,
    params: Params,
    data: _EdgeData,
    mask: jnp.ndarray,
    dots: jnp.ndarray,
    valid: jnp.ndarray,
    level: int,
    config: Config,
    consistency: str,
) -> LevelSystem:
    """Normal equations at T with the hard decisions given: ``mask`` (gate, validity,
    visibility and, for ``consistency="hard"``, the consistency test) and ``dots``
    g(p) . g(p'). Everything else is a smooth function of T, params and data."""
    r, J, _, _ = residual_and_jacobian(data.field, data.intr.at_level(level), T, data.pts_k)

    def weight_of(r):
        return edge_weight(params, edge_features(data.mag, data.rho, r, level, config))

    # elementwise in r: the JVP with ones is each weight's own slope
    weight, slope = jax.jvp(weight_of, (r,), (jnp.ones_like(r),))
    reject = None
    if consistency == "soft":
        soft = jax.nn.sigmoid((dots - params.eta) / params.temperature)
        weight, slope, reject = weight * soft, slope * soft, 1.0 - soft
    system = robust_system(r, J, mask, valid, params.huber_delta(level),
                           config.max_residual[level], weight=weight, reject=reject,
                           weight_slope=slope)
    if consistency == "soft":  # inliers as the plain tracker counts them
        inliers = jnp.sum(mask & (dots >= params.eta)).astype(system.sums.dtype)
        system = LevelSystem(system.sums.at[28].set(inliers))
    return system


def _decisions(
    T: Rigid, params: Params, data: _EdgeData, kf: KeyframeEdges,
    edge_map: jnp.ndarray, level: int, config: Config, consistency: str,
) -> tuple[jnp.ndarray, jnp.ndarray]:
    """The hard decisions at T (as ``solve.normal_equations`` takes them): the inlier mask
    and g(p) . g(p') (K,) of the nearest edges p'."""
    r, _, ok, uv_c, grad = residual_jacobian_grad(data.field, data.intr.at_level(level), T,
                                                  data.pts_k)
    dots = consistency_dots_at_level(kf.grad, edge_map, uv_c, r, grad, level)
    mask = kf.valid & ok & (r <= config.max_residual[level])
    if consistency == "hard":
        mask = mask & (dots >= params.eta)
    return mask, dots


def _align(
    T: Rigid, system_at, iterations: int, knobs: SolveKnobs, checkpoint: bool
) -> tuple[Rigid, LevelSystem]:
    """``iterations`` LM tries (a scan: reverse-differentiable), frozen once
    ``solve.lm_continues`` says stop (what ``solve.align_level``'s while loop does)."""

    def body(carry, _):
        state, active = carry
        new = lm_iteration(system_at, state)
        state = jax.tree.map(lambda a, b: jnp.where(active, a, b), new, state)
        return (state, active & jax.lax.stop_gradient(lm_continues(new, knobs))), None

    if checkpoint:
        body = jax.checkpoint(body)
    init = (lm_start(T, system_at(T)), jnp.asarray(True))
    (state, _), _ = jax.lax.scan(body, init, None, length=iterations)
    return state.T, state.system


def _flat(T: Rigid) -> jnp.ndarray:
    """A pose's parameters as one array (12,): R row by row, then t."""
    return jnp.concatenate([T.R.reshape(-1), T.t])


def _unflat(x: jnp.ndarray) -> Rigid:
    return Rigid(x[:9].reshape(3, 3), x[9:])


def _tangent_cotangent(T: Rigid, ct: jnp.ndarray) -> jnp.ndarray:
    """Cotangent of the pose parameters (``_flat``, 12) -> of a left twist at T (6)."""
    _, vjp = jax.vjp(lambda xi: _flat(T.retract(xi)), jnp.zeros(6, ct.dtype))
    return vjp(ct)[0]


@partial(jax.custom_vjp, nondiff_argnums=(0,))
def _implicit_pose(stationarity, T_params: jnp.ndarray, inputs) -> jnp.ndarray:
    """T* (``_flat`` parameters) unchanged; its VJP is the implicit function theorem on
    ``stationarity(T, inputs) = 0`` (6,)."""
    del stationarity, inputs
    return T_params


def _implicit_fwd(stationarity, T_params, inputs):
    return T_params, (T_params, inputs)


def _implicit_bwd(stationarity, res, ct):
    T_params, inputs = res
    T = _unflat(T_params)
    ct_xi = _tangent_cotangent(T, ct)

    def F_xi(xi):
        return stationarity(T.retract(xi), inputs)[0]

    A = jax.jacfwd(F_xi)(jnp.zeros(6, T_params.dtype))  # dF/dxi (6, 6), exact
    F0, vjp_in, inliers = jax.vjp(lambda i: stationarity(T, i), inputs, has_aux=True)
    ok = inliers >= 6  # otherwise no step was taken and T* is no stationary point
    eye = jnp.eye(6, dtype=A.dtype)
    eps = jnp.finfo(A.dtype).eps * (jnp.abs(jnp.trace(A)) + 1.0)
    A = jnp.where(ok, A + eps * eye, eye)
    adj = jnp.linalg.solve(A.T, ct_xi)
    (ct_inputs,) = vjp_in(jnp.where(ok, -adj, 0.0))
    del F0
    return jnp.zeros_like(T_params), ct_inputs


_implicit_pose.defvjp(_implicit_fwd, _implicit_bwd)


def _level0_stationarity(spec, T, inputs):
    """F(T) = J^T W r at level 0 with the decisions in ``inputs`` fixed; aux: inliers."""
    config, consistency = spec
    params, data, mask_f, dots, valid_f = inputs
    mask, valid = mask_f > 0.5, valid_f > 0.5
    system = _system(T, params, data, mask, dots, valid, 0, config, consistency)
    return system.g, system.inliers


class _Stationarity(NamedTuple):
    """Hashable callable for custom_vjp's non-differentiable argument."""

    config: Config
    consistency: str

    def __call__(self, T, inputs):
        """F(T, inputs) and the inlier count (see ``_level0_stationarity``)."""
        return _level0_stationarity((self.config, self.consistency), T, inputs)


def track_differentiable(
    kf: KeyframeEdges,
    dist: tuple[jnp.ndarray, ...],
    edge_map: jnp.ndarray,
    T_init: jnp.ndarray,
    intr: Intrinsics,
    params: Params,
    config: Config,
    *,
    mag: jnp.ndarray | None = None,
    adjoint: str = "unrolled",
    consistency: str = "soft",
    checkpoint: bool = False,
) -> TrackResult:
    """``solve.track`` with learnable ``params``, differentiable w.r.t. them (and the float
    inputs) through ``adjoint`` ("unrolled" or "implicit", see the module docstring).

    mag (K,): gradient magnitude of each keyframe edge for the weighting model (zeros when
    None; ``edge_magnitudes`` looks them up). ``consistency="hard"`` with
    ``Params.default(config)`` runs the plain tracker's computation (same tries, same
    decisions). Jit with ``config``, ``adjoint``, ``consistency``, ``checkpoint`` static.
    """
    if adjoint not in ADJOINTS:
        raise ValueError(f"adjoint must be one of {ADJOINTS}, got {adjoint!r}")
    if consistency not in CONSISTENCY:
        raise ValueError(f"consistency must be one of {CONSISTENCY}, got {consistency!r}")
    dtype = dist[0].dtype
    intr = Intrinsics(*(jnp.asarray(v, dtype) for v in intr))
    mag = jnp.zeros_like(kf.rho) if mag is None else jnp.asarray(mag, kf.rho.dtype)
    knobs = solve_knobs(config)
    if adjoint == "implicit":  # the forward pass without gradients
        inputs = jax.lax.stop_gradient((kf, dist, T_init, intr, params, mag))
        kf_s, dist_s, T_init_s, intr_s, params_s, mag_s = inputs
    else:
        kf_s, dist_s, T_init_s, intr_s, params_s, mag_s = kf, dist, T_init, intr, params, mag

    def data_at(level, kf, dist, intr, mag):
        pts_k = unproject(intr, kf.uv, kf.rho)
        return _EdgeData(pts_k, kf.rho, mag, dist[level], intr)

    T = Rigid.from_matrix(jnp.asarray(T_init_s, dtype))
    for level in reversed(range(config.num_levels)):
        data = data_at(level, kf_s, dist_s, intr_s, mag_s)

        def system_at(T, data=data, level=level):
            mask, dots = _decisions(T, params_s, data, kf_s, edge_map, level, config,
                                    consistency)
            return _system(T, params_s, data, mask, dots, kf_s.valid, level, config,
                           consistency)

        T, final = _align(T, system_at, config.iterations[level], knobs, checkpoint)

    data = data_at(0, kf, dist, intr, mag)
    if adjoint == "implicit":
        mask, dots = _decisions(T, params_s, data_at(0, kf_s, dist_s, intr_s, mag_s), kf_s,
                                edge_map, 0, config, consistency)
        f = data.pts_k.dtype
        inputs = (params, data, mask.astype(f), dots, kf.valid.astype(f))
        T = _unflat(_implicit_pose(_Stationarity(config, consistency), _flat(T), inputs))
        final = _system(T, params, data, mask, dots, kf.valid, 0, config, consistency)
    return track_result(T, final, data.pts_k, kf, dist[0].shape, intr)


def edge_magnitudes(frame: Frame, kf: KeyframeEdges) -> np.ndarray:
    """Gradient magnitude (K,) of each keyframe edge, looked up in the frame the edges come
    from by pixel (0 for padding slots); host side, numpy."""
    h, w = frame.shape
    img = np.zeros((h, w), np.float32)
    uv = np.rint(frame.edge_uv).astype(int)
    img[uv[:, 1], uv[:, 0]] = frame.edge_mag
    u = np.clip(np.rint(np.asarray(kf.uv[0])).astype(int), 0, w - 1)
    v = np.clip(np.rint(np.asarray(kf.uv[1])).astype(int), 0, h - 1)
    return np.where(np.asarray(kf.valid), img[v, u], 0.0).astype(np.float32)


def selection_scores(mag: jnp.ndarray, gains: jnp.ndarray, params: Params) -> jnp.ndarray:
    """The selection's score p_e * gain_e of each candidate (what the partition greedy
    maximises, ``selection.partition_greedy``), p_e = 1 / (1 + exp(a - m_e)) with the
    learnable offset ``params.reobs_a``: the only place ``a`` enters. The greedy's argmax over
    these scores is a hard decision and is not differentiated."""
    return reobservation_probability(mag, params.reobs_a) * gains


def _safe_norm(x: jnp.ndarray) -> jnp.ndarray:
    """Euclidean norm with a zero (not NaN) gradient at 0."""
    sq = jnp.sum(x * x)
    pos = sq > 0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, sq, 1.0)), 0.0)


def _relative(T_est: jnp.ndarray, T_gt: jnp.ndarray) -> tuple[jnp.ndarray, jnp.ndarray]:
    """E = T_gt^-1 T_est as (rotation (3, 3), translation (3,)), from 4x4 matrices."""
    R_gt, R_est = T_gt[:3, :3], T_est[:3, :3]
    return R_gt.T @ R_est, R_gt.T @ (T_est[:3, 3] - T_gt[:3, 3])


def relative_pose_error(T_est: jnp.ndarray, T_gt: jnp.ndarray) -> tuple[jnp.ndarray, jnp.ndarray]:
    """Translation (m) and rotation (rad) error of an estimated relative pose T_est (4, 4)
    against the true one T_gt: of E = T_gt^-1 T_est. The angle comes from the chordal
    distance, 2 asin(|R_E - I|_F / sqrt(8)), so its gradient is finite everywhere (and 0
    at E = I, where a norm's is not defined)."""
    R, t = _relative(T_est, T_gt)
    chord = _safe_norm(R - jnp.eye(3, dtype=R.dtype))
    angle = 2.0 * jnp.arcsin(jnp.clip(chord / jnp.sqrt(8.0), 0.0, 1.0 - 1e-12))
    return _safe_norm(t), angle


def rpe_loss(T_est: jnp.ndarray, T_gt: jnp.ndarray, *, rot_weight: float = 1.0) -> jnp.ndarray:
    """Relative-pose error, translation (m) + rot_weight * rotation (rad)."""
    t_err, r_err = relative_pose_error(T_est, T_gt)
    return t_err + rot_weight * r_err


def pose_loss(T_est: jnp.ndarray, T_gt: jnp.ndarray, *, rot_weight: float = 1.0) -> jnp.ndarray:
    """Smooth squared relative-pose error: |t_E|^2 + rot_weight^2 |R_E - I|_F^2 / 2 of
    E = T_gt^-1 T_est (the rotation term is 2 (1 - cos angle) ~ angle^2)."""
    R, t = _relative(T_est, T_gt)
    rot = jnp.sum((R - jnp.eye(3, dtype=R.dtype)) ** 2) / 2.0
    return jnp.sum(t * t) + rot_weight**2 * rot
