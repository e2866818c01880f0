"""The camera as the unknown: the tracker's level-0 cost over many (keyframe, frame) pairs as
a function of the camera's parameters, and its joint Gauss-Newton solve over the pairs'
poses and the camera, the poses eliminated by the Schur complement.

Parameters (``PARAMS``, in that order): fx, fy, cx, cy (pixels), ``readout_s`` (the colour
camera's rolling-shutter readout), ``depth_time_offset_s`` (t_depth_true = t_depth_file +
offset), ``depth_scale`` (true depth = scale * depth read) and the depth camera's pose in the
colour camera (``T_color_depth``: a rotation vector and a translation; the depth image is
what a camera of the colour camera's pinhole sees from there). The solve works in
``STEP_UNITS`` (px, ms, %, mrad, mm): one unit of each is a comparable change of the cost.

The model of a pair, keyframe k and frame f (each with the velocity of its camera, a body
twist per second from the tracked poses, and ``lag``, its depth image's file time minus its
colour image's time):
- a keyframe edge at pixel p with depth z read: the depth camera saw it from its pose
  T_color_depth at time lag_k + offset after the colour image's middle row; moved from
  that camera (first order) it keeps the colour ray through p and takes the depth it has
  there (a smooth surface: the depth camera's pixel for p is near p);
  then the rolling shutter's unroll (``shutter.unroll_edges``) moves it to the middle row;
- the frame sees it through its rolling shutter (``shutter.shutter_warp``, the frame's own
  velocity times readout / H per row), and the residual is the distance field there, gated,
  checked for gradient consistency and Huber-weighted as by the tracker at level 0;
- a keyframe depth point (pixel and depth read) goes to the colour keyframe by
  T_color_depth and its lag, to the frame by the pair's pose, to the frame's depth camera
  by the frame's lag and T_color_depth^-1, and meets
  the frame's depth image as the tracker's point-to-plane residual (``depth.point_to_plane``).
With readout, offset and lags 0, scale 1 and T_color_depth the identity this is the
tracker's level-0 cost.

The solve (``solve_camera``): Levenberg-Marquardt (``solvers.LevenbergMarquardt``) on the
joint normal equations of all pairs' poses (left twists, 6 each) and the free camera
parameters, each pair's 6x6 pose block eliminated (``schur.eliminate_blocks``); Jacobians by
forward-mode autodiff through the model. The tracker's hard decisions (gate, consistency,
visibility) are taken again at every point, as the tracker does; a try is kept when it
lowers the summed robust cost.
"""

from __future__ import annotations

from collections.abc import Callable
from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..camera import Intrinsics, unproject
from ..derive import SolveKnobs
from ..frontend.depth import depth_valid
from ..frontend.residuals import consistency_dots_known
from ..frontend.robust import huber_cost, huber_weights
from ..frontend.shutter import RowMotion, shutter_warp
from ..geometry import Pose
from ..image.interp import bilinear_with_grad
from ..solvers import LevenbergMarquardt
from ..window.schur import eliminate_blocks

#: The camera parameters the solve can free, in the order of its vectors; the last six are
#: the depth camera's pose in the colour camera, T_color_depth = (R(depth_rot), depth_t): a
#: rotation vector (rad) and a translation (m).
PARAMS = ("fx", "fy", "cx", "cy", "readout_s", "depth_time_offset_s", "depth_scale",
          "depth_rot_x", "depth_rot_y", "depth_rot_z", "depth_t_x", "depth_t_y", "depth_t_z")
#: One solve unit of each parameter: 1 px (pinhole), 1 ms, 1 ms, 1 % (of scale 1), 1 mrad,
#: 1 mm.
STEP_UNITS = np.array([1.0, 1.0, 1.0, 1.0, 1e-3, 1e-3, 1e-2, 1e-3, 1e-3, 1e-3, 1e-3, 1e-3,
                       1e-3])
#: The solve's damping policy (the tracker's numbers, a wider range).
CAMERA_DAMPING = LevenbergMarquardt(lam_init=1e-3, lam_min=1e-8, lam_max=1e6)


class PairData(NamedTuple):
    """One (keyframe, frame) pair for the camera's cost (numpy or JAX arrays; stacked on a
    leading axis for many pairs). Keyframe: ``uv`` (2, K) edge pixels (level 0, as
    selected, not unrolled), ``z`` (K,) their depth read (m), ``grad`` (2, K) normalised
    gradients, ``valid`` (K,); ``dpix`` (2, M) and ``dz`` (M,) its depth points' pixels and
    depth read, ``normals`` (3, M) their normals (zero: padding); ``vel_k`` (6,) its
    velocity [v, w] per second (body twist), ``lag_k`` () its depth image's time minus its
    colour image's (s). Frame: ``field`` (H, W) level-0 distance field, ``code`` (H, W)
    direction codes, ``depth`` (H, W) depth read (m, 0 missing), ``vel_f`` (6,), ``lag_f``
    ()."""

    uv: jnp.ndarray
    z: jnp.ndarray
    grad: jnp.ndarray
    valid: jnp.ndarray
    dpix: jnp.ndarray
    dz: jnp.ndarray
    normals: jnp.ndarray
    vel_k: jnp.ndarray
    lag_k: jnp.ndarray
    field: jnp.ndarray
    code: jnp.ndarray
    depth: jnp.ndarray
    vel_f: jnp.ndarray
    lag_f: jnp.ndarray


class PairSystem(NamedTuple):
    """One pair's normal equations over [pose twist (6), camera step (P)] at a point: H
    (6 + P, 6 + P) = J^T W J, g (6 + P,) = J^T W r, the robust cost (), the edge inliers
    ()."""

    H: jnp.ndarray
    g: jnp.ndarray
    cost: jnp.ndarray
    inliers: jnp.ndarray


def _move(pts: jnp.ndarray, vel: jnp.ndarray, dt: jnp.ndarray) -> jnp.ndarray:
    """Points (3, K) that a camera moving with ``vel`` [v, w] (per unit of ``dt``) sees at
    time t + dt, as it sees them at time t: P + dt (w x P + v), first order (the
    ``shutter`` module's convention)."""
    v, w = vel[:3], vel[3:]
    return pts + dt * (jnp.cross(w[:, None], pts, axis=0) + v[:, None])


def _unproject(intr: Intrinsics, uv: jnp.ndarray, z: jnp.ndarray) -> jnp.ndarray:
    """``camera.unproject`` by depth z (K,), which may be 0 (a missing depth)."""
    return unproject(intr, uv, jnp.ones_like(z)) * z


def pair_residuals(xi: jnp.ndarray, theta: jnp.ndarray, T0: Pose, pair: PairData,
                   height: int, focal: jnp.ndarray
                   ) -> tuple[tuple[jnp.ndarray, jnp.ndarray], tuple]:
    """The pair's residuals at pose exp(xi) T0 (T_frame_keyframe) and camera ``theta``
    (``PARAMS`` values): ((edge residuals (K,), depth residuals (M,)), (edge pixels in the
    frame (2, K), edge validity (K,), the field's gradient there (2, K), depth validity
    (M,))). The model: the module doc. ``focal``: the focal length (px) that turns depth
    residuals into pixels, a constant (the start's sqrt(fx fy)): scaled by the camera being
    solved, a smaller focal length would shrink every depth residual."""
    fx, fy, cx, cy, readout, offset, scale = (theta[i] for i in range(7))
    intr = Intrinsics(fx, fy, cx, cy)
    R_cd = Pose.exp(jnp.concatenate([jnp.zeros(3, theta.dtype), theta[7:10]])).R
    t_cd = theta[10:13]
    T = T0.retract(xi)
    mid = 0.5 * (height - 1)
    # keyframe edges: depth read by the depth camera (its pose, its time), on the colour ray,
    # then unrolled
    ray = _unproject(intr, pair.uv, jnp.ones_like(pair.z))
    z = jnp.where(pair.valid, scale * pair.z, 1.0)
    z_ray = _move(R_cd @ (ray * z) + t_cd[:, None], pair.vel_k, pair.lag_k + offset)[2]
    P = ray * jnp.where(z_ray > 1e-6, z_ray, z)
    P = _move(P, pair.vel_k * readout / height, pair.uv[1] - mid)
    rows = RowMotion(twist=pair.vel_f * readout / height, ref=jnp.asarray(mid, P.dtype),
                     rate=jnp.zeros((), P.dtype))
    uv_f, pts_f, _ = shutter_warp(intr, T, P, rows)
    r, grad, inside = bilinear_with_grad(pair.field, uv_f)
    ok = inside & (pts_f[2] > 1e-6) & pair.valid
    # depth points: keyframe depth camera -> colour keyframe -> frame -> frame depth camera
    D = _unproject(intr, pair.dpix, scale * pair.dz)
    D = _move(R_cd @ D + t_cd[:, None], pair.vel_k, pair.lag_k + offset)
    n = pair.normals
    q = _move(T.apply(D), pair.vel_f, -(pair.lag_f + offset))
    q = R_cd.T @ (q - t_cd[:, None])  # in the frame's depth camera
    nq = R_cd.T @ (T.R @ (R_cd @ n))
    zq = jnp.where(q[2] > 1e-6, q[2], 1.0)
    u, v = fx * q[0] / zq + cx, fy * q[1] / zq + cy
    h, w = pair.depth.shape
    inside_d = (q[2] > 1e-6) & (u >= 0) & (u <= w - 1) & (v >= 0) & (v <= h - 1)
    ui = jax.lax.stop_gradient(jnp.clip(jnp.round(u), 0, w - 1)).astype(jnp.int32)
    vi = jax.lax.stop_gradient(jnp.clip(jnp.round(v), 0, h - 1)).astype(jnp.int32)
    d = pair.depth[vi, ui]
    p_c = _unproject(intr, jnp.stack([ui, vi]).astype(q.dtype), scale * d)
    r_d = focal / zq * jnp.sum(nq * (q - p_c), axis=0)
    ok_d = inside_d & (d > 0) & depth_valid(n)
    return (r, jnp.where(ok_d, r_d, 0.0)), (uv_f, ok, grad, ok_d)


def pair_system(xi: jnp.ndarray, phi: jnp.ndarray, theta0: jnp.ndarray, free: jnp.ndarray,
                T0: Pose, pair: PairData, knobs: SolveKnobs, height: int) -> PairSystem:
    """The pair's Huber-weighted normal equations over [xi (6), phi (P)] at xi, with camera
    theta0 + free * STEP_UNITS * phi (``free`` (P,) 0/1 masks the fixed parameters: their
    columns are zero), gated as the tracker's level 0 (``align.normal_equations``): edges
    beyond the gate or inconsistent in gradient, and depth residuals beyond the gate, cost
    the gate's Huber cost."""
    units = jnp.asarray(STEP_UNITS, phi.dtype) * free

    def residuals(x):
        return pair_residuals(x[:6], theta0 + units * x[6:], T0, pair, height,
                              jnp.sqrt(theta0[0] * theta0[1]))

    x = jnp.concatenate([xi, phi])
    (r, r_d), (uv_f, ok, grad, ok_d) = residuals(x)
    (J, J_d), _ = jax.jacfwd(residuals, has_aux=True)(x)
    delta, gate = knobs.huber_delta[0], knobs.max_residual[0]
    consistent = consistency_dots_known(pair.grad, pair.code, uv_f, r, grad) >= knobs.eta
    mask = ok & (r <= gate) & consistent
    mask_d = ok_d & (jnp.abs(r_d) <= gate)
    gate_cost = huber_cost(gate, delta)
    w = jnp.where(mask, huber_weights(r, delta), 0.0)
    w_d = jnp.where(mask_d, huber_weights(r_d, delta), 0.0)
    H = (J.T * w) @ J + (J_d.T * w_d) @ J_d
    g = J.T @ (w * r) + J_d.T @ (w_d * r_d)
    cost = (jnp.sum(jnp.where(mask, huber_cost(r, delta), jnp.where(pair.valid, gate_cost, 0.)))
            + jnp.sum(jnp.where(mask_d, huber_cost(r_d, delta),
                                jnp.where(depth_valid(pair.normals), gate_cost, 0.0))))
    return PairSystem(H, g, cost, jnp.sum(mask).astype(r.dtype))


class CameraSolve(NamedTuple):
    """The point of the joint solve: ``xi`` (N, 6) each pair's left twist from its start
    pose, ``phi`` (P,) the camera step in ``STEP_UNITS`` from the start camera."""

    xi: jnp.ndarray
    phi: jnp.ndarray


class JointSystem(NamedTuple):
    """All pairs' systems at a point and their sum's cost (``cost``, what a try must
    lower)."""

    pairs: PairSystem
    cost: jnp.ndarray


def joint_system(x: CameraSolve, theta0, free, T0: Pose, pairs: PairData, knobs: SolveKnobs,
                 height: int) -> JointSystem:
    """Every pair's ``pair_system`` at x (vmapped over the pairs)."""
    systems = jax.vmap(pair_system, in_axes=(0, None, None, None, 0, 0, None, None))(
        x.xi, x.phi, theta0, free, T0, pairs, knobs, height)
    return JointSystem(systems, jnp.sum(systems.cost))


def reduced_camera_system(systems: PairSystem, lam: jnp.ndarray | float = 0.0):
    """The camera's system once every pair's pose is eliminated (``eliminate_blocks``), with
    the LM damping lam diag(H) on both blocks: (S (P, P), r (P,), the elimination for
    back-substitution, and the per-pair reduced gradients (N, P))."""
    H, g = systems.H, systems.g
    A = H + lam * jnp.eye(H.shape[-1], dtype=H.dtype) * H
    return eliminate_blocks(A[:, 6:, 6:], A[:, 6:, :6], A[:, :6, :6], g[:, 6:], g[:, :6])


def _camera_step(system: JointSystem, lam: jnp.ndarray, free: jnp.ndarray) -> CameraSolve:
    """The damped joint step: the camera's from the reduced system (fixed parameters held),
    each pair's pose by back-substitution."""
    e = reduced_camera_system(system.pairs, lam)
    eye = jnp.eye(e.S.shape[0], dtype=e.S.dtype)
    S = e.S + 1e-9 * (jnp.trace(e.S) + 1.0) * eye
    S = jnp.where(free[:, None] * free[None, :] > 0, S, eye)
    d_phi = -jnp.linalg.solve(S, e.r * free)
    return CameraSolve(e.back(d_phi), d_phi)


def _step_norm(d: CameraSolve) -> jnp.ndarray:
    return jnp.sqrt(jnp.sum(d.phi ** 2) + jnp.max(jnp.sum(d.xi ** 2, axis=1)))


@partial(jax.jit, static_argnums=(6,))
def _lm_try(state, theta0, free, T0: Pose, pairs: PairData, knobs: SolveKnobs, height: int):
    """One Levenberg-Marquardt try of the joint solve (one program)."""
    new, _ = CAMERA_DAMPING.step(
        state, solve=lambda x, system, lam: _camera_step(system, lam, free),
        apply=lambda x, d: CameraSolve(x.xi + d.xi, x.phi + d.phi),
        evaluate=lambda x, system: joint_system(x, theta0, free, T0, pairs, knobs, height),
        norm=_step_norm)
    return new


_joint_system = jax.jit(joint_system, static_argnums=(6,))


def pad_pairs(pairs: PairData, T0: np.ndarray, multiple: int = 32
              ) -> tuple[PairData, np.ndarray, int]:
    """The pairs (stacked, numpy) and their start poses (N, 4, 4) padded to a multiple of
    ``multiple`` with copies of the first pair whose edges and depth points are all invalid
    (they add nothing to any sum), so that a calibration compiles its solve once for a
    range of pair counts. Returns them and N."""
    n = pairs.valid.shape[0]
    extra = -n % multiple
    if extra == 0:
        return pairs, T0, n

    def pad(name, a):
        filler = np.repeat(a[:1], extra, axis=0)
        if name == "valid":
            filler = np.zeros_like(filler)
        elif name == "normals":
            filler = np.zeros_like(filler)
        return np.concatenate([a, filler])

    padded = PairData(**{name: pad(name, np.asarray(getattr(pairs, name)))
                         for name in PairData._fields})
    return padded, np.concatenate([T0, np.repeat(T0[:1], extra, axis=0)]), n


def solve_camera(theta0: np.ndarray, free: np.ndarray, T0: Pose, pairs: PairData,
                 knobs: SolveKnobs, height: int, *, iterations: int = 20,
                 step_tol: float = 1e-3, on_try: Callable[[int, float], None] | None = None,
                 ) -> tuple[CameraSolve, JointSystem, int, float]:
    """Levenberg-Marquardt over every pair's pose and the free camera parameters from the
    start camera theta0 (``PARAMS`` values) and the pairs' poses T0 (N poses): at most
    ``iterations`` tries, stopped when a step is under ``step_tol`` (in the solve's units,
    the pose twists included) or after 5 rejections in a row; ``on_try(try, cost)`` is
    called after each. Returns the point, its systems, the number of tries and the summed
    robust cost at the start. Programs are compiled once per pair count (``pad_pairs``)."""
    dtype = jnp.float32
    theta0 = jnp.asarray(theta0, dtype)
    free = jnp.asarray(free, dtype)
    n = pairs.valid.shape[0]
    x0 = CameraSolve(jnp.zeros((n, 6), dtype), jnp.zeros(len(PARAMS), dtype))
    state = CAMERA_DAMPING.init(x0, _joint_system(x0, theta0, free, T0, pairs, knobs, height),
                                dtype)
    start_cost = float(state.system.cost)
    tries = 0
    for tries in range(1, iterations + 1):  # noqa: B007 (returned)
        state = _lm_try(state, theta0, free, T0, pairs, knobs, height)
        if on_try is not None:
            on_try(tries, float(state.system.cost))
        if not bool(CAMERA_DAMPING.continues(state, step_tol, 5)):
            break
    return state.x, state.system, tries, start_cost


def camera_of(theta0: np.ndarray, free: np.ndarray, phi: np.ndarray) -> np.ndarray:
    """The camera (``PARAMS`` values, float64) at step phi from theta0."""
    return np.asarray(theta0, np.float64) + np.asarray(free, np.float64) * STEP_UNITS \
        * np.asarray(phi, np.float64)


def sandwich_covariance(systems: PairSystem, clusters: np.ndarray, free: np.ndarray
                        ) -> np.ndarray:
    """The covariance (P, P) of the free camera parameters (``PARAMS`` units; fixed ones 0)
    at a solution, robust to noise correlated within a cluster of pairs (pairs sharing a
    keyframe share its edges): S^-1 (sum_c b_c b_c^T) S^-1 * C / (C - 1), with S the
    reduced camera information and b_c the reduced gradients summed over cluster c (C
    clusters; pairs labelled below 0 are padding, in none). Infinite variances where S is
    singular along a parameter."""
    e = reduced_camera_system(systems)
    S = np.asarray(e.S, np.float64)
    per_pair = np.asarray(e.per_pair, np.float64)
    f = np.flatnonzero(np.asarray(free) > 0)
    cov = np.zeros((len(PARAMS), len(PARAMS)))
    if f.size == 0:
        return cov
    labels = np.unique(clusters[clusters >= 0])  # negative: padding (``pad_pairs``)
    B = np.zeros((f.size, f.size))
    for c in labels:
        b = per_pair[clusters == c][:, f].sum(axis=0)
        B += np.outer(b, b)
    B *= len(labels) / max(len(labels) - 1, 1)
    Sf = S[np.ix_(f, f)]
    w, V = np.linalg.eigh(0.5 * (Sf + Sf.T))
    if w.min() <= 1e-9 * max(w.max(), 1e-300):
        out = np.full((f.size, f.size), np.inf)
    else:
        Sinv = (V / w) @ V.T
        out = Sinv @ B @ Sinv
    cov[np.ix_(f, f)] = out
    units = STEP_UNITS
    return cov * np.outer(units, units)
