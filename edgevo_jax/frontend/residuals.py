"""Warp, distance residual, its analytic Jacobian, and the gradient-consistency mask.

Keyframe edges enter as 3D points P = pi^-1(p, rho) (3, K) in the keyframe (computed once
per alignment: each pyramid level only changes the intrinsics).

r_i(xi) = D_c(pi(exp(xi) T P_i))  (EdgeVO, distance-field residual)
dr/dxi at xi = 0 = grad D(u') . d pi / dP (P') . [I | -[P']x]   with P' = T P_i,
twist xi = [v, w], left perturbation.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from ..camera import Intrinsics, project
from ..geometry import Pose
from ..image.interp import bilinear, bilinear_with_grad, edge_direction_at
from ..image.preprocess import EdgeMap
from .shutter import RowMotion, shutter_warp


def warp(
    intr: Intrinsics, T_c_k: Pose, pts_k: jnp.ndarray
) -> tuple[jnp.ndarray, jnp.ndarray]:
    """w(rho, p, xi): keyframe points (3, K) into the current camera; returns the warped
    pixels (2, K) and the points P' (3, K) in the current camera frame."""
    pts = T_c_k.apply(pts_k)
    return project(intr, pts), pts


def residual(
    field: jnp.ndarray, intr: Intrinsics, T_c_k: Pose, pts_k: jnp.ndarray
) -> tuple[jnp.ndarray, jnp.ndarray]:
    """Distance residuals r (K,) and validity (in front of the camera and inside the field)."""
    uv_c, pts = warp(intr, T_c_k, pts_k)
    r, inside = bilinear(field, uv_c)
    return r, inside & (pts[2] > 1e-6)


def residual_and_jacobian(
    field: jnp.ndarray, intr: Intrinsics, T_c_k: Pose, pts_k: jnp.ndarray
) -> tuple[jnp.ndarray, jnp.ndarray, jnp.ndarray, jnp.ndarray]:
    """Residuals (K,), analytic Jacobian w.r.t. a left twist [v, w] (6, K), validity (K,)
    and warped pixels (2, K)."""
    r, J, ok, uv_c, _ = residual_jacobian_grad(field, intr, T_c_k, pts_k)
    return r, J, ok, uv_c


def residual_jacobian_grad(
    field: jnp.ndarray, intr: Intrinsics, T_c_k: Pose, pts_k: jnp.ndarray,
    rows: RowMotion | None = None,
) -> tuple[jnp.ndarray, jnp.ndarray, jnp.ndarray, jnp.ndarray, jnp.ndarray]:
    """``residual_and_jacobian`` and the field's gradient at the warped pixels (2, K).
    ``rows``: the frame's rolling shutter (``shutter.shutter_warp``; None: a global
    shutter)."""
    if rows is None:
        uv_c, pts = warp(intr, T_c_k, pts_k)
        scale = None
    else:
        uv_c, pts, scale = shutter_warp(intr, T_c_k, pts_k, rows)
    r, grad, inside = bilinear_with_grad(field, uv_c)
    J = point_jacobian(intr, pts, grad)
    return r, J if scale is None else J * scale, inside & (pts[2] > 1e-6), uv_c, grad


def point_jacobian(intr: Intrinsics, pts: jnp.ndarray, grad: jnp.ndarray) -> jnp.ndarray:
    """d/dxi of f(pi(exp(xi) P')) at xi = 0 for a pixel-space gradient ``grad`` = df/du (2, K)
    at points P' (3, K): grad . d pi/dP . [I | -[P']x], (6, K)."""
    x, y, z = pts[0], pts[1], pts[2]
    iz = 1.0 / jnp.where(z > 1e-6, z, 1.0)
    ax = grad[0] * intr.fx * iz  # a = df/dP' = grad . d pi/dP
    ay = grad[1] * intr.fy * iz
    az = -(ax * x + ay * y) * iz
    # a . (w x P') = w . (P' x a)
    return jnp.stack([ax, ay, az, y * az - z * ay, z * ax - x * az, x * ay - y * ax])


def residual_jacobian_autodiff(
    field: jnp.ndarray, intr: Intrinsics, T_c_k: Pose, pts_k: jnp.ndarray
) -> jnp.ndarray:
    """The same Jacobian (6, K) by forward-mode autodiff of r(exp(xi) T) at xi = 0."""

    def r_of(xi: jnp.ndarray) -> jnp.ndarray:
        return residual(field, intr, T_c_k.retract(xi), pts_k)[0]

    return jax.jacfwd(r_of)(jnp.zeros(6, pts_k.dtype)).T


def consistency_dots_at_level(
    grad_k: jnp.ndarray, edges: EdgeMap, uv_l: jnp.ndarray, r: jnp.ndarray,
    field_grad: jnp.ndarray, level: int,
) -> jnp.ndarray:
    """g(p) . g(p') (K,) for warped level-l pixels uv_l (2, K) whose residuals r (K,) and
    field gradients (2, K) are known (the solve has them), with g(p) (2, K) the keyframe
    edges' normalised gradients and p' the nearest frame edge; -1 where none is found. The
    step to the nearest edge is taken on level l's field, with no further lookups in level
    0's. Piecewise constant in uv_l: zero derivative."""
    uv0 = (uv_l + 0.5) * (2.0**level) - 0.5
    return consistency_dots_known(grad_k, edges.code, uv0, r * (2.0**level), field_grad)


def consistency_dots_known(grad_k: jnp.ndarray, code: jnp.ndarray, uv0: jnp.ndarray,
                           d: jnp.ndarray, field_grad: jnp.ndarray) -> jnp.ndarray:
    """``consistency_dots_at_level`` for level-0 points uv0 (2, K) whose distances d (K,)
    (level-0 px) and distance-field gradients (2, K) are already known: no lookup of the
    field again;
    code: the frame's direction codes (``preprocess.EdgeMap.code``)."""
    return _dots(grad_k, *edge_direction_at(code, uv0, d, field_grad))


def _dots(grad_k: jnp.ndarray, g_near: jnp.ndarray, found: jnp.ndarray) -> jnp.ndarray:
    g_near = g_near.astype(grad_k.dtype)
    return jnp.where(found, grad_k[0] * g_near[0] + grad_k[1] * g_near[1], -1.0)
