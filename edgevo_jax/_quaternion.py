"""Unit-quaternion SO(3) / SE(3) arithmetic, jaxlie's op for op and over leading axes (so
its float32 rounding too), behind ``geometry.Pose``'s quaternion paths (see that module).
Quaternions are wxyz (..., 4)."""

from __future__ import annotations

import jax.numpy as jnp


def quat_eps(dtype: jnp.dtype) -> float:
    """jaxlie's small-angle threshold on |w|^2 for ``dtype``."""
    return 1e-10 if jnp.dtype(dtype) == jnp.float64 else 1e-5


def quat_from_matrix(m: jnp.ndarray) -> jnp.ndarray:
    """The unit quaternion of a nearly orthonormal m (..., 3, 3): from the case of largest
    diagonal (Mike Day, "Converting a rotation matrix to a quaternion")."""
    def at(i, j):
        return m[..., i, j]

    cases = (
        (1 + at(0, 0) - at(1, 1) - at(2, 2),
         lambda t: [at(2, 1) - at(1, 2), t, at(1, 0) + at(0, 1), at(0, 2) + at(2, 0)]),
        (1 - at(0, 0) + at(1, 1) - at(2, 2),
         lambda t: [at(0, 2) - at(2, 0), at(1, 0) + at(0, 1), t, at(2, 1) + at(1, 2)]),
        (1 - at(0, 0) - at(1, 1) + at(2, 2),
         lambda t: [at(1, 0) - at(0, 1), at(0, 2) + at(2, 0), at(2, 1) + at(1, 2), t]),
        (1 + at(0, 0) + at(1, 1) + at(2, 2),
         lambda t: [t, at(2, 1) - at(1, 2), at(0, 2) - at(2, 0), at(1, 0) - at(0, 1)]),
    )
    (t0, q0), (t1, q1), (t2, q2), (t3, q3) = ((t, jnp.stack(q(t), axis=-1)) for t, q in cases)
    cond0, cond1, cond2 = at(2, 2) < 0, at(0, 0) > at(1, 1), at(0, 0) < -at(1, 1)
    t = jnp.where(cond0, jnp.where(cond1, t0, t1), jnp.where(cond2, t2, t3))
    q = jnp.where(cond0[..., None], jnp.where(cond1[..., None], q0, q1),
                  jnp.where(cond2[..., None], q2, q3))
    return q * 0.5 / jnp.sqrt(t[..., None])


def quat_as_matrix(wxyz: jnp.ndarray) -> jnp.ndarray:
    """The rotation matrix (..., 3, 3) of a quaternion (..., 4) (normalised first)."""
    q = wxyz * jnp.sqrt(2.0 / jnp.sum(jnp.square(wxyz), axis=-1, keepdims=True))
    o = jnp.einsum("...i,...j->...ij", q, q)
    return jnp.stack([
        1.0 - o[..., 2, 2] - o[..., 3, 3], o[..., 1, 2] - o[..., 3, 0],
        o[..., 1, 3] + o[..., 2, 0], o[..., 1, 2] + o[..., 3, 0],
        1.0 - o[..., 1, 1] - o[..., 3, 3], o[..., 2, 3] - o[..., 1, 0],
        o[..., 1, 3] - o[..., 2, 0], o[..., 2, 3] + o[..., 1, 0],
        1.0 - o[..., 1, 1] - o[..., 2, 2],
    ], axis=-1).reshape(*q.shape[:-1], 3, 3)


def quaternion_projection(m: jnp.ndarray) -> jnp.ndarray:
    """The rotation (..., 3, 3) of the unit quaternion of a nearly orthonormal m."""
    return quat_as_matrix(quat_from_matrix(m))


def quat_mul(a: jnp.ndarray, b: jnp.ndarray) -> jnp.ndarray:
    """The Hamilton product a b of quaternions (..., 4)."""
    terms_i = jnp.array([[0, 1, 2, 3], [0, 1, 2, 3], [0, 2, 3, 1], [0, 3, 1, 2]])
    terms_j = jnp.array([[0, 1, 2, 3], [1, 0, 3, 2], [2, 0, 1, 3], [3, 0, 2, 1]])
    signs = jnp.array([[1, -1, -1, -1], [1, 1, 1, -1], [1, 1, 1, -1], [1, 1, 1, -1]])
    outer = jnp.einsum("...i,...j->...ij", a, b)
    return jnp.sum(signs * outer[..., terms_i, terms_j], axis=-1)


def quat_conj(q: jnp.ndarray) -> jnp.ndarray:
    """The conjugate (inverse of a unit quaternion), wxyz (..., 4)."""
    return q * jnp.array([1, -1, -1, -1])


def quat_apply(q: jnp.ndarray, p: jnp.ndarray) -> jnp.ndarray:
    """q p q^-1 of points p (..., 3)."""
    padded = jnp.concatenate([jnp.zeros((*p.shape[:-1], 1), p.dtype), p], axis=-1)
    return quat_mul(quat_mul(q, padded), quat_conj(q))[..., 1:]


def quat_exp(w: jnp.ndarray) -> jnp.ndarray:
    """exp of rotation vectors w (..., 3) as quaternions (..., 4) (series near 0)."""
    th2 = jnp.sum(jnp.square(w), axis=-1)
    th4 = th2 * th2
    taylor = th2 < quat_eps(w.dtype)
    th = jnp.sqrt(jnp.where(taylor, jnp.ones_like(th2), th2))
    real = jnp.where(taylor, 1.0 - th2 / 8.0 + th4 / 384.0, jnp.cos(0.5 * th))
    imag = jnp.where(taylor, 0.5 - th2 / 48.0 + th4 / 3840.0, jnp.sin(0.5 * th) / th)
    return jnp.concatenate([real[..., None], imag[..., None] * w], axis=-1)


def quat_log(wxyz: jnp.ndarray) -> jnp.ndarray:
    """The rotation vectors (..., 3) of quaternions (..., 4)."""
    w = wxyz[..., 0]
    n2 = jnp.sum(jnp.square(wxyz[..., 1:]), axis=-1)
    taylor = n2 < quat_eps(n2.dtype)
    n = jnp.sqrt(jnp.where(taylor, 1.0, n2))
    w_safe = jnp.where(taylor, w, 1.0)
    atan = jnp.arctan2(jnp.where(w < 0, -n, n), jnp.abs(w))
    factor = jnp.where(
        taylor, 2.0 / w_safe - 2.0 / 3.0 * n2 / w_safe**3,
        jnp.where(jnp.abs(w) < quat_eps(w.dtype), jnp.where(w > 0, 1.0, -1.0) * jnp.pi / n,
                  2.0 * atan / n))
    return factor[..., None] * wxyz[..., 1:]


def skew(w: jnp.ndarray) -> jnp.ndarray:
    """[w]x (..., 3, 3) of w (..., 3)."""
    wx, wy, wz = jnp.moveaxis(w, -1, 0)
    zero = jnp.zeros_like(wx)
    return jnp.stack([zero, -wz, wy, wz, zero, -wx, -wy, wx, zero],
                     axis=-1).reshape(*w.shape[:-1], 3, 3)


def quat_se3_exp(xi: jnp.ndarray) -> tuple[jnp.ndarray, jnp.ndarray]:
    """exp of twists [v, w] (..., 6) as (R (..., 3, 3), t (..., 3)) through the quaternion
    of w: R its matrix, t = V v with V = R near 0, else I + B W + C W^2."""
    w = xi[..., 3:]
    R = quat_as_matrix(quat_exp(w))
    th2 = jnp.sum(jnp.square(w), axis=-1)
    taylor = th2 < quat_eps(th2.dtype)
    th2 = jnp.where(taylor, jnp.ones_like(th2), th2)
    th = jnp.sqrt(th2)
    W = skew(w)
    eye = jnp.eye(3, dtype=xi.dtype)
    V = jnp.where(taylor[..., None, None], R,
                  eye + ((1.0 - jnp.cos(th)) / th2)[..., None, None] * W
                  + ((th - jnp.sin(th)) / (th2 * th))[..., None, None]
                  * jnp.einsum("...ij,...jk->...ik", W, W))
    return R, jnp.einsum("...ij,...j->...i", V, xi[..., :3])


def quat_se3_log(q: jnp.ndarray, t: jnp.ndarray) -> jnp.ndarray:
    """The twists [v, w] (..., 6) of (quaternion (..., 4), translation (..., 3))."""
    w = quat_log(q)
    th2 = jnp.sum(jnp.square(w), axis=-1)
    taylor = th2 < quat_eps(th2.dtype)
    th2 = jnp.where(taylor, jnp.ones_like(th2), th2)
    th = jnp.sqrt(th2)
    W = skew(w)
    W2 = jnp.einsum("...ij,...jk->...ik", W, W)
    eye = jnp.eye(3, dtype=t.dtype)
    V_inv = jnp.where(taylor[..., None, None], eye - 0.5 * W + W2 / 12.0,
                      eye - 0.5 * W + ((1.0 - th * jnp.cos(th / 2.0) / (2.0 * jnp.sin(th / 2.0)))
                                       / th2)[..., None, None] * W2)
    return jnp.concatenate([jnp.einsum("...ij,...j->...i", V_inv, t), w], axis=-1)
