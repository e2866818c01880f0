"""SE(3): ``Pose``, the one device pose type, and its numpy float64 twin for host code.

Conventions (docs/architecture.md): ``T_a_b`` maps points from frame b to frame a (p_a = T_a_b p_b);
twists are xi = [v, w] (6,), translation first, exp(xi) = [[exp([w]x), V v], [0, 1]];
updates are left-multiplicative, T <- exp(xi) T.

Device (``Pose``, a pytree of R (3, 3) and t (3,), float32 by default): ``exp``, ``log``,
``compose`` (``@``), ``inverse``, ``apply`` (to points (3, K)), ``retract`` (exp(xi) @ T),
``from_matrix`` / ``as_matrix``; ``predict`` is the constant-velocity prediction. Batch
with ``jax.vmap``; ``from_matrix(..., orthonormalise=None)``, ``as_matrix``, ``inverse``
and ``compose`` also broadcast over leading axes.

Host (numpy float64, rigid transforms as (..., 4, 4) arrays, as the tracker keeps them):
``inverse_np``, ``compose_np``, ``exp_np``, ``log_np``, ``predict_np``,
``orthonormalise_np``, ``scale_motion_np``, ``rotation_angle_np``: the same maps as the
device type's, so host code never re-derives them.

Two multiplication styles, on purpose: ``retract`` and ``apply`` (the solve's inner loop)
write their 3x3 products out as products and sums in a fixed order (``_matmul3``), which
XLA's CPU backend fuses into neighbouring kernels and rounds alike whatever the batch size;
``compose`` multiplies the homogeneous 4x4 matrices (one dot), as the constant-velocity
prediction always has. The two round differently (~1e-7 in float32), so
``retract(xi)`` equals ``exp(xi) @ T`` to rounding, not bit for bit.

Three operations also go through unit quaternions, jaxlie's arithmetic op for op:
``from_matrix(..., orthonormalise="quaternion")`` (the edge selection's and the window
activation's warps), ``exp(..., method="quaternion")`` (the window's pose update) and
``log_relative`` (the window prior's offsets). The selection's argmax and the window's
accept / reject decisions turn a last-bit difference there into millimetres of trajectory,
so those call sites keep the rounding they were tuned with.
"""

from __future__ import annotations

from typing import Literal, NamedTuple

import jax.numpy as jnp
import numpy as np

from ._quaternion import (
    quat_apply,
    quat_conj,
    quat_from_matrix,
    quat_mul,
    quat_se3_exp,
    quat_se3_log,
    quaternion_projection,
)

Projection = Literal["gram_schmidt", "quaternion"] | None


def _matmul3(A: jnp.ndarray, B: jnp.ndarray) -> jnp.ndarray:
    """A (3, 3) @ B (3, 3) or (3,) written out as products and sums in a fixed order: XLA on
    CPU fuses these into their neighbours (a dot is a kernel of its own) and rounds them the
    same way whatever the batch size of a vmapped caller (``align.sum_rows`` says why)."""
    if B.ndim == 1:
        return jnp.stack([A[i, 0] * B[0] + A[i, 1] * B[1] + A[i, 2] * B[2] for i in range(3)])
    return jnp.stack([jnp.stack([A[i, 0] * B[0, j] + A[i, 1] * B[1, j] + A[i, 2] * B[2, j]
                                 for j in range(3)]) for i in range(3)])


def _dot3(a: jnp.ndarray, b: jnp.ndarray) -> jnp.ndarray:
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _hat(w: jnp.ndarray) -> jnp.ndarray:
    """[w]x (3, 3) of w (3,): [w]x p = w x p."""
    zero = jnp.zeros_like(w[0])
    return jnp.stack([jnp.stack([zero, -w[2], w[1]]), jnp.stack([w[2], zero, -w[0]]),
                      jnp.stack([-w[1], w[0], zero])])


def _exp_so3_v(w: jnp.ndarray) -> tuple[jnp.ndarray, jnp.ndarray, jnp.ndarray]:
    """R = exp([w]x) (3, 3), V (3, 3) with exp([v, w]) = [[R, V v], [0, 1]], and W = [w]x:
    Rodrigues' formula R = I + A W + B W^2, V = I + B W + C W^2 with theta = |w|,
    A = sin(theta) / theta, B = (1 - cos theta) / theta^2, C = (theta - sin theta) / theta^3.
    B is computed as sinc(theta / 2)^2 / 2 and C by its series below theta = 0.1 (both
    cancel catastrophically in float32 otherwise)."""
    th2 = _dot3(w, w)
    tiny = th2 < 1e-8
    th = jnp.sqrt(jnp.where(tiny, 1.0, th2))
    half = 0.5 * th
    A = jnp.where(tiny, 1.0 - th2 / 6.0, jnp.sin(th) / th)
    s_half = jnp.where(tiny, 1.0 - th2 / 24.0, jnp.sin(half) / half)
    B = 0.5 * s_half * s_half
    small = th2 < 1e-2
    C = jnp.where(small, 1.0 / 6.0 - th2 / 120.0 + th2 * th2 / 5040.0,
                  (th - jnp.sin(th)) / (th * jnp.where(small, 1.0, th2)))
    W = _hat(w)
    W2 = _matmul3(W, W)
    eye = jnp.eye(3, dtype=w.dtype)
    return eye + A * W + B * W2, eye + B * W + C * W2, W


def _log_so3(R: jnp.ndarray) -> jnp.ndarray:
    """w (3,) with exp([w]x) = R (3, 3), |w| in [0, pi].

    theta = atan2(|s|, cos) with s = vee(R - R^T) / 2 = sin(theta) axis and
    cos = (trace R - 1) / 2 (accurate at every angle). Where cos >= 0 the axis comes from s:
    w = s theta / sin(theta), with theta / sin(theta) by its series near 0. Where cos < 0
    (theta > pi / 2, s small near pi) it comes from the symmetric part,
    (R + R^T) / 2 - cos I = (1 - cos) a a^T: the column of largest diagonal, normalised,
    its sign that of s. Gradients are finite at the identity."""
    s = 0.5 * jnp.stack([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    cos = 0.5 * (R[0, 0] + R[1, 1] + R[2, 2] - 1.0)
    sin2 = _dot3(s, s)
    tiny = sin2 < 1e-12
    sin = jnp.sqrt(jnp.where(tiny, 1.0, sin2))
    th = jnp.arctan2(jnp.where(tiny, 0.0, sin), cos)
    # theta / sin(theta): series 1 + t^2/6 + 7 t^4/360 where sin ~ theta is small
    small = sin2 < 1e-6
    ratio = jnp.where(small, 1.0 + sin2 / 6.0 + 7.0 * sin2 * sin2 / 360.0,
                      th / jnp.where(small, 1.0, sin))
    w_near0 = ratio * s
    far = cos < 0.0
    eye = jnp.eye(3, dtype=R.dtype)
    M = jnp.where(far, 0.5 * (R + R.T) - cos * eye, eye)  # eye: finite gradients off far
    j = jnp.argmax(jnp.diagonal(M))
    col = M[:, j]
    norm = jnp.sqrt(jnp.maximum(_dot3(col, col), jnp.finfo(R.dtype).tiny))
    sign = jnp.where(_dot3(col, s) < 0.0, -1.0, 1.0)
    th_far = jnp.arctan2(jnp.sqrt(jnp.where(far, sin2, 1.0)), cos)
    w_far = (sign * th_far / norm) * col
    return jnp.where(far, w_far, w_near0)


class Pose(NamedTuple):
    """A rigid transform T_a_b as its rotation matrix R (3, 3) and translation t (3,): a
    pytree, p_a = R p_b + t.

    A rotation matrix rather than a quaternion: ``retract`` and ``apply`` are then a few
    fused elementwise kernels on XLA's CPU backend (a quaternion group element costs dozens
    of small ones per Levenberg-Marquardt try of the solve). Methods act on one pose (batch
    them with ``jax.vmap``); ``from_matrix(..., orthonormalise=None)``, ``as_matrix``,
    ``inverse`` and ``compose`` also broadcast over leading axes."""

    R: jnp.ndarray
    t: jnp.ndarray

    @staticmethod
    def identity(dtype: jnp.dtype = jnp.float32) -> Pose:
        """The identity transform."""
        return Pose(jnp.eye(3, dtype=dtype), jnp.zeros(3, dtype))

    @staticmethod
    def exp(xi: jnp.ndarray, *, method: Literal["rodrigues", "quaternion"] = "rodrigues"
            ) -> Pose:
        """exp of a twist xi = [v, w] (6,): R = exp([w]x), t = V v. ``"rodrigues"``:
        Rodrigues' formula (``_exp_so3_v`` states the series used in float32), the solve's
        update. ``"quaternion"``: through the unit quaternion of w (jaxlie's arithmetic,
        ``quat_se3_exp``; xi may carry leading axes (..., 6)), the window's pose update,
        whose trajectories depend on its rounding."""
        if method == "quaternion":
            return Pose(*quat_se3_exp(xi))
        if method != "rodrigues":
            raise ValueError(f"method must be 'rodrigues' or 'quaternion', got {method!r}")
        R, V, _ = _exp_so3_v(xi[3:])
        return Pose(R, _matmul3(V, xi[:3]))

    def log(self) -> jnp.ndarray:
        """The twist xi = [v, w] (6,) with exp(xi) = self, |w| in [0, pi]: w = log(R)
        (``_log_so3``: accurate near the identity and near pi), v = V^-1 t with
        V^-1 = I - W / 2 + D W^2, W = [w]x, D = (1 - (theta / 2) cot(theta / 2)) / theta^2
        (series 1/12 + theta^2/720 + theta^4/30240 below theta = 0.1, where it cancels)."""
        w = _log_so3(self.R)
        th2 = _dot3(w, w)
        small = th2 < 1e-2
        half = 0.5 * jnp.sqrt(jnp.where(small, 1.0, th2))
        D = jnp.where(small, 1.0 / 12.0 + th2 / 720.0 + th2 * th2 / 30240.0,
                      (1.0 - half * jnp.cos(half) / jnp.sin(half)) / jnp.where(small, 1.0, th2))
        W = _hat(w)
        V_inv = jnp.eye(3, dtype=w.dtype) - 0.5 * W + D * _matmul3(W, W)
        return jnp.concatenate([_matmul3(V_inv, self.t), w])

    def log_relative(self, base: Pose) -> jnp.ndarray:
        """log(self @ base^-1) (..., 6), the twist of the left offset from ``base`` to self,
        computed through unit quaternions (both rotation blocks projected as by
        ``from_matrix(..., orthonormalise="quaternion")``; jaxlie's arithmetic op for op,
        ``quat_se3_log``): the window prior's offsets, whose rounding the trajectories
        depend on. Broadcasts over leading axes."""
        q, q0_inv = quat_from_matrix(self.R), quat_conj(quat_from_matrix(base.R))
        t0_inv = -quat_apply(q0_inv, base.t)
        return quat_se3_log(quat_mul(q, q0_inv), quat_apply(q, t0_inv) + self.t)

    @staticmethod
    def from_matrix(T: jnp.ndarray, *, orthonormalise: Projection = "gram_schmidt") -> Pose:
        """From a (4, 4) matrix (its last row is not read), its rotation block projected
        back onto SO(3) (float32 products drift from orthonormality by ~1e-7 each):
        ``"gram_schmidt"`` on its rows (the solve's start), ``"quaternion"`` through its
        unit quaternion (``quaternion_projection``: the edge selection's and the window
        activation's warp), or None: the block as it is. T may carry leading axes
        (..., 4, 4) except with ``"gram_schmidt"``. The two projections round differently,
        and the selection's choices (an argmax) and so the trajectories depend on those
        bits."""
        if orthonormalise is None:
            return Pose(T[..., :3, :3], T[..., :3, 3])
        if orthonormalise == "quaternion":
            return Pose(quaternion_projection(T[..., :3, :3]), T[..., :3, 3])
        if orthonormalise != "gram_schmidt":
            raise ValueError(f"orthonormalise must be 'gram_schmidt', 'quaternion' or None, "
                             f"got {orthonormalise!r}")
        r0 = T[0, :3]
        r0 = r0 / jnp.sqrt(_dot3(r0, r0))
        r1 = T[1, :3] - _dot3(T[1, :3], r0) * r0
        r1 = r1 / jnp.sqrt(_dot3(r1, r1))
        r2 = jnp.stack([r0[1] * r1[2] - r0[2] * r1[1], r0[2] * r1[0] - r0[0] * r1[2],
                        r0[0] * r1[1] - r0[1] * r1[0]])
        return Pose(jnp.stack([r0, r1, r2]), T[:3, 3])

    def as_matrix(self) -> jnp.ndarray:
        """The homogeneous (..., 4, 4) matrix."""
        top = jnp.concatenate([self.R, self.t[..., None]], axis=-1)
        bottom = jnp.broadcast_to(jnp.asarray([0.0, 0.0, 0.0, 1.0], self.R.dtype),
                                  (*top.shape[:-2], 1, 4))
        return jnp.concatenate([top, bottom], axis=-2)

    def compose(self, other: Pose) -> Pose:
        """self @ other: T_a_c = T_a_b @ T_b_c, as the product of the homogeneous 4x4
        matrices (one dot; broadcasts over leading axes)."""
        return Pose.from_matrix(self.as_matrix() @ other.as_matrix(), orthonormalise=None)

    def __matmul__(self, other: Pose) -> Pose:
        """``compose``."""
        return self.compose(other)

    def inverse(self) -> Pose:
        """T_b_a of T_a_b: [R^T, -R^T t] (broadcasts over leading axes)."""
        Rt = jnp.swapaxes(self.R, -1, -2)
        return Pose(Rt, -(Rt @ self.t[..., None])[..., 0])

    def apply(self, pts: jnp.ndarray) -> jnp.ndarray:
        """R p + t for points (3, K) (struct of arrays), written out per row."""
        R, t = self.R, self.t
        x, y, z = pts[0], pts[1], pts[2]
        return jnp.stack([R[i, 0] * x + R[i, 1] * y + R[i, 2] * z + t[i] for i in range(3)])

    def retract(self, xi: jnp.ndarray) -> Pose:
        """exp(xi) @ self for a left twist xi = [v, w] (6,), products written out
        (``_matmul3``): the solve's update."""
        dR, dt = Pose.exp(xi)
        return Pose(_matmul3(dR, self.R), _matmul3(dR, self.t) + dt)


def predict(last: Pose, prev: Pose) -> Pose:
    """Constant velocity: last @ prev^-1 @ last, for the last two poses of a camera in one
    frame, either world poses (T_w_(i-1), T_w_(i-2) -> T_w_i) or relative to a fixed frame
    on the other side (T_(i-1)_kf, T_(i-2)_kf -> T_i_kf). ``predict_np`` is its host twin."""
    return last @ (prev.inverse() @ last)


# -- host twin: numpy float64, rigid transforms as (..., 4, 4) arrays ------------------------


def inverse_np(T: np.ndarray) -> np.ndarray:
    """Inverse of rigid transforms (..., 4, 4): [R^T, -R^T t] (float64)."""
    T = np.asarray(T, np.float64)
    Rt = np.swapaxes(T[..., :3, :3], -1, -2)
    out = np.zeros_like(T)
    out[..., :3, :3] = Rt
    if T.ndim == 2:
        out[:3, 3] = -Rt @ T[:3, 3]
    else:
        out[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, T[..., :3, 3])
    out[..., 3, 3] = 1.0
    return out


def compose_np(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """A @ B of rigid transforms (..., 4, 4) (float64)."""
    return np.asarray(A, np.float64) @ np.asarray(B, np.float64)


def predict_np(last: np.ndarray, prev: np.ndarray) -> np.ndarray:
    """Constant velocity on the host: last @ (prev^-1 @ last) for (4, 4) poses (``predict``)."""
    return compose_np(last, compose_np(inverse_np(prev), last))


def _hat_np(w: np.ndarray) -> np.ndarray:
    x, y, z = w[..., 0], w[..., 1], w[..., 2]
    zero = np.zeros_like(x)
    return np.stack([np.stack([zero, -z, y], -1), np.stack([z, zero, -x], -1),
                     np.stack([-y, x, zero], -1)], -2)


def exp_np(xi: np.ndarray) -> np.ndarray:
    """exp of twists xi = [v, w] (..., 6) as (..., 4, 4) matrices (float64; Rodrigues, with
    series where theta = |w| < 1e-3)."""
    xi = np.asarray(xi, np.float64)
    v, w = xi[..., :3], xi[..., 3:]
    th2 = np.sum(w * w, axis=-1)[..., None, None]
    small = th2 < 1e-6
    th2_safe = np.where(small, 1.0, th2)
    th = np.sqrt(th2_safe)
    A = np.where(small, 1.0 - th2 / 6.0, np.sin(th) / th)
    B = np.where(small, 0.5 - th2 / 24.0, (1.0 - np.cos(th)) / th2_safe)
    C = np.where(small, 1.0 / 6.0 - th2 / 120.0, (th - np.sin(th)) / (th * th2_safe))
    W = _hat_np(w)
    W2 = W @ W
    eye = np.eye(3)
    out = np.zeros((*xi.shape[:-1], 4, 4))
    out[..., :3, :3] = eye + A * W + B * W2
    out[..., :3, 3] = ((eye + B * W + C * W2) @ v[..., None])[..., 0]
    out[..., 3, 3] = 1.0
    return out


def log_np(T: np.ndarray) -> np.ndarray:
    """The twists xi = [v, w] (..., 6) of rigid transforms T (..., 4, 4), |w| in [0, pi]
    (float64; ``Pose.log``'s method: accurate near the identity and near pi)."""
    T = np.asarray(T, np.float64)
    R = T[..., :3, :3]
    s = 0.5 * np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0],
                        R[..., 1, 0] - R[..., 0, 1]], -1)
    cos = 0.5 * (np.trace(R, axis1=-2, axis2=-1) - 1.0)
    sin = np.linalg.norm(s, axis=-1)
    th = np.arctan2(sin, cos)
    small = sin < 1e-6
    ratio = np.where(small, 1.0 + sin**2 / 6.0, th / np.where(small, 1.0, sin))
    w_near0 = ratio[..., None] * s
    M = 0.5 * (R + np.swapaxes(R, -1, -2)) - cos[..., None, None] * np.eye(3)
    j = np.argmax(np.diagonal(M, axis1=-2, axis2=-1), axis=-1)
    col = np.take_along_axis(M, j[..., None, None], axis=-1)[..., 0]
    norm = np.maximum(np.linalg.norm(col, axis=-1), np.finfo(np.float64).tiny)
    sign = np.where(np.sum(col * s, axis=-1) < 0.0, -1.0, 1.0)
    w_far = (sign * th / norm)[..., None] * col
    w = np.where((cos >= 0.0)[..., None], w_near0, w_far)
    th2 = np.sum(w * w, axis=-1)[..., None, None]
    small = th2 < 1e-4
    half = 0.5 * np.sqrt(np.where(small, 1.0, th2))
    D = np.where(small, 1.0 / 12.0 + th2 / 720.0,
                 (1.0 - half * np.cos(half) / np.sin(half)) / np.where(small, 1.0, th2))
    W = _hat_np(w)
    V_inv = np.eye(3) - 0.5 * W + D * (W @ W)
    return np.concatenate([(V_inv @ T[..., :3, 3:])[..., 0], w], axis=-1)


def rotation_angle_np(T: np.ndarray) -> np.ndarray | float:
    """Rotation angle (rad, in [0, pi]) of rigid transforms (..., 4, 4), or of rotation
    matrices (..., 3, 3): atan2(|vee(R - R^T)| / 2, (trace R - 1) / 2), accurate near 0 and
    pi (arccos of the trace is not). A float for one transform."""
    R = np.asarray(T, np.float64)[..., :3, :3]
    cos = (np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0
    skew = np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0],
                     R[..., 1, 0] - R[..., 0, 1]], axis=-1)
    angle = np.arctan2(np.linalg.norm(skew, axis=-1) / 2.0, cos)
    return float(angle) if angle.ndim == 0 else angle


def orthonormalise_np(T: np.ndarray) -> np.ndarray:
    """T (4, 4) with its rotation block projected back onto SO(3) (float32 round-off): the
    nearest rotation (polar factor) by Newton's iteration R <- R (3 I - R^T R) / 2, which
    converges quadratically from a nearly orthonormal R (an SVD costs ten times more in
    numpy's per-call overhead; the tracker does this on every frame)."""
    R = np.asarray(T[:3, :3], np.float64)
    eye = np.eye(3)
    for _ in range(3):
        err = R.T @ R - eye
        if np.abs(err).max() < 1e-15:
            break
        R = R @ (1.5 * eye - 0.5 * (R.T @ R))
    if np.abs(R.T @ R - eye).max() > 1e-9 or np.linalg.det(R) < 0:  # far from a rotation
        u, _, vt = np.linalg.svd(T[:3, :3])
        R = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
    out = np.array(T, np.float64, copy=True)
    out[:3, :3] = R
    return out


def scale_motion_np(T: np.ndarray, s: float) -> np.ndarray:
    """exp(s log T) for a 4x4 rigid motion T: s = 0.5 is half the rotation angle and half
    the screw motion (numpy float64 out)."""
    return exp_np(s * log_np(T))
