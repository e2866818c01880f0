"""Levenberg-Marquardt on the window's robust energy plus its prior (``refine``): the
gauge, the pose-only warm-up, the fixed-inlier-set acceptance and the scale restoration
(see ``window``'s module doc for the problem)."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..config import Config
from ..derive import MappingConfig
from ..geometry import Pose
from ..solvers import WINDOW_DAMPING, LevenbergMarquardt
from .prior import Prior, no_prior, with_prior
from .problem import (
    NormalEquations,
    WindowProblem,
    as_mapping_config,
    depth_prior_terms,
    edge_residuals,
    inlier_mask,
    normal_blocks,
    robust_cost,
    with_depth_prior,
)
from .schur import schur_solve


def _restore_scale(problem: WindowProblem, log_rho_sum: jnp.ndarray,
                   gauge_index: int) -> WindowProblem:
    """Move along the exact scale orbit (translations about keyframe gauge_index's centre
    times e^-a, inverse depths times e^a: every residual unchanged) so that the sum of the
    active edges' log inverse depths is log_rho_sum again."""
    valid = problem.valid
    logs = jnp.where(valid, jnp.log(jnp.where(valid, problem.rho, 1.0)), 0.0)
    a = (log_rho_sum - jnp.sum(logs)) / jnp.maximum(jnp.sum(valid), 1)
    t = problem.poses[:, :3, 3]
    t = t[gauge_index] + (t - t[gauge_index]) * jnp.exp(-a)
    return problem._replace(poses=problem.poses.at[:, :3, 3].set(t),
                            rho=jnp.where(valid, problem.rho * jnp.exp(a), problem.rho))


def _apply(problem: WindowProblem, delta_c: jnp.ndarray, delta_p: jnp.ndarray,
           min_rho: float) -> WindowProblem:
    n, _, A = problem.uv.shape
    # exp(xi) T as a 4x4 product
    T = (Pose.exp(delta_c[: 6 * n].reshape(n, 6), method="quaternion")
         @ Pose.from_matrix(problem.poses, orthonormalise=None)).as_matrix()
    rho = jnp.where(problem.valid,
                    jnp.maximum(problem.rho + delta_p.reshape(n, A), min_rho), problem.rho)
    return problem._replace(poses=T, rho=rho,
                            intrinsics=problem.intrinsics + delta_c[6 * n:])


class _Judged(NamedTuple):
    """The window's LM system: the normal equations at a point (with its own inlier set) and
    the energy of that point judged with the inlier set of the point the try started from
    (what ``refine`` compares against the start's own energy)."""

    ne: NormalEquations
    fixed_set_cost: jnp.ndarray


def _judged_system(p: WindowProblem, prev_mask: jnp.ndarray, cfg: MappingConfig,
                   prior: Prior) -> _Judged:
    """The normal equations at p (its own inliers, the depth prior and ``prior`` added) and
    p's energy judged with the inliers ``prev_mask`` (n, n-1, A) of the try's start."""
    e = edge_residuals(p, cfg.eta)
    inl = inlier_mask(e, e.considered, cfg)
    ne = with_depth_prior(normal_blocks(e, e.considered, inl, cfg), p, cfg)
    terms = depth_prior_terms(p, cfg)
    fixed_cost = robust_cost(e, e.considered, prev_mask, cfg) + (
        0.0 if terms is None else terms[2])
    ne_p = with_prior(ne, p, prior)
    return _Judged(ne_p, fixed_cost + (ne_p.cost - ne.cost))


def _fixed_variables(n: int, cfg: MappingConfig) -> tuple[np.ndarray, np.ndarray]:
    """Which of the 6 n + 4 camera variables stay fixed (static bool masks): in the pose-only
    warm-up (the gauge pose and the intrinsics) and in the joint tries (the gauge pose, and
    the intrinsics unless ``refine_intrinsics``)."""
    m = 6 * n + 4
    gauge = np.zeros(m, bool)
    gauge[6 * cfg.gauge_index: 6 * cfg.gauge_index + 6] = True
    pose_only = gauge.copy()
    pose_only[6 * n:] = True
    joint = gauge.copy()
    joint[6 * n:] = not cfg.refine_intrinsics
    return pose_only, joint


def _damped_step(ne: NormalEquations, lam: jnp.ndarray, joint_stage: jnp.ndarray,
                 pose_only: np.ndarray, joint: np.ndarray, cfg: MappingConfig
                 ) -> tuple[jnp.ndarray, jnp.ndarray]:
    """The damped Schur-complement step (camera (m,), depths (n A,)) with the stage's fixed
    variables held (identity rows) and, before the joint stage, the depths frozen; zeros
    where the solve is not finite."""
    fixed = jnp.where(joint_stage, jnp.asarray(joint), jnp.asarray(pose_only))
    depths = joint_stage & cfg.refine_depths
    free = ~fixed
    H_cc = jnp.where(free[:, None] & free[None, :], ne.H_cc, 0.0) + jnp.diag(
        fixed.astype(ne.H_cc.dtype))
    H_cp = jnp.where(free[:, None] & depths, ne.H_cp, 0.0)
    h_pp = jnp.where(depths, ne.h_pp, 0.0)  # zero depth rows: schur_solve gives delta 0
    dc, dp = schur_solve(H_cc, H_cp, h_pp, jnp.where(free, ne.b_c, 0.0), ne.b_p, lam)
    ok = jnp.all(jnp.isfinite(dc)) & jnp.all(jnp.isfinite(dp))
    return jnp.where(ok, dc, 0.0), jnp.where(ok, dp, 0.0)


def _at(problem: WindowProblem, x) -> WindowProblem:
    """``problem`` with the LM point x = (poses (n, 4, 4) T_w_k, rho (n, A) inverse depths
    (1/m), intrinsics (4,) fx, fy, cx, cy in pixels) put in; every other field as it was."""
    return problem._replace(poses=x[0], rho=x[1], intrinsics=x[2])


def _log_rho_sum(problem: WindowProblem) -> jnp.ndarray:
    """The sum () of the active edges' log inverse depths (log 1/m): the scale that
    ``_restore_scale`` gives back after every step."""
    return jnp.sum(jnp.where(problem.valid,
                             jnp.log(jnp.where(problem.valid, problem.rho, 1.0)), 0.0))


def _try_body(problem: WindowProblem, cfg: MappingConfig, prior: Prior,
              lm: LevenbergMarquardt, log_rho_sum: jnp.ndarray) -> Callable:
    """The while-loop body of ``refine``: carry (i () int, LMState over the point of ``_at``
    with a ``_Judged`` system, cost0 ()) -> the carry after try i. Try 0 only evaluates the
    start (cost0 = its energy), tries 1 .. warmup_iterations move the poses alone, the later
    ones are joint (lam reset to ``lambda_init`` for the first); with ``fix_scale`` every
    candidate is moved back to the scale ``log_rho_sum`` (()) of the start."""
    warm = cfg.warmup_iterations
    pose_only, joint = _fixed_variables(problem.poses.shape[0], cfg)

    def body(carry):
        # try i = 0 evaluates the start; tries 1..warm move the poses alone
        i, state, cost0 = carry
        state = state._replace(lam=jnp.where(i == warm + 1, cfg.lambda_init, state.lam))

        def solve(x, judged: _Judged, lam):
            dc, dp = _damped_step(judged.ne, lam, i > warm, pose_only, joint, cfg)
            return jnp.where(i == 0, 0.0, dc), jnp.where(i == 0, 0.0, dp)

        def apply(x, delta):
            p_new = _apply(_at(problem, x), delta[0], delta[1], cfg.min_rho)
            if cfg.fix_scale:
                p_new = _restore_scale(p_new, log_rho_sum, cfg.gauge_index)
            return (p_new.poses, p_new.rho, p_new.intrinsics)

        state, new = lm.step(
            state, solve=solve, apply=apply,
            evaluate=lambda x, judged: _judged_system(_at(problem, x), judged.ne.mask, cfg,
                                                      prior),
            accept=lambda old, new: new.fixed_set_cost < old.ne.cost,
            norm=lambda d: jnp.sqrt(d[0] @ d[0] + d[1] @ d[1]))
        # a converged warm-up must not end the loop before the joint tries
        state = state._replace(step=jnp.where((i == 0) | (i == warm), jnp.inf, state.step))
        return i + 1, state, jnp.where(i == 0, new.ne.cost, cost0)

    return body


def _initial_carry(problem: WindowProblem, cfg: MappingConfig, prior: Prior,
                   lm: LevenbergMarquardt) -> tuple:
    """The carry before try 0: (i = 0, the LMState at ``problem``'s point (``_at``) with
    zero normal equations of the window's shapes and an infinite cost (so that try 0, a zero
    step, is kept and evaluates the start; lam and step in ``problem.rho``'s dtype),
    cost0 = inf)."""
    dtype = problem.rho.dtype
    n_, _, A_ = problem.uv.shape
    shapes = jax.eval_shape(lambda p, m: _judged_system(p, m, cfg, prior), problem,
                            jnp.zeros((n_, n_ - 1, A_), bool)).ne
    ne0 = jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), shapes)
    ne0 = ne0._replace(cost=jnp.asarray(jnp.inf, shapes.cost.dtype))
    x0 = (problem.poses, problem.rho, problem.intrinsics)
    return (jnp.asarray(0), lm.init(x0, _Judged(ne0, ne0.cost), dtype), ne0.cost)


def refine(
    problem: WindowProblem, config: MappingConfig | Config, prior: Prior | None = None,
    iterations: int | None = None,
) -> tuple[WindowProblem, dict[str, jnp.ndarray]]:
    """Levenberg-Marquardt on the window's robust energy (plus ``prior``, if any).

    Each iteration: the IRLS normal equations (``normal_equations``), the prior's terms
    (first-estimate Jacobians: its H is kept from when it was made, its gradient is
    H dx + b at the current offset dx, see ``prior_terms``), the pose of ``gauge_index``
    held fixed (its rows and columns replaced by the identity), the Schur-complement solve
    with lam diag(H) damping, the scale restored (``fix_scale``, module doc), and the step
    kept only if it lowers the energy judged with the inlier set of the point it starts from
    (gating and the gradient test are steps in the cost: with the set re-decided inside the
    comparison, LM stalls against them), then lam x 0.1 and a new inlier set, else lam x 10
    (``solvers.WINDOW_DAMPING``: lam from ``lambda_init``, within [1e-7, 1e4]).
    The first ``warmup_iterations`` tries move the poses alone (depths and intrinsics
    frozen: the poses, fitted by all edges at once, converge from further away than one
    edge's depth can, and the weakly observable intrinsics would absorb the depths' errors),
    then ``iterations`` (argument, else the config's) joint ones, lam reset to
    ``lambda_init`` for the first of them. One lax.while_loop that
    evaluates the residuals once per try; jit with ``config`` and ``iterations`` static
    (None stands for ``no_prior(problem)``; pass that explicitly to share one compiled
    program between calls with and without a prior).
    Returns the refined problem (poses, rho, intrinsics) and stats: cost_before, cost_after
    (robust energy with its own inlier set), inliers (count), iterations (tries).
    """
    cfg = as_mapping_config(config)
    prior = no_prior(problem) if prior is None else prior
    iters = cfg.iterations if iterations is None else iterations
    warm = cfg.warmup_iterations
    lm = dataclasses.replace(WINDOW_DAMPING, lam_init=cfg.lambda_init)

    def cond(carry):
        i, state, _ = carry
        return (i <= warm + iters) & (lm.continues(state, cfg.step_tol) | (i <= warm))

    body = _try_body(problem, cfg, prior, lm, _log_rho_sum(problem))
    init = _initial_carry(problem, cfg, prior, lm)
    i, state, cost0 = jax.lax.while_loop(cond, body, init)
    ne = state.system.ne
    stats = {"cost_before": cost0, "cost_after": ne.cost, "inliers": ne.count,
             "iterations": i - 1}
    return _at(problem, state.x), stats
