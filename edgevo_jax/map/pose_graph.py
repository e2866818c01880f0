"""The pose graph over keyframes, the back end of loop closure: one node per keyframe (its
pose T_world_node), edges from tracking and the sliding window (plain squares, with the
information of their solves) and loop edges from verified place recognition (a Cauchy
kernel: a false loop loses its weight instead of bending the map).

Residual: an edge (i, j) measures Z_ij, the pose of node j in node i (T_i_j). Its error is the
twist r = [v, w] (6,) in frame j with T_i^-1 T_j = Z_ij exp(r), r = log(Z_ij^-1 T_i^-1 T_j),
and chi2 = r^T Omega r with Omega the edge's information (6, 6).

Cost: sum over valid edges of 0.5 rho(chi2), rho(s) = s on plain edges and
rho(s) = c^2 log(1 + s / c^2) on robust ones (c = ``robust_scale``).

Solve: ``solvers.POSE_GRAPH_DAMPING``'s Levenberg-Marquardt on one left twist per node
(T_k <- exp(delta_k) T_k), in a ``lax.while_loop``. Each try solves the Gauss-Newton normal
equations with iteratively reweighted robust edges (weights rho'(chi2) from the current
point) and the exact gradient, Marquardt-damped (H + lam diag H). With J_j = A the derivative
of r in node j's twist and J_i = -A, A = (d log(E exp(d)) / dd at 0) Ad(T_j^-1), E = exp(r),
H is block-sparse: M = w A^T Omega A on the diagonal blocks of i and j, -M at (i, j) and
(j, i). ``linear_solver="direct"`` (the default) factors it on the host (a sparse Cholesky,
``block_sparse.direct``: one numeric factorisation a try, whatever the graph's shape);
``linear_solver="cg"`` never forms it: preconditioned conjugate gradients (6x6
block-Jacobi) multiply by it one edge's blocks at a time on the device, in iterations that
grow with the graph. Fixed nodes, and free nodes that no valid edge touches, do not move
(zero rows and columns, identity on the diagonal). Each connected part of the graph needs a
fixed node: a part without one is held by the damping alone.

Derivative (reverse mode, a ``custom_vjp``): the implicit function theorem at the optimum
on the stationarity condition g = 0, g the cost's gradient in per-node left twists. g is
analytic (an edge's error carries its own JVP: ``Pose.log`` and ``Pose.exp`` are never
differentiated); its linearisation's transpose in the twists is the exact Hessian H
(symmetric at the optimum), and H lambda = (the cotangent as left twists) is solved, plus
eps max(diag H) for directions no edge constrains: "direct" forms H's blocks (each edge's
12x12 by forward mode, ``_hessian``) and factors it, "cg" runs the same PCG on H's products.
The cotangents of ``measured`` (tangents off SE(3) projected onto it) and ``information``
are -(dg / dtheta)^T lambda. The start (``poses``, fixed nodes included) is a constant: its
derivative is zero.

Everything is pure, jitted (``optimise``) and shape-static: padded nodes and edges are
masked, so graphs of one padded size share one program, and ``jax.vmap`` batches graphs
("direct" factors a batch's graphs one after another on the host; "cg" stays on the device).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..geometry import Pose
from ..solvers import POSE_GRAPH_DAMPING
from .block_sparse import Blocks, block_jacobi, direct, pcg

#: The Cauchy kernel's default scale c: sqrt of chi-square's 99 % quantile with 6 degrees of
#: freedom (16.81), so a loop edge as far off as the worst 1 % of inliers keeps half its weight.
ROBUST_SCALE = math.sqrt(16.81)

_MAX_REJECTS = 6  # rejected tries in a row before LM stops (lam x 10 each)
_RESOLVED = 64  # steps under 64 eps max|t| (the poses' rounding, eps the dtype's) end a solve


class PoseGraph(NamedTuple):
    """A pose graph (a pytree of fixed shapes; padding by masks).

    poses (N, 4, 4): T_world_node, the start of the optimisation; i, j (E,) int32: the two
    nodes of each edge; measured (E, 4, 4): Z_ij, the measured T_i_j; information (E, 6, 6):
    symmetric positive definite, of the error twist r (6,) = [v, w] with
    T_i^-1 T_j = Z_ij exp(r) (r in frame j); robust (E,) bool: a Cauchy kernel on the edge
    (loop edges), else plain squares; valid (E,) bool: False = padding, ignored;
    fixed (N,) bool: nodes held at their start (the gauge; padding nodes are fixed)."""

    poses: jnp.ndarray
    i: jnp.ndarray
    j: jnp.ndarray
    measured: jnp.ndarray
    information: jnp.ndarray
    robust: jnp.ndarray
    valid: jnp.ndarray
    fixed: jnp.ndarray


class Solution(NamedTuple):
    """What ``optimise`` returns. poses (N, 4, 4): the optimised T_world_node (fixed, padding
    and unconstrained nodes unchanged); chi2 (E,): r^T Omega r of each edge at the solution
    (0 for padding); weight (E,): rho'(chi2), the robust kernel's weight (1 on plain edges,
    0 on padding); cost (): the total robust cost; iterations () int32: LM tries taken."""

    poses: jnp.ndarray
    chi2: jnp.ndarray
    weight: jnp.ndarray
    cost: jnp.ndarray
    iterations: jnp.ndarray


def _slots(n: int) -> int:
    """The next power of two >= n, at least 64."""
    return max(64, 1 << max(0, n - 1).bit_length())


def graph(
    poses: np.ndarray,
    edges: Sequence[tuple[int, int, np.ndarray, np.ndarray, bool]],
    *,
    fixed: Iterable[int],
    nodes: int | None = None,
    edge_slots: int | None = None,
    dtype: np.dtype = np.float32,
) -> PoseGraph:
    """A ``PoseGraph`` from host data: ``poses`` (n, 4, 4) T_world_node; ``edges`` a sequence
    of (i, j, Z_ij (4, 4), information (6, 6), robust); ``fixed`` the node indices held at
    their start (at least one). Nodes are padded to ``nodes`` and edges to ``edge_slots``
    (default: the next power of two >= 64 of each: graphs of similar size share a program);
    padding nodes are identity and fixed, padding edges identity and invalid. Arrays of
    ``dtype`` (float64 needs ``jax.enable_x64``); indices int32."""
    poses = np.asarray(poses, np.float64).reshape(-1, 4, 4)
    edges = list(edges)
    n, m = poses.shape[0], len(edges)
    N = _slots(n) if nodes is None else nodes
    E = _slots(m) if edge_slots is None else edge_slots
    if N < n or E < m:
        raise ValueError(f"{n} nodes / {m} edges do not fit in {N} / {E} slots")
    fixed = sorted(set(int(k) for k in fixed))
    if not fixed or fixed[0] < 0 or fixed[-1] >= n:
        raise ValueError(f"fixed must name at least one node in [0, {n}), got {fixed}")
    P, Z, info = (np.tile(np.eye(d), (k, 1, 1)) for d, k in ((4, N), (4, E), (6, E)))
    P[:n] = poses
    ij, robust, valid = np.zeros((2, E), np.int32), np.zeros(E, bool), np.arange(E) < m
    for k, (a, b, z, om, rob) in enumerate(edges):
        if not (0 <= a < n and 0 <= b < n):
            raise ValueError(f"edge {k} joins nodes ({a}, {b}) outside [0, {n})")
        ij[:, k], Z[k], info[k], robust[k] = (a, b), z, om, bool(rob)
    fix = np.arange(N) >= n
    fix[fixed] = True
    return PoseGraph(jnp.asarray(P, dtype), jnp.asarray(ij[0]), jnp.asarray(ij[1]),
                     jnp.asarray(Z, dtype), jnp.asarray(info, dtype), jnp.asarray(robust),
                     jnp.asarray(valid), jnp.asarray(fix))


class _Edges(NamedTuple):
    """The non-differentiable part of a graph: i, j (E,), robust, valid (E,), movable (N,)."""

    i: jnp.ndarray
    j: jnp.ndarray
    robust: jnp.ndarray
    valid: jnp.ndarray
    movable: jnp.ndarray


def _edges(g: PoseGraph) -> _Edges:
    """The edges, and the movable nodes: not fixed and touched by a valid edge."""
    touched = jnp.zeros(g.fixed.shape, jnp.int32).at[g.i].add(g.valid).at[g.j].add(g.valid)
    return _Edges(g.i, g.j, g.robust, g.valid, (touched > 0) & ~g.fixed)


def _take(x: Pose, k: jnp.ndarray) -> Pose:
    return Pose(x.R[k], x.t[k])


def _residual(x: Pose, measured: jnp.ndarray, e: _Edges) -> jnp.ndarray:
    """The error twists r = log(Z_ij^-1 T_i^-1 T_j) (E, 6)."""
    Z = Pose.from_matrix(measured, orthonormalise=None)
    return jax.vmap(_edge_error)(_take(x, e.i), _take(x, e.j), Z)


def _hat(a: jnp.ndarray) -> jnp.ndarray:
    """[a]x (3, 3): its column k is a x e_k."""
    return jnp.cross(a, jnp.eye(3, dtype=a.dtype)).T


def _mm(a: jnp.ndarray, b: jnp.ndarray) -> jnp.ndarray:
    """a @ b for small matrices (..., n, k) @ (..., k, m), its k products written out: XLA's
    CPU backend runs batched products of 3x3 and 6x6 matrices as one small kernel each, and
    these fused elementwise ones 4-6x faster."""
    return sum(a[..., :, k, None] * b[..., None, k, :] for k in range(a.shape[-1]))


def _right_jacobian_inverse(r: jnp.ndarray) -> jnp.ndarray:
    """d log(exp(r) exp(d)) / dd at d = 0 (6, 6) for r = [v, w]: J_l^-1(-r) (Barfoot),
    [[K, -K Q K], [0, K]] with K = J_l^-1(phi) = I - W / 2 + D W^2 and Q(rho, phi)
    (rho, phi = -v, -w; W = [phi]x, P = [rho]x), its coefficients by their series (to
    theta^6) below theta = |w| = 0.5 in float32, 0.1 in float64 (where they cancel)."""
    P, W = _hat(-r[:3]), _hat(-r[3:])
    th2 = jnp.sum(r[3:] * r[3:])
    small = th2 < (0.25 if r.dtype == jnp.float32 else 1e-2)
    t2 = jnp.where(small, 1.0, th2)
    th = jnp.sqrt(t2)
    sin, cos = jnp.sin(th), jnp.cos(th)

    def series(c0, c1, c2, c3):
        return c0 + th2 * (c1 + th2 * (c2 + th2 * c3))

    a = jnp.where(small, series(1 / 6, -1 / 120, 1 / 5040, -1 / 362880), (th - sin) / (th * t2))
    b = jnp.where(small, series(1 / 24, -1 / 720, 1 / 40320, -1 / 3628800),
                  (t2 + 2 * cos - 2) / (2 * t2 * t2))
    c = jnp.where(small, series(1 / 120, -1 / 2520, 1 / 120960, -1 / 9979200),
                  (2 * th - 3 * sin + th * cos) / (2 * t2 * t2 * th))
    d = jnp.where(small, series(1 / 12, 1 / 720, 1 / 30240, 1 / 1209600),
                  (1 - 0.5 * th / jnp.tan(0.5 * th)) / t2)
    WP, PW, WW = _mm(W, P), _mm(P, W), _mm(W, W)
    WPW = _mm(WP, W)
    Q = (0.5 * P + a * (WP + PW + WPW) + b * (_mm(WW, P) + _mm(PW, W) - 3 * WPW)
         + c * (_mm(WPW, W) + _mm(W, WPW)))
    K = jnp.eye(3, dtype=r.dtype) - 0.5 * W + d * WW
    return jnp.block([[K, -_mm(_mm(K, Q), K)], [jnp.zeros_like(K), K]])


def _adjoint(T: Pose) -> jnp.ndarray:
    """Ad(T) (6, 6) for twists [v, w]: [[R, [t]x R], [0, R]] (T exp(xi) T^-1 = exp(Ad(T) xi))."""
    return jnp.block([[T.R, _mm(_hat(T.t), T.R)], [jnp.zeros_like(T.R), T.R]])


def _jacobian(r: jnp.ndarray, Tj: Pose) -> jnp.ndarray:
    """A (6, 6), the derivative of an edge's error r in node j's left twist (node i's is -A):
    T_j^-1 exp(d) T_j = exp(Ad(T_j^-1) d), then log's derivative on the right at exp(r)."""
    return _mm(_right_jacobian_inverse(r), _adjoint(Tj.inverse()))


def _left_twist(T: Pose, dT: Pose) -> jnp.ndarray:
    """The left twist (6,) of a tangent dT at T: dT T^-1 = [[W, u], [0, 0]] -> [u, vee(W)]
    (W's skew part: tangents off SE(3) are projected onto it)."""
    W = dT.R @ T.R.T
    w = 0.5 * jnp.stack([W[2, 1] - W[1, 2], W[0, 2] - W[2, 0], W[1, 0] - W[0, 1]])
    return jnp.concatenate([dT.t - jnp.cross(w, T.t), w])


@jax.custom_jvp
def _edge_error(Ti: Pose, Tj: Pose, Z: Pose) -> jnp.ndarray:
    """r = log(Z^-1 T_i^-1 T_j) (6,); its derivative is analytic (``_edge_error_jvp``), so
    derivatives never differentiate ``Pose.log`` itself."""
    ZiT, RiT = jnp.swapaxes(Z.R, -1, -2), jnp.swapaxes(Ti.R, -1, -2)
    t = _mm(RiT, (Tj.t - Ti.t)[..., None])[..., 0] - Z.t  # T_i^-1 T_j's, less Z's
    return Pose(_mm(ZiT, _mm(RiT, Tj.R)), _mm(ZiT, t[..., None])[..., 0]).log()


@_edge_error.defjvp
def _edge_error_jvp(primals, tangents):
    """With left twists d_i, d_j, d_Z of the tangents: Z^-1 T_i^-1 T_j moves by
    exp(Ad(T_j^-1) (d_j - d_i - Ad(T_i) d_Z)) on the right, so dr = A (d_j - d_i - Ad(T_i) d_Z)."""
    (Ti, Tj, Z), (dTi, dTj, dZ) = primals, tangents
    r = _edge_error(Ti, Tj, Z)
    d = _left_twist(Tj, dTj) - _left_twist(Ti, dTi) - _adjoint(Ti) @ _left_twist(Z, dZ)
    return r, _jacobian(r, Tj) @ d


def _robust(r: jnp.ndarray, information: jnp.ndarray, e: _Edges, c: float):
    """chi2 = r^T Omega r, rho(chi2) and rho'(chi2) (E,) each, 0 on padding."""
    chi2 = jnp.where(e.valid, jnp.einsum("ea,eab,eb->e", r, information, r), 0.0)
    s = chi2 / (c * c)
    rho = jnp.where(e.robust, c * c * jnp.log1p(s), chi2)
    weight = jnp.where(e.valid, jnp.where(e.robust, 1 / (1 + s), 1), 0)
    return chi2, jnp.where(e.valid, rho, 0.0), weight


class _System(NamedTuple):
    """The LM system at a point: cost (), gradient g (N, 6), weighted per-edge blocks
    M = w A^T Omega A (E, 6, 6), the diagonal blocks D of the Gauss-Newton Hessian (N, 6, 6)."""

    cost: jnp.ndarray
    g: jnp.ndarray
    M: jnp.ndarray
    D: jnp.ndarray


def _scatter(e: _Edges, n: int, on_j: jnp.ndarray, on_i: jnp.ndarray) -> jnp.ndarray:
    return jnp.zeros((n, *on_j.shape[1:]), on_j.dtype).at[e.j].add(on_j).at[e.i].add(on_i)


def _edge_terms(xi: Pose, xj: Pose, measured: jnp.ndarray, information: jnp.ndarray,
                e: _Edges, c: float):
    """Each edge's share at its nodes' poses xi, xj (E,): rho(chi2) (E,), its gradient in
    node j's left twist w A^T Omega r (E, 6) (node i's is minus it) and M = w A^T Omega A
    (E, 6, 6), the Gauss-Newton block (w = rho'(chi2), frozen)."""
    r = jax.vmap(_edge_error)(xi, xj, Pose.from_matrix(measured, orthonormalise=None))
    A = jax.vmap(_jacobian)(r, xj)
    _, rho, w = _robust(r, information, e, c)
    WA = w[:, None, None] * _mm(information, A)  # w Omega A
    ge = jnp.einsum("eba,eb->ea", WA, r)  # w A^T Omega r
    return rho, ge, _mm(jnp.swapaxes(A, 1, 2), WA)


def _system(x: Pose, measured: jnp.ndarray, information: jnp.ndarray, e: _Edges, c: float
            ) -> _System:
    rho, ge, M = _edge_terms(_take(x, e.i), _take(x, e.j), measured, information, e, c)
    n = x.t.shape[0]
    g = jnp.where(e.movable[:, None], _scatter(e, n, ge, -ge), 0.0)
    return _System(0.5 * jnp.sum(rho), g, M, _scatter(e, n, M, M))


def _hessian(x: Pose, measured: jnp.ndarray, information: jnp.ndarray, e: _Edges, c: float
             ) -> Blocks:
    """The exact Hessian dg/dd (as ``Blocks``) of the left gradient g (``_System.g``) in the
    nodes' left twists d (exp(d) x, ``_moved``), the weights rho' differentiated too: each
    edge's (12, 12) derivative of its two gradient blocks in its two nodes' twists, by 12
    forward-mode products over all edges at once."""
    xi, xj = _take(x, e.i), _take(x, e.j)

    def gradients(d):  # (E, 12) -> (E, 12): edge e's gradient blocks on nodes i and j
        _, ge, _ = _edge_terms(_moved(xi, d[:, :6]), _moved(xj, d[:, 6:]), measured,
                               information, e, c)
        return jnp.concatenate([-ge, ge], axis=1)

    zero = jnp.zeros((e.i.shape[0], 12), x.t.dtype)
    basis = jnp.broadcast_to(jnp.eye(12, dtype=x.t.dtype)[:, None, :], (12, *zero.shape))
    J = jnp.moveaxis(jax.vmap(lambda t: jax.jvp(gradients, (zero,), (t,))[1])(basis), 0, -1)
    D = jnp.zeros((x.t.shape[0], 6, 6), J.dtype).at[e.i].add(J[:, :6, :6]).at[e.j].add(
        J[:, 6:, 6:])
    return Blocks(D, J[:, :6, 6:], J[:, 6:, :6], e.i, e.j, e.valid, e.movable)


def _settles(old: _System, new: _System) -> jnp.ndarray:
    """A try is kept when it lowers the cost, or keeps it within rounding (64 eps) and
    shrinks the gradient: cost alone cannot resolve the last sqrt(eps) of the optimum."""
    slack = 64 * jnp.finfo(old.cost.dtype).eps * (jnp.abs(old.cost) + 1.0)
    shrinks = (new.cost <= old.cost + slack) & (jnp.sum(new.g * new.g) < jnp.sum(old.g * old.g))
    return (new.cost < old.cost) | shrinks


def _damped_step(s: _System, lam: jnp.ndarray, e: _Edges, spec: tuple) -> jnp.ndarray:
    """The LM step (N, 6): (H + lam diag H) delta = -g on movable nodes, 0 elsewhere, by the
    sparse Cholesky (spec[1] "direct") or PCG (spec[1] "cg", spec[2:]: iterations, tolerance)."""
    mov = e.movable[:, None]
    diag = jnp.diagonal(s.D, axis1=-2, axis2=-1)
    damped = s.D + lam * jax.vmap(jnp.diag)(diag)
    b = jnp.where(mov, -s.g, 0.0)
    if spec[1] == "direct":  # H's edge blocks: -M at (i, j) and (j, i)
        return jnp.where(mov, direct(Blocks(damped, -s.M, -s.M, e.i, e.j, e.valid, e.movable),
                                     b, symmetric=True), 0.0)

    def op(v):  # H v: one gather, 6x6 blocks per edge, one scatter
        v = jnp.where(mov, v, 0.0)
        z = jnp.einsum("eab,eb->ea", s.M, v[e.j] - v[e.i])
        return jnp.where(mov, _scatter(e, v.shape[0], z, -z) + lam * diag * v, v)

    delta = pcg(op, b, block_jacobi(damped, e.movable), spec[3], spec[2])
    return jnp.where(mov, delta, 0.0)


def _moved(x: Pose, d: jnp.ndarray) -> Pose:
    """exp(d) x to first order in the left twists d (N, 6): (I + [w]x) R, (I + [w]x) t + v.
    Its derivative at d = 0 is ``Pose.retract``'s, without differentiating ``Pose.exp``."""
    w = d[:, 3:]
    R = x.R + jnp.cross(w[:, :, None], x.R, axis=1)
    return Pose(R, x.t + jnp.cross(w, x.t) + d[:, :3])


@partial(jax.custom_vjp, nondiff_argnums=(0,))
def _implicit(spec: tuple, R, t, measured, information, e: _Edges, D):
    """The optimum (R, t) unchanged; its VJP is the implicit function theorem (module doc).
    spec: (robust_scale, linear_solver, cg_iterations, cg_tol), static; D: the Gauss-Newton
    diagonal blocks at the optimum (the Tikhonov term's scale, PCG's preconditioner)."""
    del spec, measured, information, e, D
    return R, t


def _implicit_fwd(spec, R, t, measured, information, e, D):
    return (R, t), (R, t, measured, information, e, D)


def _implicit_bwd(spec, res, ct):
    (c, solver, cg_iterations, cg_tol), (R, t, measured, information, e, D) = spec, res
    x, mov = Pose(R, t), e.movable[:, None]
    zero = jnp.zeros(t.shape[:1] + (6,), t.dtype)
    _, pull = jax.vjp(lambda d: _moved(x, d), zero)
    (ct_xi,) = pull(Pose(*ct))

    def stationarity(d, measured, information):
        """The cost's left gradient (N, 6) at exp(d) x, d on the movable nodes."""
        return _system(_moved(x, jnp.where(mov, d, 0.0)), measured, information, e, c).g

    # one linearisation for both: its transpose in d is the Hessian (symmetric at the optimum)
    _, transpose = jax.vjp(stationarity, zero, measured, information)
    tikhonov = jnp.finfo(t.dtype).eps * jnp.max(jnp.abs(jnp.diagonal(D, axis1=-2, axis2=-1)))
    b = jnp.where(mov, ct_xi, 0.0)
    if solver == "direct":  # the same Hessian, formed: its blocks by forward mode
        H = _hessian(x, measured, information, e, c)
        H = H._replace(D=H.D + tikhonov * jnp.eye(6, dtype=t.dtype)).transpose()
        adjoint = direct(H, b)
    else:
        def op(v):
            v = jnp.where(mov, v, 0.0)
            return jnp.where(mov, transpose(v)[0] + tikhonov * v, v)

        adjoint = pcg(op, b, block_jacobi(D, e.movable), cg_tol, cg_iterations)
    _, ct_m, ct_o = transpose(-jnp.where(mov, adjoint, 0.0))
    return jnp.zeros_like(R), jnp.zeros_like(t), ct_m, ct_o, None, None


_implicit.defvjp(_implicit_fwd, _implicit_bwd)


@partial(jax.jit, static_argnames=("robust_scale", "iterations", "step_tol", "cost_tol",
                                   "linear_solver", "cg_iterations", "cg_tol"))
def optimise(
    graph: PoseGraph,
    *,
    robust_scale: float = ROBUST_SCALE,
    iterations: int = 30,
    step_tol: float = 1e-5,
    cost_tol: float = 1e-6,
    linear_solver: str = "direct",
    cg_iterations: int = 1000,
    cg_tol: float = 1e-3,
) -> Solution:
    """The poses minimising the graph's robust cost (module doc), from ``graph.poses``.

    robust_scale: the Cauchy scale c on robust edges (default sqrt(16.81): chi-square's 99 %
    quantile with 6 degrees of freedom, so a loop edge as far off as the worst 1 % of inliers
    keeps half its weight); iterations: the LM tries at most; step_tol: stop once a try's
    largest twist component (m or rad) is below it, or below 64 eps max|t| of the start's
    positions (what the dtype resolves there), or once a kept try lowers the cost by less
    than ``cost_tol`` of it (relative; 0: no such test), or after 6 rejected tries in a row;
    linear_solver: how each linear system (the LM step, the derivative's adjoint) is solved:
    "direct", a sparse factorisation on the host (``block_sparse.direct``: exact, graphs of
    a vmapped batch one after another), or "cg", preconditioned conjugate gradients on the device
    (``block_sparse.pcg``: no host round trip; its iterations grow with the graph);
    cg_iterations, cg_tol: the conjugate gradients' budget and relative residual ("cg" only).
    Jitted, vmap-able over graphs of one shape; reverse-differentiable in ``measured`` and
    ``information`` (implicit, module doc), with a zero derivative in ``poses``."""
    if linear_solver not in ("direct", "cg"):
        raise ValueError(f"linear_solver must be 'direct' or 'cg', not {linear_solver!r}")
    start = jax.lax.stop_gradient(graph.poses)
    measured = jax.lax.stop_gradient(graph.measured)
    information = jax.lax.stop_gradient(graph.information)
    e = _edges(graph)
    c = robust_scale
    spec = (float(c), linear_solver, cg_iterations, cg_tol)

    def evaluate(x, _old=None):
        return _system(x, measured, information, e, c)

    def body(carry):
        k, state, _ = carry
        before = state.system.cost
        state, _ = POSE_GRAPH_DAMPING.step(
            state, solve=lambda x, s, lam: _damped_step(s, lam, e, spec),
            apply=jax.vmap(Pose.retract), evaluate=evaluate, accept=_settles,
            norm=lambda delta: jnp.max(jnp.abs(delta)))  # size-independent
        flat = (state.rejects == 0) & (before - state.system.cost < cost_tol * before)
        return k + 1, state, flat & (cost_tol > 0)

    def cond(carry):
        k, state, flat = carry
        return (k == 0) | ((k <= iterations) & ((k == 1) | (
            ~flat & POSE_GRAPH_DAMPING.continues(state, tol, _MAX_REJECTS))))

    # pass 0 evaluates the start (a zero step, kept against an infinite cost, lam back to
    # lam_init): the system is traced once, which halves the compile time
    x0 = jax.vmap(Pose.from_matrix)(start)
    # a step the poses' own rounding drowns ends the solve too (float32 at 50 m: 0.4 mm)
    tol = jnp.maximum(step_tol, _RESOLVED * jnp.finfo(start.dtype).eps * jnp.max(jnp.abs(x0.t)))
    blank = jax.tree.map(jnp.zeros_like, jax.eval_shape(evaluate, x0))
    blank = blank._replace(cost=jnp.asarray(jnp.inf, start.dtype),
                           D=jnp.broadcast_to(jnp.eye(6, dtype=start.dtype), blank.D.shape))
    lam = POSE_GRAPH_DAMPING.lam_init / POSE_GRAPH_DAMPING.shrink
    state = POSE_GRAPH_DAMPING.init(x0, blank, start.dtype, lam)
    passes, state, _ = jax.lax.while_loop(
        cond, body, (jnp.asarray(0, jnp.int32), state, jnp.asarray(False)))
    x = Pose(*_implicit(spec, *state.x, graph.measured, graph.information, e, state.system.D))
    poses = jnp.where(e.movable[:, None, None], x.as_matrix(), start)
    chi2, rho, weight = _robust(_residual(x, graph.measured, e), graph.information, e, c)
    return Solution(poses, chi2, weight, 0.5 * jnp.sum(rho), passes - 1)
