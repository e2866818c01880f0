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

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .camera import Intrinsics, project, unproject
from .config import Config
from .derive import MappingConfig, window_config
from .geometry import Pose
from .interp import EdgeMap, bilinear, bilinear_with_grad
from .residuals import consistency_dots_known
from .robust import huber_cost, huber_weights
from .schur import eliminate_diagonal, marginalize, schur_solve
from .solvers import WINDOW_DAMPING


class WindowProblem(NamedTuple):
    """The window of n keyframes with up to A active edges each (struct of arrays).

    poses (n, 4, 4) T_w_k; uv (n, 2, A) level-0 pixels of each keyframe's hosted edges;
    rho (n, A) their inverse depths (1/m); valid (n, A) bool (padding slots False);
    fields (n, H, W) level-0 distance fields (pixels), or a tuple of n (H, W) fields (no
    stacked copy); intrinsics (4,) fx, fy, cx, cy.
    Optional, for EdgeVO's gradient-consistency test (a match counts only where
    g(p) . g(p') >= eta, p' the nearest edge to the projection): grad (n, 2, A) the hosted
    edges' normalised image gradients and edge_map each keyframe's ``interp.EdgeMap``
    (stacked, (n, H, W) arrays, or a tuple of n EdgeMaps; preprocess.Frame.edge_map). None:
    no such test.
    rho_prior (n, A), optional: measured inverse depths (the depth sensor's), which
    MappingConfig.depth_prior_sigma turns into the prior term 0.5 ((rho - rho_prior) / sigma)^2
    per active edge. None: no depth measurement.
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

    @property
    def camera(self) -> Intrinsics:
        """The intrinsics as a camera.Intrinsics of scalars."""
        c = self.intrinsics
        return Intrinsics(c[0], c[1], c[2], c[3])


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


def _as_mapping_config(config: MappingConfig | Config) -> MappingConfig:
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


def _edge_codes(edge_map: EdgeMap | tuple[EdgeMap, ...], j: int) -> jnp.ndarray:
    """Keyframe j's direction codes (H, W) from stacked EdgeMap arrays or a tuple of them."""
    return edge_map.code[j] if isinstance(edge_map, EdgeMap) else edge_map[j].code


def _robust_cost(e: EdgeResiduals, considered: jnp.ndarray, mask: jnp.ndarray,
                 cfg: MappingConfig) -> jnp.ndarray:
    """Huber cost of the residuals in ``mask`` (still in view), the gate's Huber cost for
    every other considered one (so that rejecting a residual never lowers the cost; for a
    fixed mask, a residual beyond the gate keeps its larger Huber cost)."""
    inl = mask & e.ok
    gate_cost = huber_cost(jnp.asarray(cfg.max_residual, e.r.dtype), cfg.huber_delta)
    return jnp.sum(jnp.where(inl, huber_cost(jnp.where(inl, e.r, 0.0), cfg.huber_delta),
                             jnp.where(considered, gate_cost, 0.0)))


def _blocks(e: EdgeResiduals, considered: jnp.ndarray, mask: jnp.ndarray,
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
    cost = _robust_cost(e, considered, mask, cfg)
    return NormalEquations(H_cc, H_cp, h_pp, b_c, b_p, cost, jnp.sum(mask), mask)


def _depth_prior(problem: WindowProblem, cfg: MappingConfig,
                 hosts: jnp.ndarray | None = None):
    """(h_pp, b_p, cost) of the measured-depth prior 0.5 sum ((rho - rho_prior) / sigma)^2 over
    the valid edges (of ``hosts`` only, when given), or None without one."""
    if problem.rho_prior is None or cfg.depth_prior_sigma <= 0:
        return None
    on = problem.valid if hosts is None else problem.valid & hosts[:, None]
    w = jnp.where(on, 1.0 / cfg.depth_prior_sigma ** 2, 0.0).astype(problem.rho.dtype)
    d = jnp.where(on, problem.rho - problem.rho_prior, 0.0)
    return (w.reshape(-1), (w * d).reshape(-1), 0.5 * jnp.sum(w * d * d))


def _with_depth_prior(ne: NormalEquations, problem: WindowProblem, cfg: MappingConfig,
                      hosts: jnp.ndarray | None = None) -> NormalEquations:
    terms = _depth_prior(problem, cfg, hosts)
    if terms is None:
        return ne
    h, b, cost = terms
    return ne._replace(h_pp=ne.h_pp + h, b_p=ne.b_p + b, cost=ne.cost + cost)


def _considered(e: EdgeResiduals, hosts: jnp.ndarray | None) -> jnp.ndarray:
    n = e.r.shape[0]
    return e.considered if hosts is None else e.considered & hosts[pair_hosts(n)][:, :, None]


def _inliers(e: EdgeResiduals, considered: jnp.ndarray, cfg: MappingConfig) -> jnp.ndarray:
    return considered & e.ok & e.consistent & (e.r <= cfg.max_residual)


def normal_equations(
    problem: WindowProblem, config: MappingConfig | Config, *,
    hosts: jnp.ndarray | None = None, mask: jnp.ndarray | None = None,
) -> NormalEquations:
    """Huber-weighted Gauss-Newton blocks of the window at the current estimate.

    The inliers: valid, in view, in front, gradient-consistent (if the problem has gradients)
    and under the gate; or, if ``mask`` (n, n-1, A) is given, those of its residuals still
    in view (a fixed inlier set: ``refine`` judges a step with the set of the point it starts
    from, so that the cost it compares is continuous). hosts (n,) bool, optional: only the
    residuals of edges hosted by these keyframes count (``marginalize_keyframe``).
    Fixed shapes; the per-pair sums go into the blocks through static incidence tables (no
    scatter); the dense full Hessian is never formed.
    """
    cfg = _as_mapping_config(config)
    e = edge_residuals(problem, cfg.eta)
    considered = _considered(e, hosts)
    inl = _inliers(e, considered, cfg) if mask is None else mask & considered & e.ok
    return _with_depth_prior(_blocks(e, considered, inl, cfg), problem, cfg, hosts)


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
    return Prior(H=jnp.zeros((m, m), dtype), b=jnp.zeros(m, dtype), poses=problem.poses,
                 intrinsics=problem.intrinsics, mask=jnp.zeros(m, bool))


def append_keyframe_to_prior(prior: Prior, T_w_new: jnp.ndarray) -> Prior:
    """The prior in the layout of a window with one more keyframe, appended last (pose
    T_w_new (4, 4)): zero rows and columns for its pose, which it does not constrain."""
    m = prior.H.shape[0]
    at = m - 4  # the new pose goes between the poses and the intrinsics
    idx = np.concatenate([np.arange(at), np.arange(at + 6, m + 6)])
    H = jnp.zeros((m + 6, m + 6), prior.H.dtype).at[np.ix_(idx, idx)].set(prior.H)
    b = jnp.zeros(m + 6, prior.b.dtype).at[idx].set(prior.b)
    mask = jnp.zeros(m + 6, bool).at[idx].set(prior.mask)
    poses = jnp.concatenate([prior.poses, jnp.asarray(T_w_new, prior.poses.dtype)[None]])
    return Prior(H=H, b=b, poses=poses, intrinsics=prior.intrinsics, mask=mask)


def _with_prior(ne: NormalEquations, problem: WindowProblem, prior: Prior | None):
    if prior is None:
        return ne
    H, g, cost = prior_terms(problem.poses, problem.intrinsics, prior)
    return ne._replace(H_cc=ne.H_cc + H, b_c=ne.b_c + g, cost=ne.cost + cost)


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
    cfg = _as_mapping_config(config)
    prior = no_prior(problem) if prior is None else prior
    iters = cfg.iterations if iterations is None else iterations
    warm = cfg.warmup_iterations
    n = problem.poses.shape[0]
    m = 6 * n + 4
    gauge = np.zeros(m, bool)
    gauge[6 * cfg.gauge_index: 6 * cfg.gauge_index + 6] = True
    pose_only = gauge.copy()
    pose_only[6 * n:] = True
    joint = gauge.copy()
    joint[6 * n:] = not cfg.refine_intrinsics

    def system(p: WindowProblem, prev_mask: jnp.ndarray):
        """Blocks at p (own inliers, prior added) and the energy with prev_mask's inliers."""
        e = edge_residuals(p, cfg.eta)
        ne = _with_depth_prior(_blocks(e, e.considered, _inliers(e, e.considered, cfg), cfg),
                               p, cfg)
        terms = _depth_prior(p, cfg)
        fixed_cost = _robust_cost(e, e.considered, prev_mask, cfg) + (
            0.0 if terms is None else terms[2])
        ne_p = _with_prior(ne, p, prior)
        return ne_p, fixed_cost + (ne_p.cost - ne.cost)

    def step(p: WindowProblem, ne: NormalEquations, lam: jnp.ndarray, joint_stage: jnp.ndarray):
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

    def at(x) -> WindowProblem:
        return problem._replace(poses=x[0], rho=x[1], intrinsics=x[2])

    lm = dataclasses.replace(WINDOW_DAMPING, lam_init=cfg.lambda_init)

    def cond(carry):
        i, state, _ = carry
        return (i <= warm + iters) & (lm.continues(state, cfg.step_tol) | (i <= warm))

    def body(carry):
        # try i = 0 evaluates the start; tries 1..warm move the poses alone
        i, state, cost0 = carry
        state = state._replace(lam=jnp.where(i == warm + 1, cfg.lambda_init, state.lam))

        def solve(x, judged: _Judged, lam):
            dc, dp = step(at(x), judged.ne, lam, i > warm)
            return jnp.where(i == 0, 0.0, dc), jnp.where(i == 0, 0.0, dp)

        def apply(x, delta):
            p_new = _apply(at(x), delta[0], delta[1], cfg.min_rho)
            if cfg.fix_scale:
                p_new = _restore_scale(p_new, log_rho_sum, cfg.gauge_index)
            return (p_new.poses, p_new.rho, p_new.intrinsics)

        state, new = lm.step(
            state, solve=solve, apply=apply,
            evaluate=lambda x, judged: _Judged(*system(at(x), judged.ne.mask)),
            accept=lambda old, new: new.fixed_set_cost < old.ne.cost,
            norm=lambda d: jnp.sqrt(d[0] @ d[0] + d[1] @ d[1]))
        # a converged warm-up must not end the loop before the joint tries
        state = state._replace(step=jnp.where((i == 0) | (i == warm), jnp.inf, state.step))
        return i + 1, state, jnp.where(i == 0, new.ne.cost, cost0)

    dtype = problem.rho.dtype
    log_rho_sum = jnp.sum(jnp.where(problem.valid,
                                    jnp.log(jnp.where(problem.valid, problem.rho, 1.0)), 0.0))
    n_, _, A_ = problem.uv.shape
    shapes = jax.eval_shape(system, problem, jnp.zeros((n_, n_ - 1, A_), bool))[0]
    ne0 = jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), shapes)
    ne0 = ne0._replace(cost=jnp.asarray(jnp.inf, shapes.cost.dtype))
    x0 = (problem.poses, problem.rho, problem.intrinsics)
    init = (jnp.asarray(0), lm.init(x0, _Judged(ne0, ne0.cost), dtype), ne0.cost)
    i, state, cost0 = jax.lax.while_loop(cond, body, init)
    x, ne = state.x, state.system.ne
    out = problem._replace(poses=x[0], rho=x[1], intrinsics=x[2])
    stats = {"cost_before": cost0, "cost_after": ne.cost, "inliers": ne.count,
             "iterations": i - 1}
    return out, stats


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


def marginalize_keyframe(
    problem: WindowProblem, drop_index: int, config: MappingConfig | Config,
    prior: Prior | None = None,
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
    Cost: the normal equations plus O(m^2 A) for the depths and a 6 x 6 pseudo-inverse.
    """
    n, _, A = problem.uv.shape
    m = 6 * n + 4
    hosts = jnp.arange(n) == drop_index
    ne = _with_prior(normal_equations(problem, config, hosts=hosts), problem, prior)
    cols = slice(drop_index * A, (drop_index + 1) * A)
    Hcp, h_pp = ne.H_cp[:, cols], ne.h_pp[cols]
    # the depths first (diagonal block: 1 / h, zero for unobserved slots), then the pose's
    # 6 x 6 block: the same Schur complement as eliminating both at once, without the
    # (6 + A)^2 pseudo-inverse (whose eigh took up to a second on some windows)
    e = eliminate_diagonal(ne.H_cc, Hcp, h_pp, ne.b_c, ne.b_p[cols])
    pose = np.arange(6 * drop_index, 6 * drop_index + 6)
    keep = np.setdiff1d(np.arange(m), pose)
    Hm, bm = marginalize(e.S, e.r, keep, pose)
    rest = remove_keyframe(problem, drop_index)
    return Prior(H=Hm, b=bm, poses=rest.poses, intrinsics=rest.intrinsics,
                 mask=jnp.ones(m - 6, bool))


def marginalize_edges(
    problem: WindowProblem, edges: jnp.ndarray, config: MappingConfig, prior: Prior
) -> Prior:
    """Prior left by marginalising the inverse depths of ``edges`` (n, A) bool (their
    residuals in every keyframe of the window), added to ``prior`` (whose H is kept, its
    gradient taken at the current estimate: first-estimate Jacobians). The depth block is
    diagonal, so the Schur complement (``schur.eliminate_diagonal``) needs no inverse but
    1 / h_pp. Linearisation point: the
    current poses and intrinsics."""
    n = problem.poses.shape[0]
    inl = normal_equations(problem, config).mask
    ne = normal_equations(problem, config, mask=inl & edges[pair_hosts(n)])
    H_p, g_p, _ = prior_terms(problem.poses, problem.intrinsics, prior)
    e = eliminate_diagonal(H_p + ne.H_cc, ne.H_cp, ne.h_pp, g_p + ne.b_c, ne.b_p)
    return Prior(H=e.S, b=e.r, poses=problem.poses, intrinsics=problem.intrinsics,
                 mask=jnp.ones_like(prior.mask))
