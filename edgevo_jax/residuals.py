"""Warp, distance residual, its analytic Jacobian, and the gradient-consistency mask.

r_i(xi) = D_c(pi(exp(xi) T pi^-1(p_i, rho_i)))  (EdgeVO, distance-field residual)
dr/dxi at xi = 0 = grad D(u') . d pi / dP (P') . [I | -[P']x]   with P' = T pi^-1(p_i, rho_i).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import jaxlie

from .camera import Intrinsics, project, project_jacobian, unproject
from .geometry import retract_left, transform_points
from .interp import bilinear, bilinear_with_grad, nearest


def warp(
    intr: Intrinsics, T_c_k: jaxlie.SE3, uv: jnp.ndarray, rho: jnp.ndarray
) -> tuple[jnp.ndarray, jnp.ndarray]:
    """w(rho, p, xi): keyframe pixels uv (K, 2) with inverse depth rho (K,) into the current
    frame; returns the warped pixels (K, 2) and the points P' (K, 3) in the current camera."""
    pts = transform_points(T_c_k, unproject(intr, uv, rho))
    return project(intr, pts), pts


def residual(
    field: jnp.ndarray, intr: Intrinsics, T_c_k: jaxlie.SE3, uv: jnp.ndarray, rho: jnp.ndarray
) -> tuple[jnp.ndarray, jnp.ndarray]:
    """Distance residuals r (K,) and validity (in front of the camera and inside the field)."""
    uv_c, pts = warp(intr, T_c_k, uv, rho)
    r, inside = bilinear(field, uv_c)
    return r, inside & (pts[:, 2] > 1e-6)


def residual_and_jacobian(
    field: jnp.ndarray, intr: Intrinsics, T_c_k: jaxlie.SE3, uv: jnp.ndarray, rho: jnp.ndarray
) -> tuple[jnp.ndarray, jnp.ndarray, jnp.ndarray, jnp.ndarray]:
    """Residuals (K,), analytic Jacobian w.r.t. a left twist [v, w] (K, 6), validity (K,)
    and warped pixels (K, 2)."""
    uv_c, pts = warp(intr, T_c_k, uv, rho)
    r, grad, inside = bilinear_with_grad(field, uv_c)
    a = jnp.sum(grad[..., :, None] * project_jacobian(intr, pts), axis=-2)  # dD/dP' (K, 3)
    jac = jnp.concatenate([a, jnp.cross(pts, a)], axis=-1)  # a.(w x P') = w.(P' x a)
    return r, jac, inside & (pts[:, 2] > 1e-6), uv_c


def residual_jacobian_autodiff(
    field: jnp.ndarray, intr: Intrinsics, T_c_k: jaxlie.SE3, uv: jnp.ndarray, rho: jnp.ndarray
) -> jnp.ndarray:
    """The same Jacobian (K, 6) by forward-mode autodiff of r(exp(xi) T) at xi = 0."""

    def r_of(xi: jnp.ndarray) -> jnp.ndarray:
        return residual(field, intr, retract_left(T_c_k, xi), uv, rho)[0]

    return jax.jacfwd(r_of)(jnp.zeros(6, uv.dtype))


def gradient_consistent(
    grad_k: jnp.ndarray, nearest_grad: jnp.ndarray, uv0: jnp.ndarray, eta: float
) -> jnp.ndarray:
    """g(p) . g(p') >= eta, with p' the nearest edge to the warped level-0 pixel uv0 (K, 2);
    nearest_grad (H, W, 2) holds g(p') * 127 as int8 (see preprocess.nearest_edge_map)."""
    g_near = nearest(nearest_grad, uv0).astype(grad_k.dtype) * (1.0 / 127.0)
    return jnp.sum(grad_k * g_near, axis=-1) >= eta
