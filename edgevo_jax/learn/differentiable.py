"""Differentiable alignment (gradients of the pose w.r.t. ``Params``), two adjoints, and
pose losses against ground truth (frame pairs, windows, chunks).

``track_differentiable`` runs the tracker's coarse-to-fine Levenberg-Marquardt
(``align.pose_try``: a ``solvers.LevenbergMarquardt`` try on ``align.robust_system``) with
the learnable parameters in place of the config's: Huber radius per level
``exp(log_huber[l])``, the gradient-consistency test made soft,
sigmoid((g(p) . g(p') - eta) / tau) (``consistency="hard"`` keeps the plain tracker's
g(p) . g(p') >= eta), and each inlier's Huber weight scaled by the per-edge weighting model
(``robust.edge_weights``). A soft-rejected fraction 1 - s of an edge adds that
fraction of the gate's cost, as the plain tracker's cost does for a rejected edge.

Two options make the cost smooth enough for exact implicit gradients (both off by default,
which is the plain tracker's computation): ``interpolation="bicubic"`` reads the distance
fields with a C1 interpolant (``interp.bicubic_with_grad``; bilinear has kinks at pixel
boundaries), and ``refine=n`` adds n rounds at level 0 after the coarse-to-fine solve, each
holding the hard decisions taken at its start (so that LM works on one smooth piece of the
cost, not against the jumps of the nearest-edge test) for ``config.iterations[0]`` tries,
a try being also kept when it shrinks the gradient without raising the cost beyond rounding
(so it gets past where cost differences drown in rounding), and then taking them again.

Two adjoints, one switch:

- ``adjoint="unrolled"``: reverse mode through every LM try of every level and round
  (``lax.scan``; ``checkpoint=True`` recomputes each try in the backward pass instead of
  storing it). Exact derivative of what the forward pass computed, converged or not; memory
  and time grow with the iteration count.
- ``adjoint="implicit"``: the forward pass runs without gradients; at the final pose T* the
  stationarity F(T*, theta) = J^T W r = 0 (the cost's gradient in a left twist, with the
  hard decisions of T*, or those the last round held) is assumed, and the implicit function
  theorem gives dT*/dtheta = -(dF/dxi)^-1 dF/dtheta, with dF/dxi the exact (autodiff) 6x6
  derivative of F (``jax.custom_vjp``). Cost independent of the iteration count; blind to
  the coarse levels and to ``T_init`` (a stationary point of level 0 depends on neither).
  With fewer than 6 inliers at T* (no step was taken) the gradient is zero.
  It is exact when T* is a stationary point of the cost with the decisions that hold at T*
  and the cost is smooth around it: ``newton_decrement(level_system(...)[0])`` at T* is then
  ~0 (relative to the cost); check it (``docs/decisions.md`` says how often the plain and the
  refined computations get there).

Hard decisions are constants in the backward pass, in both adjoints: the residual gate
(r <= max_residual), visibility, the validity of edges, which keyframe and which edges were
selected, the nearest edge p' whose gradient enters the consistency test (a nearest-pixel
lookup), and whether LM kept or rejected each step (and its damping). The gradients are those
of the smooth function that these decisions select; a finite-difference step that flips one
of them leaves that function.

``Params.reobs_a`` only enters edge selection (a discrete greedy, not differentiated); its
effect on the selection's soft scores is ``selection_scores``.

``track_window`` tracks a window against a keyframe as the tracker does, from the
constant-velocity prediction; the losses that compare its poses with the ground truth are in
``losses``.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..camera import Intrinsics, unproject
from ..config import Config
from ..derive import SolveKnobs, solve_knobs
from ..frontend.align import (
    KeyframeEdges,
    LevelSystem,
    TrackResult,
    pose_continues,
    pose_start,
    pose_try,
    robust_system,
    track_result,
)
from ..frontend.chunk import predict_matrix
from ..frontend.residuals import (
    consistency_dots_at_level,
    point_jacobian,
    residual_jacobian_grad,
    warp,
)
from ..frontend.robust import edge_weights
from ..frontend.selection import reobservation_probability
from ..geometry import Pose
from ..image.interp import bicubic_with_grad
from ..image.preprocess import Frame
from ..solvers import LMState
from .implicit import flat, implicit_pose, unflat
from .params import Params, weighting_of

ADJOINTS = ("unrolled", "implicit")
CONSISTENCY = ("soft", "hard")
INTERPOLATIONS = ("bilinear", "bicubic")


def _residuals(
    field: jnp.ndarray, intr: Intrinsics, T: Pose, pts_k: jnp.ndarray, interpolation: str
) -> tuple[jnp.ndarray, jnp.ndarray, jnp.ndarray, jnp.ndarray, jnp.ndarray]:
    """``residuals.residual_jacobian_grad`` with the field read by ``interpolation``:
    residuals (K,), Jacobian (6, K), validity (K,), warped pixels (2, K), field gradient
    (2, K). "bilinear" is the plain tracker's own computation."""
    if interpolation == "bilinear":
        return residual_jacobian_grad(field, intr, T, pts_k)
    uv_c, pts = warp(intr, T, pts_k)
    r, grad, inside = bicubic_with_grad(field, uv_c)
    return r, point_jacobian(intr, pts, grad), inside & (pts[2] > 1e-6), uv_c, grad


class _EdgeData(NamedTuple):
    """What the level systems need besides the pose (all float: it crosses custom_vjp)."""

    pts_k: jnp.ndarray  # (3, K) keyframe points
    rho: jnp.ndarray  # (K,)
    mag: jnp.ndarray  # (K,) gradient magnitude (0 = unknown)
    disc: jnp.ndarray  # (K,) depth discontinuity (``selection.depth_discontinuity``)
    field: jnp.ndarray  # (H_l, W_l) distance field of the level
    intr: Intrinsics  # level-0 intrinsics (arrays)


class _Spec(NamedTuple):
    """The static choices of the differentiable path (hashable)."""

    config: Config
    consistency: str
    interpolation: str


def _system(
    T: Pose,
    params: Params,
    data: _EdgeData,
    mask: jnp.ndarray,
    dots: jnp.ndarray,
    valid: jnp.ndarray,
    level: int,
    spec: _Spec,
) -> LevelSystem:
    """Normal equations at T with the hard decisions given: ``mask`` (gate, validity,
    visibility and, for ``consistency="hard"``, the consistency test) and ``dots``
    g(p) . g(p'). Everything else is a smooth function of T, params and data."""
    config = spec.config
    r, J, _, _, _ = _residuals(data.field, data.intr.at_level(level), T, data.pts_k,
                               spec.interpolation)

    weight, slope = edge_weights(weighting_of(params, config), data.mag, data.rho, data.disc,
                                 r, config.max_residual[level], level)
    reject = None
    if spec.consistency == "soft":
        soft = jax.nn.sigmoid((dots - params.eta) / params.temperature)
        weight, slope, reject = weight * soft, slope * soft, 1.0 - soft
    system = robust_system(r, J, mask, valid, params.huber_delta(level),
                           config.max_residual[level], weight=weight, reject=reject,
                           weight_slope=slope)
    if spec.consistency == "soft":  # inliers as the plain tracker counts them
        inliers = jnp.sum(mask & (dots >= params.eta)).astype(system.sums.dtype)
        system = LevelSystem(system.sums.at[28].set(inliers))
    return system


def _decisions(
    T: Pose, params: Params, data: _EdgeData, kf: KeyframeEdges,
    edge_map: jnp.ndarray, level: int, spec: _Spec,
) -> tuple[jnp.ndarray, jnp.ndarray]:
    """The hard decisions at T (as ``align.normal_equations`` takes them): the inlier mask
    and g(p) . g(p') (K,) of the nearest edges p'."""
    r, _, ok, uv_c, grad = _residuals(data.field, data.intr.at_level(level), T, data.pts_k,
                                      spec.interpolation)
    dots = consistency_dots_at_level(kf.grad, edge_map, uv_c, r, grad, level)
    mask = kf.valid & ok & (r <= spec.config.max_residual[level])
    if spec.consistency == "hard":
        mask = mask & (dots >= params.eta)
    return mask, dots


def _settles(old: LevelSystem, new: LevelSystem) -> jnp.ndarray:
    """LM's acceptance with ``settle``: a step is also kept when it shrinks the gradient
    without raising the cost beyond rounding (near a stationary point cost differences drown
    in rounding while the gradient still says where to go)."""
    slack = 64 * jnp.finfo(old.cost.dtype).eps * (jnp.abs(old.cost) + 1.0)
    shrinks = (new.cost <= old.cost + slack) & (new.g @ new.g < old.g @ old.g)
    return (new.cost < old.cost) | shrinks


def _lm_try(system_at, state: LMState, settle: bool) -> LMState:
    """``align.pose_try``, with ``_settles`` as the acceptance test when ``settle``."""
    return pose_try(system_at, state, _settles) if settle else pose_try(system_at, state)


def _align(
    T: Pose, system_at, iterations: int, knobs: SolveKnobs, checkpoint: bool,
    settle: bool = False,
) -> tuple[Pose, LevelSystem]:
    """``iterations`` LM tries (a scan: reverse-differentiable), frozen once
    ``align.pose_continues`` says stop (what ``align.align_level``'s while loop does)."""

    def body(carry, _):
        state, active = carry
        new = _lm_try(system_at, state, settle)
        state = jax.tree.map(lambda a, b: jnp.where(active, a, b), new, state)
        return (state, active & jax.lax.stop_gradient(pose_continues(new, knobs))), None

    if checkpoint:
        body = jax.checkpoint(body)
    init = (pose_start(T, system_at(T)), jnp.asarray(True))
    (state, _), _ = jax.lax.scan(body, init, None, length=iterations)
    return state.x, state.system


class _Stationarity(NamedTuple):
    """F(T) = J^T W r at level 0 with the decisions in ``inputs`` fixed (aux: inliers); a
    hashable callable for custom_vjp's non-differentiable argument."""

    spec: _Spec

    def __call__(self, T, inputs):
        """F(T, inputs) (6,) and the inlier count."""
        params, data, mask_f, dots, valid_f = inputs
        system = _system(T, params, data, mask_f > 0.5, dots, valid_f > 0.5, 0, self.spec)
        return system.g, system.inliers


def _check_options(adjoint: str, consistency: str, interpolation: str) -> None:
    for name, value, allowed in (("adjoint", adjoint, ADJOINTS),
                                 ("consistency", consistency, CONSISTENCY),
                                 ("interpolation", interpolation, INTERPOLATIONS)):
        if value not in allowed:
            raise ValueError(f"{name} must be one of {allowed}, got {value!r}")


def _data_at(level: int, kf: KeyframeEdges, dist, intr: Intrinsics, mag) -> _EdgeData:
    disc = jnp.zeros_like(kf.rho) if kf.disc is None else kf.disc
    return _EdgeData(unproject(intr, kf.uv, kf.rho), kf.rho, mag, disc, dist[level], intr)


def _as_arrays(kf: KeyframeEdges, dist, intr, mag):
    """Intrinsics as arrays of the fields' dtype, the magnitudes (K,) (``kf.mag`` when None,
    zeros when that is None too)."""
    dtype = dist[0].dtype
    intr = Intrinsics(*(jnp.asarray(v, dtype) for v in intr))
    mag = kf.mag if mag is None else mag
    mag = jnp.zeros_like(kf.rho) if mag is None else jnp.asarray(mag, kf.rho.dtype)
    return intr, mag


class _Inputs(NamedTuple):
    """The inputs that the forward solve of ``track_differentiable`` reads: keyframe edges,
    distance fields (one (H / 2**l, W / 2**l) array per level, pixels of the level), T_init
    (4, 4) T_cur_kf, level-0 intrinsics (arrays), params and magnitudes (K,)."""

    kf: KeyframeEdges
    dist: tuple[jnp.ndarray, ...]
    T_init: jnp.ndarray
    intr: Intrinsics
    params: Params
    mag: jnp.ndarray


def _solve_inputs(adjoint: str, kf: KeyframeEdges, dist, T_init, intr: Intrinsics,
                  params: Params, mag: jnp.ndarray) -> _Inputs:
    """The inputs as given (``adjoint="unrolled"``), or with their gradients stopped for
    ``adjoint="implicit"``, whose forward pass runs without gradients."""
    if adjoint == "implicit":  # the forward pass without gradients
        inputs = jax.lax.stop_gradient((kf, dist, T_init, intr, params, mag))
        return _Inputs(*inputs)
    return _Inputs(kf, dist, T_init, intr, params, mag)


def _coarse_to_fine(T: Pose, s: _Inputs, edge_map: jnp.ndarray, spec: _Spec,
                    knobs: SolveKnobs, checkpoint: bool) -> tuple[Pose, LevelSystem]:
    """The tracker's coarse-to-fine solve from T (T_cur_kf): ``config.iterations[l]`` LM
    tries (``_align``) per level, coarsest first, each taking its hard decisions afresh at
    every pose. Returns the pose and the last level-0 system."""
    config = spec.config
    for level in reversed(range(config.num_levels)):
        data = _data_at(level, s.kf, s.dist, s.intr, s.mag)

        def system_at(T, data=data, level=level):
            mask, dots = _decisions(T, s.params, data, s.kf, edge_map, level, spec)
            return _system(T, s.params, data, mask, dots, s.kf.valid, level, spec)

        T, final = _align(T, system_at, config.iterations[level], knobs, checkpoint)
    return T, final


def _refine_rounds(T: Pose, final: LevelSystem, s: _Inputs, edge_map: jnp.ndarray,
                   spec: _Spec, knobs: SolveKnobs, checkpoint: bool, rounds: int
                   ) -> tuple[Pose, jnp.ndarray, jnp.ndarray, LevelSystem]:
    """``rounds`` level-0 refinement rounds after the solve (module doc): the hard decisions
    of level 0 at the solve's pose T; each round holds them for ``config.iterations[0]`` LM
    tries (``settle``), then takes them again at the pose it reached. Returns the pose, the
    decisions the last round held (mask (K,), dots (K,); with no round, those at T) and the
    last system (``final`` with no round)."""
    config = spec.config
    data_s = _data_at(0, s.kf, s.dist, s.intr, s.mag)
    mask, dots = _decisions(T, s.params, data_s, s.kf, edge_map, 0, spec)

    def refine_round(T, mask, dots):
        def system_at(T):
            return _system(T, s.params, data_s, mask, dots, s.kf.valid, 0, spec)

        return _align(T, system_at, config.iterations[0], knobs, checkpoint, settle=True)

    def next_round(carry, _):  # a round; then the decisions at its pose, for the next one
        T, mask, dots, _held = carry
        T, final = refine_round(T, mask, dots)
        decisions = _decisions(T, s.params, data_s, s.kf, edge_map, 0, spec)
        return (T, *decisions, (mask, dots, final)), None

    if rounds > 0:
        (T, _, _, (mask, dots, final)), _ = jax.lax.scan(
            next_round, (T, mask, dots, (mask, dots, final)), None, length=rounds)
    return T, mask, dots, final


def _implicit_at(T: Pose, params: Params, data: _EdgeData, mask: jnp.ndarray,
                 dots: jnp.ndarray, kf: KeyframeEdges, spec: _Spec
                 ) -> tuple[Pose, LevelSystem]:
    """T (T_cur_kf) unchanged, its gradient through the implicit function theorem on the
    level-0 stationarity with the decisions mask (K,), dots (K,) fixed (``_implicit_pose``),
    and the level-0 system there (with the gradients of params and data)."""
    f = data.pts_k.dtype
    inputs = (params, data, mask.astype(f), dots, kf.valid.astype(f))
    T = unflat(implicit_pose(_Stationarity(spec), flat(T), inputs))
    return T, _system(T, params, data, mask, dots, kf.valid, 0, spec)


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
    interpolation: str = "bilinear",
    refine: int = 0,
    checkpoint: bool = False,
) -> TrackResult:
    """``align.track`` with learnable ``params``, differentiable w.r.t. them (and the float
    inputs) through ``adjoint`` ("unrolled" or "implicit", see the module docstring).

    mag (K,): gradient magnitude of each keyframe edge for the weighting model (default
    ``kf.mag``, zeros when that is None; ``edge_magnitudes`` looks them up).
    ``interpolation``: how the distance fields are read, "bilinear" (the plain tracker's) or
    "bicubic" (``interp.bicubic_with_grad``: C1, the cost has a gradient everywhere).
    ``refine``: rounds of level-0 refinement after the coarse-to-fine solve; each holds the
    hard decisions taken at its start for ``config.iterations[0]`` LM tries (a step is also
    kept when it shrinks the gradient without raising the cost beyond rounding; a round stops
    early on ``config.step_tol``: set it to 0, the default 1e-5 leaves the pose ~1e-6 from
    stationary), then takes them again (module docstring: with "bicubic", float64, step_tol
    0 and a few rounds the pose is a
    stationary point of its own decisions, where the implicit adjoint is exact; the rounds
    can also cycle between decision sets: ``newton_decrement`` tells).
    ``consistency="hard"`` with ``Params.default(config)``, bilinear and no refinement runs
    the plain tracker's computation (same tries, same decisions). Jit with ``config``,
    ``adjoint``, ``consistency``, ``interpolation``, ``refine``, ``checkpoint`` static.
    """
    _check_options(adjoint, consistency, interpolation)
    spec = _Spec(config, consistency, interpolation)
    intr, mag = _as_arrays(kf, dist, intr, mag)
    knobs = solve_knobs(config)
    s = _solve_inputs(adjoint, kf, dist, T_init, intr, params, mag)
    T = Pose.from_matrix(jnp.asarray(s.T_init, dist[0].dtype))
    T, final = _coarse_to_fine(T, s, edge_map, spec, knobs, checkpoint)
    T, mask, dots, final = _refine_rounds(T, final, s, edge_map, spec, knobs, checkpoint,
                                          refine)
    data = _data_at(0, kf, dist, intr, mag)
    if adjoint == "implicit":  # the stationarity of the decisions at (or held to) T
        T, final = _implicit_at(T, params, data, mask, dots, kf, spec)
    start = Pose.from_matrix(jnp.asarray(s.T_init, dist[0].dtype))
    return track_result(T, final, data.pts_k, kf, dist[0].shape, intr, start)


def level_system(
    kf: KeyframeEdges,
    dist: tuple[jnp.ndarray, ...],
    edge_map: jnp.ndarray,
    T_c_k: jnp.ndarray,
    intr: Intrinsics,
    params: Params,
    config: Config,
    *,
    level: int = 0,
    mag: jnp.ndarray | None = None,
    consistency: str = "soft",
    interpolation: str = "bilinear",
) -> tuple[LevelSystem, jnp.ndarray, jnp.ndarray]:
    """What ``track_differentiable``'s LM sees at pose T_c_k (4, 4) on ``level``: the normal
    equations (H = J^T W J, g = J^T W r = the gradient of the robust cost in a left twist,
    the cost, inliers), and the hard decisions taken at T_c_k: the inlier mask (K,) and
    g(p) . g(p') (K,) of the nearest edges (what the consistency test reads).
    ``newton_decrement(system)`` says how far from stationary the pose is."""
    _check_options("unrolled", consistency, interpolation)
    spec = _Spec(config, consistency, interpolation)
    intr, mag = _as_arrays(kf, dist, intr, mag)
    data = _data_at(level, kf, dist, intr, mag)
    T = Pose.from_matrix(jnp.asarray(T_c_k, dist[0].dtype))
    mask, dots = _decisions(T, params, data, kf, edge_map, level, spec)
    return _system(T, params, data, mask, dots, kf.valid, level, spec), mask, dots


def newton_decrement(system: LevelSystem) -> jnp.ndarray:
    """g^T H^-1 g of normal equations (Gauss-Newton H): twice the cost decrease that a full
    Gauss-Newton step predicts; ~0 (relative to the cost) at a stationary point."""
    H = system.H + 1e-12 * (jnp.trace(system.H) + 1.0) * jnp.eye(6, dtype=system.H.dtype)
    return system.g @ jnp.linalg.solve(H, system.g)


def track_window(
    kf: KeyframeEdges,
    dist: tuple[jnp.ndarray, ...],
    edge_map: jnp.ndarray,
    A: jnp.ndarray,
    B: jnp.ndarray,
    intr: Intrinsics,
    params: Params,
    config: Config,
    *,
    track=None,
    **options,
) -> TrackResult:
    """``track`` (default ``track_differentiable``; or ``smooth.track_smooth``) over a window
    of N frames in order against one keyframe, each frame starting from the constant-velocity
    prediction of the two before it (``chunk.predict_matrix``; A = T_(i-1)_kf,
    B = T_(i-2)_kf (4, 4) for the first frame): the scan tracker's loop
    (``chunk.track_chunk``) with learnable params. dist holds one (N, H / 2**l, W / 2**l)
    array per level, edge_map (N, H, W) arrays; ``options`` are ``track``'s keywords.
    Returns the N TrackResults stacked on a leading axis. With the unrolled adjoint (and the
    smooth mode) the gradient also flows through the predictions; with the implicit one it
    does not (a converged pose does not depend on its start)."""

    track = track_differentiable if track is None else track

    def step(carry, frame):
        a, b = carry
        res = track(kf, frame[0], frame[1], predict_matrix(a, b), intr, params, config,
                    **options)
        return (res.T_c_k, a), res

    _, out = jax.lax.scan(step, (A, B), (tuple(dist), edge_map))
    return out


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
