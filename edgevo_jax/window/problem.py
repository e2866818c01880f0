"""Sliding-window joint refinement (EdgeVO's local mapping, after DSO): keyframe poses, the
inverse depths of the active edges and the intrinsics, with the depths eliminated by the Schur
complement, and a keyframe leaving the window through marginalisation into a Gaussian prior.

Residual of active edge p hosted by keyframe i, seen by keyframe j != i (c = fx, fy, cx, cy,
shared by back-projection and projection):

    r = D_j(pi_c(T_j_w T_w_i pi_c^-1(p, rho_p)))

Variables and their updates:
- poses: T_w_k <- exp(xi_k) T_w_k, xi_k = [v, w], a LEFT twist in the WORLD frame; a global
  rigid motion is then xi_k = g for every k, so the pose gauge is the direction [g, ..., g, 0];
- inverse depths: rho_p <- rho_p + d_p;  intrinsics: c <- c + d_c.
Camera vector (m = 6 n + 4): [xi_0, ..., xi_{n-1}, fx, fy, cx, cy]. Point vector (n A,):
host-major, edge a of keyframe k at k A + a.

Energy E = sum Huber(r) + prior (Huber(r) = r^2 / 2 inside the radius, so E = 0.5 sum w r^2
with IRLS weights w); normal equations H = J^T W J, b = J^T W r; Levenberg-Marquardt step
(H + lam diag H) delta = -b, the depth block (diagonal: an edge's depth enters only its own
residuals) eliminated by the Schur complement, the 6 n + 4 camera system solved densely.
Residuals out of the image, behind the camera, above the gate or (when the problem carries
gradients) failing EdgeVO's gradient test g(p) . g(p') >= eta get weight 0 and, in the cost,
the Huber cost of the gate (rejecting never lowers the cost).

Gauge: the energy is invariant to a global rigid motion and, since nothing measures depth
here, to a global scale (translations times s, inverse depths over s). ``refine`` holds the
pose of keyframe ``gauge_index`` (default 0, the oldest) fixed, and with ``fix_scale`` moves
every candidate back along the exact scale orbit (about that keyframe's centre, which leaves
every residual unchanged) so that the geometric mean of the active inverse depths stays that
of the initial estimate (the depth sensor's scale). A first-order projection of the steps
is not enough: each accepted step adds its second-order term, and the scale drifts. With a
depth prior (``depth_prior_sigma``) the sensor measures the scale and it is no gauge; the
restoration then only keeps the window's scale where it was.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..camera import Intrinsics, project, unproject
from ..config import Config
from ..derive import MappingConfig, window_config
from ..frontend.residuals import consistency_dots_known
from ..frontend.robust import huber_cost, huber_weights
from ..image.interp import bilinear, bilinear_with_grad
from ..image.preprocess import EdgeMap


class WindowProblem(NamedTuple):
    """The window of n keyframes with up to A active edges each (struct of arrays).

    poses (n, 4, 4) T_w_k; uv (n, 2, A) level-0 pixels of each keyframe's hosted edges;
    rho (n, A) their inverse depths (1/m); valid (n, A) bool (padding slots False);
    fields (n, H, W) level-0 distance fields (pixels), or a tuple of n (H, W) fields (no
    stacked copy); intrinsics (4,) fx, fy, cx, cy.
    Optional, for EdgeVO's gradient-consistency test (a match counts only where
    g(p) . g(p') >= eta, p' the nearest edge to the projection): grad (n, 2, A) the hosted
    edges' normalised image gradients and edge_map each keyframe's ``preprocess.EdgeMap``
    (stacked, (n, H, W) arrays, or a tuple of n EdgeMaps; preprocess.Frame.edge_map). None:
    no such test.
    rho_prior (n, A), optional: measured inverse depths (the depth sensor's), which
    MappingConfig.depth_prior_sigma turns into the prior term 0.5 ((rho - rho_prior) / sigma)^2
    per active edge. None: no depth measurement.
    row_twists (n, 6), optional: each keyframe's motion per level-0 row [v, w] under a
    rolling shutter (``frontend.shutter``; its hosted edges are already at its middle row's
    time): a point seen by keyframe j is moved into the row it lands on. Held fixed (not
    refined). None: global shutters.
    """

    poses: jnp.ndarray
    uv: jnp.ndarray
    rho: jnp.ndarray
    valid: jnp.ndarray
    fields: jnp.ndarray | tuple[jnp.ndarray, ...]
    intrinsics: jnp.ndarray
    grad: jnp.ndarray | None = None
    edge_map: EdgeMap | tuple[EdgeMap, ...] | None = None
    rho_prior: jnp.ndarray | None = None
    row_twists: jnp.ndarray | None = None

    @property
    def camera(self) -> Intrinsics:
        """The intrinsics as a camera.Intrinsics of scalars."""
        c = self.intrinsics
        return Intrinsics(c[0], c[1], c[2], c[3])


class NormalEquations(NamedTuple):
    """Blocks of the Gauss-Newton system of the window (see the module doc for the layouts).

    H_cc (m, m) camera block; H_cp (m, n A) camera-depth block; h_pp (n A,) the diagonal
    depth block; b_c (m,), b_p (n A,) gradients J^T W r; cost: the robust energy; count: the
    number of inlier residuals; mask (n, n-1, A): which (``EdgeResiduals`` layout).
    """

    H_cc: jnp.ndarray
    H_cp: jnp.ndarray
    h_pp: jnp.ndarray
    b_c: jnp.ndarray
    b_p: jnp.ndarray
    cost: jnp.ndarray
    count: jnp.ndarray
    mask: jnp.ndarray


class EdgeResiduals(NamedTuple):
    """Residuals of every (target j, s-th other keyframe i = pair_hosts(n)[j, s], edge a),
    shaped (n, n-1, A), with their Jacobians: J_rho (n, n-1, A) w.r.t. the host edge's inverse
    depth, J_xi (6, n, n-1, A) w.r.t. the HOST pose twist xi_i (the target's is exactly
    -J_xi, world-frame left twists), J_c (4, n, n-1, A) w.r.t. fx, fy, cx, cy; considered:
    valid host slot; ok: also in view, in front of the camera and finite; consistent: the
    gradient test passes (all True when the problem carries no gradients)."""

    r: jnp.ndarray
    J_rho: jnp.ndarray
    J_xi: jnp.ndarray
    J_c: jnp.ndarray
    considered: jnp.ndarray
    ok: jnp.ndarray
    consistent: jnp.ndarray


def pair_hosts(n: int) -> np.ndarray:
    """Static (n, n-1) table: row j lists the keyframes other than j (the hosts it sees)."""
    return np.array([[i for i in range(n) if i != j] for j in range(n)], np.int32).reshape(
        n, n - 1
    )


def as_mapping_config(config: MappingConfig | Config) -> MappingConfig:
    """A MappingConfig as it is; a run's Config through ``derive.window_config`` (the numbers
    the tracker's local map refines with)."""
    return config if isinstance(config, MappingConfig) else window_config(config)


def _rot(R: jnp.ndarray, P: jnp.ndarray) -> jnp.ndarray:
    """R @ P with R (..., 3, 3) broadcast against P (3, ..., A) over its middle axes."""
    return jnp.stack([sum(R[..., i, k, None] * P[k] for k in range(3)) for i in range(3)])


def _rot_t(R: jnp.ndarray, P: jnp.ndarray) -> jnp.ndarray:
    """R^T @ P, shapes as in ``_rot``."""
    return jnp.stack([sum(R[..., k, i, None] * P[k] for k in range(3)) for i in range(3)])


def edge_residual(
    field_j: jnp.ndarray, intrinsics: jnp.ndarray, T_w_i: jnp.ndarray, T_w_j: jnp.ndarray,
    uv: jnp.ndarray, rho: jnp.ndarray,
) -> tuple[jnp.ndarray, jnp.ndarray]:
    """The definition r = D_j(pi_c(T_j_w T_w_i pi_c^-1(p, rho))) for edges uv (2, K), rho (K,)
    hosted by i and seen by j; returns r (K,) and the in-view-and-in-front mask. (Reference
    for the analytic Jacobians; the solver uses ``edge_residuals``.)"""
    c = Intrinsics(intrinsics[0], intrinsics[1], intrinsics[2], intrinsics[3])
    R_j = T_w_j[:3, :3]
    pts_w = T_w_i[:3, :3] @ unproject(c, uv, rho) + T_w_i[:3, 3:]
    pts = R_j.T @ (pts_w - T_w_j[:3, 3:])  # T_j_w = T_w_j^-1
    r, inside = bilinear(field_j, project(c, pts))
    return r, inside & (pts[2] > 1e-6)


def edge_residuals(problem: WindowProblem, eta: float = 0.6) -> EdgeResiduals:
    """Residuals of every active edge in every other keyframe, with analytic Jacobians.

    With P_i = pi^-1(p, rho) (host), P_w = T_w_i P_i, P_j = T_j_w P_w and a = grad D_j .
    d pi / dP (at P_j): dr/dxi_i = [R_w_j a, P_w x R_w_j a], dr/dxi_j = -dr/dxi_i,
    dr/drho = -(R_i_j a) . P_i / rho, dr/dc = grad D_j . d pi/dc + (R_i_j a) . dP_i/dc.
    """
    n, _, A = problem.uv.shape
    hosts = pair_hosts(n)
    fx, fy, cx, cy = (problem.intrinsics[k] for k in range(4))
    rho = jnp.where(problem.valid, problem.rho, 1.0)
    z = 1.0 / rho
    P_i = jnp.stack([(problem.uv[:, 0] - cx) / fx * z, (problem.uv[:, 1] - cy) / fy * z, z])
    R_w, t_w = problem.poses[:, :3, :3], problem.poses[:, :3, 3]
    P_w = _rot(R_w, P_i) + t_w.T[:, :, None]  # (3, n, A)
    # gather the hosts seen by each target: (3, n, n-1, A)
    Pi_t, Pw_t = P_i[:, hosts], P_w[:, hosts]
    R_j = R_w[:, None]  # (n, 1, 3, 3): R_w_j of each target
    P_j = _rot_t(R_j, Pw_t - t_w.T[:, :, None, None])
    if problem.row_twists is not None:  # into the row of each target it lands on
        P_j = _rows_moved(P_j, problem.row_twists, problem.intrinsics, _height(problem))
    Z = P_j[2]
    front = Z > 1e-6
    iz = 1.0 / jnp.where(front, Z, 1.0)
    uv_j = jnp.stack([fx * P_j[0] * iz + cx, fy * P_j[1] * iz + cy])  # (2, n, n-1, A)
    flat = uv_j.reshape(2, n, (n - 1) * A).transpose(1, 0, 2)
    # one lookup per target keyframe in its own field (a stacked (n, H, W) array or a tuple
    # of n fields: the local map passes the keyframes' fields as they are, never copied)
    looked = [bilinear_with_grad(problem.fields[j], flat[j]) for j in range(n)]
    r_flat, grad_flat, inside = (jnp.stack(x) for x in zip(*looked, strict=True))
    r = r_flat.reshape(n, n - 1, A)
    grad = grad_flat.transpose(1, 0, 2).reshape(2, n, n - 1, A)
    inside = inside.reshape(n, n - 1, A)
    ax, ay = grad[0] * fx * iz, grad[1] * fy * iz
    a = jnp.stack([ax, ay, -(ax * P_j[0] + ay * P_j[1]) * iz])  # dr/dP_j
    aw = _rot(R_j, a)  # dr/dP_w
    J_w = jnp.stack([Pw_t[1] * aw[2] - Pw_t[2] * aw[1], Pw_t[2] * aw[0] - Pw_t[0] * aw[2],
                     Pw_t[0] * aw[1] - Pw_t[1] * aw[0]])
    J_xi = jnp.concatenate([aw, J_w])
    ai = _rot_t(R_w[hosts], aw)  # dr/dP_i
    rho_t = rho[hosts]
    J_rho = -(ai[0] * Pi_t[0] + ai[1] * Pi_t[1] + ai[2] * Pi_t[2]) / rho_t
    J_c = jnp.stack([
        grad[0] * P_j[0] * iz - ai[0] * Pi_t[0] / fx,
        grad[1] * P_j[1] * iz - ai[1] * Pi_t[1] / fy,
        grad[0] - ai[0] * Pi_t[2] / fx,
        grad[1] - ai[1] * Pi_t[2] / fy,
    ])
    considered = problem.valid[hosts]
    ok = considered & inside & front & jnp.isfinite(r)
    consistent = jnp.ones_like(ok)
    if problem.grad is not None and problem.edge_map is not None:
        g_host = jnp.moveaxis(problem.grad[hosts], 2, 0).reshape(2, n, (n - 1) * A)
        # the nearest edge's direction from the distances and field gradients just read
        # (``interp.nearest_edge_gradient`` would read the same field again)
        dots = [consistency_dots_known(g_host[:, j], _edge_codes(problem.edge_map, j),
                                       flat[j], r_flat[j], grad_flat[j]) for j in range(n)]
        consistent = (jnp.stack(dots) >= eta).reshape(n, n - 1, A)
    return EdgeResiduals(r, J_rho, J_xi, J_c, considered, ok, consistent)


def _height(problem: WindowProblem) -> int:
    """The keyframes' image rows (static)."""
    f = problem.fields
    return (f[0] if isinstance(f, tuple | list) else f[0]).shape[0]


def _rows_moved(P_j: jnp.ndarray, twists: jnp.ndarray, intrinsics: jnp.ndarray,
                height: int) -> jnp.ndarray:
    """Points (3, n, n-1, A) in the target keyframes' cameras moved into the rows they land
    on (``frontend.shutter.shutter_warp``, one fixed-point round), twists (n, 6) per row of
    each target; the Jacobians are left as at the unmoved point (the move is ~1e-2 of it)."""
    fy, cy = intrinsics[1], intrinsics[3]
    v, w = (twists[:, k].T[:, :, None, None] for k in (slice(0, 3), slice(3, 6)))
    moved = jnp.stack([w[1] * P_j[2] - w[2] * P_j[1] + v[0],
                       w[2] * P_j[0] - w[0] * P_j[2] + v[1],
                       w[0] * P_j[1] - w[1] * P_j[0] + v[2]])
    ref = 0.5 * (height - 1)

    def row(P):
        return fy * P[1] / jnp.where(P[2] > 1e-6, P[2], 1.0) + cy - ref

    return P_j - row(P_j - row(P_j) * moved) * moved


def _edge_codes(edge_map: EdgeMap | tuple[EdgeMap, ...], j: int) -> jnp.ndarray:
    """Keyframe j's direction codes (H, W) from stacked EdgeMap arrays or a tuple of them."""
    return edge_map.code[j] if isinstance(edge_map, EdgeMap) else edge_map[j].code


def robust_cost(e: EdgeResiduals, considered: jnp.ndarray, mask: jnp.ndarray,
                 cfg: MappingConfig) -> jnp.ndarray:
    """Huber cost of the residuals in ``mask`` (still in view), the gate's Huber cost for
    every other considered one (so that rejecting a residual never lowers the cost; for a
    fixed mask, a residual beyond the gate keeps its larger Huber cost)."""
    inl = mask & e.ok
    gate_cost = huber_cost(jnp.asarray(cfg.max_residual, e.r.dtype), cfg.huber_delta)
    return jnp.sum(jnp.where(inl, huber_cost(jnp.where(inl, e.r, 0.0), cfg.huber_delta),
                             jnp.where(considered, gate_cost, 0.0)))


def normal_blocks(e: EdgeResiduals, considered: jnp.ndarray, mask: jnp.ndarray,
            cfg: MappingConfig) -> NormalEquations:
    """The normal-equation blocks of the residuals in ``mask`` (see ``normal_equations``)."""
    n, _, A = e.r.shape
    ht = pair_hosts(n)
    tt = np.repeat(np.arange(n, dtype=np.int32)[:, None], n - 1, axis=1)
    r = jnp.where(mask, e.r, 0.0)
    w = jnp.where(mask, huber_weights(r, cfg.huber_delta), 0.0)
    J_rho = jnp.where(mask, e.J_rho, 0.0)
    J_xi = jnp.where(mask, e.J_xi, 0.0)
    J_c = jnp.where(mask, e.J_c, 0.0)
    wJx, wJc, wJr = w * J_xi, w * J_c, w * J_rho
    # per pair sums, then static incidence tables instead of scatters: S[j, s, k] = 1 where
    # keyframe k hosts pair (j, s); D = S - (k is its target) carries dr/dxi_j = -dr/dxi_i
    S = (ht[:, :, None] == np.arange(n)).astype(np.float64)
    D = S - (tt[:, :, None] == np.arange(n))
    S, D = jnp.asarray(S, r.dtype), jnp.asarray(D, r.dtype)
    Hxx = jnp.einsum("kjsa,ljsa->jskl", wJx, J_xi)  # (n, n-1, 6, 6)
    Hxc = jnp.einsum("kjsa,ljsa->jskl", wJx, J_c)  # (n, n-1, 6, 4)
    Hpose = jnp.einsum("jsp,jsq,jskl->pkql", D, D, Hxx).reshape(6 * n, 6 * n)
    Hpc = jnp.einsum("jsp,jskl->pkl", D, Hxc).reshape(6 * n, 4)
    Hcc = jnp.einsum("kjsa,ljsa->kl", wJc, J_c)
    H_cc = jnp.block([[Hpose, Hpc], [Hpc.T, Hcc]])
    b_pose = jnp.einsum("jsp,kjsa,jsa->pk", D, wJx, r).reshape(-1)
    b_c = jnp.concatenate([b_pose, jnp.einsum("kjsa,jsa->k", wJc, r)])
    Hxp = jnp.einsum("jsp,jsh,kjsa->pkha", D, S, wJx * J_rho).reshape(6 * n, n * A)
    Hcp = jnp.einsum("jsh,kjsa->kha", S, wJc * J_rho).reshape(4, n * A)
    H_cp = jnp.concatenate([Hxp, Hcp])
    h_pp = jnp.einsum("jsh,jsa->ha", S, wJr * J_rho).reshape(-1)
    b_p = jnp.einsum("jsh,jsa->ha", S, wJr * r).reshape(-1)
    cost = robust_cost(e, considered, mask, cfg)
    return NormalEquations(H_cc, H_cp, h_pp, b_c, b_p, cost, jnp.sum(mask), mask)


def depth_prior_terms(problem: WindowProblem, cfg: MappingConfig,
                 hosts: jnp.ndarray | None = None):
    """(h_pp, b_p, cost) of the measured-depth prior 0.5 sum ((rho - rho_prior) / sigma)^2 over
    the valid edges (of ``hosts`` only, when given), or None without one."""
    if problem.rho_prior is None or cfg.depth_prior_sigma <= 0:
        return None
    on = problem.valid if hosts is None else problem.valid & hosts[:, None]
    w = jnp.where(on, 1.0 / cfg.depth_prior_sigma ** 2, 0.0).astype(problem.rho.dtype)
    d = jnp.where(on, problem.rho - problem.rho_prior, 0.0)
    return (w.reshape(-1), (w * d).reshape(-1), 0.5 * jnp.sum(w * d * d))


def with_depth_prior(ne: NormalEquations, problem: WindowProblem, cfg: MappingConfig,
                      hosts: jnp.ndarray | None = None) -> NormalEquations:
    """``ne`` with the measured-depth prior's terms (``depth_prior_terms``) added."""
    terms = depth_prior_terms(problem, cfg, hosts)
    if terms is None:
        return ne
    h, b, cost = terms
    return ne._replace(h_pp=ne.h_pp + h, b_p=ne.b_p + b, cost=ne.cost + cost)


def _considered(e: EdgeResiduals, hosts: jnp.ndarray | None) -> jnp.ndarray:
    n = e.r.shape[0]
    return e.considered if hosts is None else e.considered & hosts[pair_hosts(n)][:, :, None]


def inlier_mask(e: EdgeResiduals, considered: jnp.ndarray, cfg: MappingConfig) -> jnp.ndarray:
    """The inliers among the ``considered`` residuals: in view, gradient-consistent and
    under the gate (n, n-1, A)."""
    return considered & e.ok & e.consistent & (e.r <= cfg.max_residual)


def normal_equations(
    problem: WindowProblem, config: MappingConfig | Config, *,
    hosts: jnp.ndarray | None = None, mask: jnp.ndarray | None = None,
    residuals: EdgeResiduals | None = None,
) -> NormalEquations:
    """Huber-weighted Gauss-Newton blocks of the window at the current estimate.

    The inliers: valid, in view, in front, gradient-consistent (if the problem has gradients)
    and under the gate; or, if ``mask`` (n, n-1, A) is given, those of its residuals still
    in view (a fixed inlier set: ``refine`` judges a step with the set of the point it starts
    from, so that the cost it compares is continuous). hosts (n,) bool, optional: only the
    residuals of edges hosted by these keyframes count (``marginalize_keyframe``).
    ``residuals``: the problem's ``edge_residuals`` at this estimate, where the caller has
    them already (one evaluation for several systems at one linearisation point).
    Fixed shapes; the per-pair sums go into the blocks through static incidence tables (no
    scatter); the dense full Hessian is never formed.
    """
    cfg = as_mapping_config(config)
    e = edge_residuals(problem, cfg.eta) if residuals is None else residuals
    considered = _considered(e, hosts)
    inl = inlier_mask(e, considered, cfg) if mask is None else mask & considered & e.ok
    return with_depth_prior(normal_blocks(e, considered, inl, cfg), problem, cfg, hosts)


def remove_keyframe(problem: WindowProblem, index: int) -> WindowProblem:
    """The window without keyframe ``index`` (static): the others keep their order. Slices,
    not a gather: on the CPU, gathering the (n, H, W) fields costs ~5x a copy (~15 ms per
    keyframe outside jit, as the local map calls it). Fields and edge maps given per keyframe
    (tuples) are dropped from the tuple, not copied."""
    n = problem.poses.shape[0]
    index = range(n)[index]  # IndexError outside the window; negative counts from the end

    def without(x):
        if index == 0:
            return x[1:]
        return x[:-1] if index == n - 1 else jnp.concatenate([x[:index], x[index + 1:]])

    def drop(name, a):
        if name == "intrinsics" or a is None:
            return a
        if _per_keyframe(a):  # a tuple of the keyframes' own arrays: leave one out
            return tuple(x for k, x in enumerate(a) if k != index)
        return jax.tree.map(without, a)

    return WindowProblem(*(drop(name, a)
                           for name, a in zip(WindowProblem._fields, problem, strict=True)))


def _per_keyframe(a) -> bool:
    """Whether a WindowProblem's fields / edge_map entry is a tuple with one item per
    keyframe (rather than arrays stacked on a leading axis)."""
    return isinstance(a, tuple | list) and not isinstance(a, EdgeMap)


