"""SE(3) helpers: jaxlie, and ``Rigid``, a rotation-matrix pose for the solve's inner loop.
Twists are [v, w] (translation first), as in jaxlie.

``T_a_b`` maps points from frame b to frame a. Host-side 4x4 helpers use numpy float64.
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
import jaxlie
import numpy as np


def _matmul3(A: jnp.ndarray, B: jnp.ndarray) -> jnp.ndarray:
    """A (3, 3) @ B (3, 3) or (3,) written out as products and sums in a fixed order: XLA on
    CPU fuses these into their neighbours (a dot is a kernel of its own) and rounds them the
    same way whatever the batch size of a vmapped caller (``solve.sum_rows`` says why)."""
    if B.ndim == 1:
        return jnp.stack([A[i, 0] * B[0] + A[i, 1] * B[1] + A[i, 2] * B[2] for i in range(3)])
    return jnp.stack([jnp.stack([A[i, 0] * B[0, j] + A[i, 1] * B[1, j] + A[i, 2] * B[2, j]
                                 for j in range(3)]) for i in range(3)])


def _dot3(a: jnp.ndarray, b: jnp.ndarray) -> jnp.ndarray:
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def exp_se3(xi: jnp.ndarray) -> tuple[jnp.ndarray, jnp.ndarray]:
    """exp of a twist xi = [v, w] (6,) as (R (3, 3), t (3,)): Rodrigues' formula,
    R = I + A W + B W^2 and t = (I + B W + C W^2) v with W = [w]x, theta = |w|,
    A = sin(theta) / theta, B = (1 - cos theta) / theta^2, C = (theta - sin theta) / theta^3.
    B is computed as sinc(theta / 2)^2 / 2 and C by its series below theta = 0.1 (both
    cancel catastrophically in float32 otherwise)."""
    v, w = xi[:3], xi[3:]
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
    zero = jnp.zeros_like(w[0])
    W = jnp.stack([jnp.stack([zero, -w[2], w[1]]), jnp.stack([w[2], zero, -w[0]]),
                   jnp.stack([-w[1], w[0], zero])])
    W2 = _matmul3(W, W)
    eye = jnp.eye(3, dtype=xi.dtype)
    return eye + A * W + B * W2, _matmul3(eye + B * W + C * W2, v)


class Rigid(NamedTuple):
    """A rigid transform as its rotation matrix R (3, 3) and translation t (3,) (a pytree).

    The solve's pose: its left update ``retract`` and ``transform_points`` are a few fused
    elementwise kernels on XLA's CPU backend, where jaxlie's quaternion SE3 costs dozens of
    small ones per Levenberg-Marquardt try (the try's cost on 512 edges is mostly such
    per-kernel overhead)."""

    R: jnp.ndarray
    t: jnp.ndarray

    @staticmethod
    def from_matrix(T: jnp.ndarray) -> Rigid:
        """From a (4, 4) matrix, its rotation block projected back onto SO(3) (Gram-Schmidt
        on the rows; float32 products drift from orthonormality by ~1e-7 each)."""
        r0 = T[0, :3]
        r0 = r0 / jnp.sqrt(_dot3(r0, r0))
        r1 = T[1, :3] - _dot3(T[1, :3], r0) * r0
        r1 = r1 / jnp.sqrt(_dot3(r1, r1))
        r2 = jnp.stack([r0[1] * r1[2] - r0[2] * r1[1], r0[2] * r1[0] - r0[0] * r1[2],
                        r0[0] * r1[1] - r0[1] * r1[0]])
        return Rigid(jnp.stack([r0, r1, r2]), T[:3, 3])

    def as_matrix(self) -> jnp.ndarray:
        """The (4, 4) matrix."""
        top = jnp.concatenate([self.R, self.t[:, None]], axis=1)
        bottom = jnp.asarray([[0.0, 0.0, 0.0, 1.0]], self.R.dtype)
        return jnp.concatenate([top, bottom], axis=0)

    def translation(self) -> jnp.ndarray:
        """t (3,)."""
        return self.t

    def retract(self, xi: jnp.ndarray) -> Rigid:
        """exp(xi) * self for a left twist xi = [v, w] (6,)."""
        dR, dt = exp_se3(xi)
        return Rigid(_matmul3(dR, self.R), _matmul3(dR, self.t) + dt)


def retract_left(T: jaxlie.SE3 | Rigid, xi: jnp.ndarray) -> jaxlie.SE3 | Rigid:
    """Left-multiplicative update exp(xi) * T, xi = [v, w] (6,)."""
    if isinstance(T, Rigid):
        return T.retract(xi)
    return jaxlie.SE3.exp(xi) @ T


def rotation_translation(T: jaxlie.SE3 | Rigid) -> tuple[jnp.ndarray, jnp.ndarray]:
    """(R (3, 3), t (3,)) of a pose."""
    if isinstance(T, Rigid):
        return T.R, T.t
    return T.rotation().as_matrix(), T.translation()


def transform_points(T: jaxlie.SE3 | Rigid, pts: jnp.ndarray) -> jnp.ndarray:
    """R @ p + t for points (3, K) (struct of arrays)."""
    R, t = rotation_translation(T)
    x, y, z = pts[0], pts[1], pts[2]
    return jnp.stack([R[i, 0] * x + R[i, 1] * y + R[i, 2] * z + t[i] for i in range(3)])


def inverse_np(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid 4x4 transform (numpy)."""
    R, t = T[:3, :3], T[:3, 3]
    out = np.eye(4)
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ t
    return out


def rotation_angle_np(T: np.ndarray) -> float:
    """Rotation angle (rad) of a 4x4 rigid transform."""
    c = (np.trace(T[:3, :3]) - 1.0) / 2.0
    return float(np.arccos(np.clip(c, -1.0, 1.0)))


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
    xi = np.asarray(jaxlie.SE3.from_matrix(T).log(), np.float64)
    return np.asarray(jaxlie.SE3.exp(s * xi).as_matrix(), np.float64)
