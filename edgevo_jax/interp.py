"""Bilinear lookup of a 2D field at sub-pixel points (pure and differentiable).

Points are struct-of-arrays, uv (2, K) = (columns, rows), origin at the centre of the top-left
pixel. Points outside [0, W-1] x [0, H-1] are clamped for the lookup and flagged invalid.
"""

from __future__ import annotations

import jax.numpy as jnp


def _corners(field: jnp.ndarray, uv: jnp.ndarray):
    h, w = field.shape
    u, v = uv[0], uv[1]
    valid = (u >= 0) & (u <= w - 1) & (v >= 0) & (v <= h - 1)
    u0 = jnp.clip(jnp.floor(u), 0, w - 2)
    v0 = jnp.clip(jnp.floor(v), 0, h - 2)
    fu = jnp.clip(u - u0, 0.0, 1.0)
    fv = jnp.clip(v - v0, 0.0, 1.0)
    base = v0.astype(jnp.int32) * w + u0.astype(jnp.int32)
    flat = field.reshape(-1)
    f00, f01, f10, f11 = (jnp.take(flat, base + o, mode="clip") for o in (0, 1, w, w + 1))
    return f00, f01, f10, f11, fu, fv, valid


def bilinear(field: jnp.ndarray, uv: jnp.ndarray) -> tuple[jnp.ndarray, jnp.ndarray]:
    """Field (H, W) at points uv (2, K); returns values (K,) and the inside-mask (K,)."""
    f00, f01, f10, f11, fu, fv, valid = _corners(field, uv)
    top = f00 + fu * (f01 - f00)
    bottom = f10 + fu * (f11 - f10)
    return top + fv * (bottom - top), valid


def bilinear_with_grad(
    field: jnp.ndarray, uv: jnp.ndarray
) -> tuple[jnp.ndarray, jnp.ndarray, jnp.ndarray]:
    """Values (K,), the exact derivative of the bilinear interpolant d/d(u, v) (2, K) and the
    inside-mask (K,)."""
    f00, f01, f10, f11, fu, fv, valid = _corners(field, uv)
    top = f00 + fu * (f01 - f00)
    bottom = f10 + fu * (f11 - f10)
    du = (1 - fv) * (f01 - f00) + fv * (f11 - f10)
    return top + fv * (bottom - top), jnp.stack([du, bottom - top]), valid


def nearest(field: jnp.ndarray, uv: jnp.ndarray) -> jnp.ndarray:
    """Field (H, W, C) at the pixel nearest to each point uv (2, K), clamped: (C, K)."""
    h, w, c = field.shape
    iu = jnp.clip(jnp.round(uv[0]), 0, w - 1).astype(jnp.int32)
    iv = jnp.clip(jnp.round(uv[1]), 0, h - 1).astype(jnp.int32)
    return jnp.take(field.reshape(h * w, c), iv * w + iu, axis=0, mode="clip").T
