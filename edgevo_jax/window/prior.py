"""The window's Gaussian prior on its camera vector (poses and intrinsics): its terms at
the current estimate (first-estimate Jacobians), its layout as keyframes come and go, and
marginalisation into it (a keyframe, or stale edges' inverse depths) through the Schur
complement (``schur``)."""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..config import Config
from ..derive import MappingConfig
from ..geometry import Pose
from .problem import (
    EdgeResiduals,
    NormalEquations,
    WindowProblem,
    as_mapping_config,
    edge_residuals,
    inlier_mask,
    normal_equations,
    pair_hosts,
    remove_keyframe,
)
from .schur import eliminate_diagonal, marginalize


class Prior(NamedTuple):
    """Gaussian prior 0.5 dx^T H dx + b^T dx on the camera vector of a window (m = 6 n + 4).

    dx is the tangent-space offset of the current estimate from the linearisation point:
    dx_k = log(T_w_k T0_w_k^-1) (left, world frame) for each pose, dx_c = c - c0 for the
    intrinsics. H (m, m) and b (m,) come from marginalisation; poses (n, 4, 4) and
    intrinsics (4,) are the linearisation point; mask (m,) bool: the variables it constrains
    (H and b are zero elsewhere).
    """

    H: jnp.ndarray
    b: jnp.ndarray
    poses: jnp.ndarray
    intrinsics: jnp.ndarray
    mask: jnp.ndarray


def _tangent_offset(poses: jnp.ndarray, intrinsics: jnp.ndarray, prior: Prior) -> jnp.ndarray:
    """dx (m,) of the estimate from the prior's linearisation point, zero off its mask."""
    T = Pose.from_matrix(poses, orthonormalise=None)
    T0 = Pose.from_matrix(prior.poses, orthonormalise=None)
    dx = jnp.concatenate([T.log_relative(T0).reshape(-1), intrinsics - prior.intrinsics])
    return jnp.where(prior.mask, dx, 0.0)


def prior_terms(
    poses: jnp.ndarray, intrinsics: jnp.ndarray, prior: Prior
) -> tuple[jnp.ndarray, jnp.ndarray, jnp.ndarray]:
    """The prior's (H, gradient H dx + b, cost 0.5 dx^T H dx + b^T dx) at the estimate.

    First-estimate Jacobians: H is the one from marginalisation (never relinearised) and
    d dx / d xi is taken as the identity (dx stays small inside the window)."""
    dx = _tangent_offset(poses, intrinsics, prior)
    Hdx = prior.H @ dx
    return prior.H, Hdx + prior.b, 0.5 * dx @ Hdx + prior.b @ dx


def no_prior(problem: WindowProblem) -> Prior:
    """The zero prior of the window's layout (constrains nothing)."""
    m = 6 * problem.poses.shape[0] + 4
    dtype = problem.rho.dtype
    H, b, mask = jax.device_put((np.zeros((m, m), dtype), np.zeros(m, dtype),
                                 np.zeros(m, bool)))  # transfers, no program compiled
    return Prior(H=H, b=b, poses=problem.poses, intrinsics=problem.intrinsics, mask=mask)


def append_keyframe_to_prior(prior: Prior, T_w_new: np.ndarray) -> Prior:
    """The prior in the layout of a window with one more keyframe, appended last (pose
    T_w_new (4, 4)): zero rows and columns for its pose, which it does not constrain. On the
    host (numpy arrays out, the intrinsics as given): a copy into a larger zero layout, which
    needs no compiled program."""
    H0, b0, poses0, mask0 = (np.asarray(x) for x in (prior.H, prior.b, prior.poses,
                                                      prior.mask))
    m = H0.shape[0]
    at = m - 4  # the new pose goes between the poses and the intrinsics
    idx = np.concatenate([np.arange(at), np.arange(at + 6, m + 6)])
    H = np.zeros((m + 6, m + 6), H0.dtype)
    H[np.ix_(idx, idx)] = H0
    b = np.zeros(m + 6, b0.dtype)
    b[idx] = b0
    mask = np.zeros(m + 6, bool)
    mask[idx] = mask0
    poses = np.concatenate([poses0, np.asarray(T_w_new, poses0.dtype)[None]])
    return Prior(H=H, b=b, poses=poses, intrinsics=prior.intrinsics, mask=mask)


def with_prior(ne: NormalEquations, problem: WindowProblem, prior: Prior | None) -> NormalEquations:
    """``ne`` with the prior's terms (``prior_terms``) added; ``ne`` itself for None."""
    if prior is None:
        return ne
    H, g, cost = prior_terms(problem.poses, problem.intrinsics, prior)
    return ne._replace(H_cc=ne.H_cc + H, b_c=ne.b_c + g, cost=ne.cost + cost)


def marginalize_keyframe(
    problem: WindowProblem, drop_index: int, config: MappingConfig | Config,
    prior: Prior | None = None, *, stale: jnp.ndarray | None = None,
) -> Prior:
    """Prior on the remaining poses and the intrinsics left by marginalising keyframe
    ``drop_index``'s pose and the inverse depths of the edges it hosts.

    The dense linear system (camera vector plus the dropped keyframe's A depths) is built at
    the current estimate from the residuals of the dropped keyframe's edges in every other
    keyframe, plus the previous ``prior`` (H kept, gradient H dx + b); the residuals of other
    keyframes' edges seen in the dropped keyframe are discarded, as in DSO (marginalising them
    would couple the remaining depths into the prior). Then ``marginalize`` (Schur complement,
    Jacobi-scaled pseudo-inverse of the pose block, after the depths' diagonal block).
    Linearised once, here: the returned prior's H is the first-estimate one. The result is
    in the layout of ``remove_keyframe(problem, drop_index)`` (its linearisation point: the
    current remaining poses and intrinsics).
    ``stale`` (n - 1, A) bool, optional: edges of the remaining keyframes (in that layout)
    to marginalise next, as ``marginalize_edges`` of them on ``remove_keyframe(problem,
    drop_index)`` would, from the same evaluation of the residuals (both steps linearise at
    the same estimate); none set: the keyframe's prior as it is.
    Cost: the normal equations plus O(m^2 A) for the depths and a 6 x 6 pseudo-inverse.
    """
    n, _, A = problem.uv.shape
    m = 6 * n + 4
    cfg = as_mapping_config(config)
    e = edge_residuals(problem, cfg.eta)
    hosts = jnp.arange(n) == drop_index
    ne = with_prior(normal_equations(problem, cfg, hosts=hosts, residuals=e), problem, prior)
    cols = slice(drop_index * A, (drop_index + 1) * A)
    Hcp, h_pp = ne.H_cp[:, cols], ne.h_pp[cols]
    # the depths first (diagonal block: 1 / h, zero for unobserved slots), then the pose's
    # 6 x 6 block: the same Schur complement as eliminating both at once, without the
    # (6 + A)^2 pseudo-inverse (whose eigh took up to a second on some windows)
    el = eliminate_diagonal(ne.H_cc, Hcp, h_pp, ne.b_c, ne.b_p[cols])
    pose = np.arange(6 * drop_index, 6 * drop_index + 6)
    keep = np.setdiff1d(np.arange(m), pose)
    Hm, bm = marginalize(el.S, el.r, keep, pose)
    rest = remove_keyframe(problem, drop_index)
    out = Prior(H=Hm, b=bm, poses=rest.poses, intrinsics=rest.intrinsics,
                mask=jnp.ones(m - 6, bool))
    if stale is None:
        return out
    edges = jnp.concatenate([stale[:drop_index], jnp.zeros((1, A), bool),
                             stale[drop_index:]])
    also = _edges_marginalized(problem, e, edges, cfg, out, drop_index)
    return jax.tree.map(lambda a, b: jnp.where(jnp.any(stale), a, b), also, out)


def marginalize_edges(
    problem: WindowProblem, edges: jnp.ndarray, config: MappingConfig, prior: Prior
) -> Prior:
    """Prior left by marginalising the inverse depths of ``edges`` (n, A) bool (their
    residuals in every keyframe of the window), added to ``prior`` (whose H is kept, its
    gradient taken at the current estimate: first-estimate Jacobians). The depth block is
    diagonal, so the Schur complement (``schur.eliminate_diagonal``) needs no inverse but
    1 / h_pp. Linearisation point: the
    current poses and intrinsics."""
    cfg = as_mapping_config(config)
    return _edges_marginalized(problem, edge_residuals(problem, cfg.eta), edges, cfg, prior)


def _edges_marginalized(
    problem: WindowProblem, e: EdgeResiduals, edges: jnp.ndarray, cfg: MappingConfig,
    prior: Prior, dropped: int | None = None,
) -> Prior:
    """``marginalize_edges`` of ``edges`` (n, A) with the problem's residuals ``e``; with
    ``dropped`` (static) a keyframe already marginalised into ``prior``: its residuals and
    variables are left out, and the result is in the layout of ``remove_keyframe(problem,
    dropped)``."""
    n, _, A = problem.uv.shape
    inl = inlier_mask(e, e.considered, cfg) & edges[pair_hosts(n)]
    poses = problem.poses
    if dropped is not None:  # no residual in the dropped keyframe (nor of its edges: edges)
        inl = inl & (jnp.arange(n) != dropped)[:, None, None]
    ne = normal_equations(problem, cfg, mask=inl, residuals=e)
    if dropped is not None:
        ne = ne._replace(H_cc=_without(_without(ne.H_cc, 0, 6 * dropped, 6), 1, 6 * dropped, 6),
                         H_cp=_without(_without(ne.H_cp, 0, 6 * dropped, 6), 1, A * dropped, A),
                         h_pp=_without(ne.h_pp, 0, A * dropped, A),
                         b_c=_without(ne.b_c, 0, 6 * dropped, 6),
                         b_p=_without(ne.b_p, 0, A * dropped, A))
        poses = remove_keyframe(problem, dropped).poses
    H_p, g_p, _ = prior_terms(poses, problem.intrinsics, prior)
    el = eliminate_diagonal(H_p + ne.H_cc, ne.H_cp, ne.h_pp, g_p + ne.b_c, ne.b_p)
    return Prior(H=el.S, b=el.r, poses=poses, intrinsics=problem.intrinsics,
                 mask=jnp.ones_like(prior.mask))


def _without(x: jnp.ndarray, axis: int, start: int, size: int) -> jnp.ndarray:
    """``x`` without the ``size`` entries from ``start`` along ``axis`` (static): slices."""
    head = jax.lax.slice_in_dim(x, 0, start, axis=axis)
    tail = jax.lax.slice_in_dim(x, start + size, x.shape[axis], axis=axis)
    return jnp.concatenate([head, tail], axis=axis)
