"""Bilinear and bicubic lookup of a 2D field at sub-pixel points (pure and differentiable).

Points are struct-of-arrays, uv (2, K) = (columns, rows), origin at the centre of the top-left
pixel. Points outside [0, W-1] x [0, H-1] are clamped for the lookup and flagged invalid.

The bilinear interpolant (the tracker's) is continuous but its derivative jumps at pixel
boundaries. The bicubic one (``bicubic_with_grad``: Catmull-Rom / Keys cubic convolution,
a = -0.5) passes through the same pixel values and is continuously differentiable (C1) over
the whole field, so a cost built on it has a gradient everywhere (the differentiable path's
``interpolation="bicubic"``, ``learn.differentiable``).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jax.custom_derivatives import SymbolicZero

from ..hostmem import aligned_stack
from .preprocess import EdgeMap

_PATCH = jax.lax.GatherDimensionNumbers(
    offset_dims=(1, 2), collapsed_slice_dims=(), start_index_map=(0, 1))


def _corners(field: jnp.ndarray, uv: jnp.ndarray):
    h, w = field.shape
    u, v = uv[0], uv[1]
    valid = (u >= 0) & (u <= w - 1) & (v >= 0) & (v <= h - 1)
    u0 = jnp.clip(jnp.floor(u), 0, w - 2)
    v0 = jnp.clip(jnp.floor(v), 0, h - 2)
    fu = jnp.clip(u - u0, 0.0, 1.0)
    fv = jnp.clip(v - v0, 0.0, 1.0)
    # one gather of the 2 x 2 patch at (v0, u0) rather than four of single values: on XLA's
    # CPU backend each gather is a kernel of its own that recomputes the points it reads
    start = jnp.stack([v0, u0], axis=-1).astype(jnp.int32)
    patch = jax.lax.gather(field, start, _PATCH, (2, 2), mode="clip")
    f00, f01, f10, f11 = patch[:, 0, 0], patch[:, 0, 1], patch[:, 1, 0], patch[:, 1, 1]
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


def _keys_weights(t: jnp.ndarray) -> tuple[jnp.ndarray, jnp.ndarray, jnp.ndarray]:
    """Catmull-Rom (Keys, a = -0.5) weights (4, K) of the samples at offsets -1, 0, 1, 2 for
    fractional positions t (K,) in [0, 1], and their first and second derivatives d/dt."""
    t2, t3 = t * t, t * t * t
    w = jnp.stack([(-t3 + 2.0 * t2 - t), (3.0 * t3 - 5.0 * t2 + 2.0),
                   (-3.0 * t3 + 4.0 * t2 + t), (t3 - t2)]) * 0.5
    dw = jnp.stack([(-3.0 * t2 + 4.0 * t - 1.0), (9.0 * t2 - 10.0 * t),
                    (-9.0 * t2 + 8.0 * t + 1.0), (3.0 * t2 - 2.0 * t)]) * 0.5
    ddw = jnp.stack([(-6.0 * t + 4.0), (18.0 * t - 10.0), (-18.0 * t + 8.0), (6.0 * t - 2.0)]) * 0.5
    return w, dw, ddw


def _bicubic_parts(field: jnp.ndarray, uv: jnp.ndarray):
    """Value (K,), gradient (2, K), Hessian (uu, uv, vv) (3, K) of the Catmull-Rom interpolant
    at uv (2, K), and the inside-mask (K,)."""
    h, w = field.shape
    u, v = uv[0], uv[1]
    valid = (u >= 0) & (u <= w - 1) & (v >= 0) & (v <= h - 1)
    u0 = jnp.clip(jnp.floor(u), 0, w - 2)
    v0 = jnp.clip(jnp.floor(v), 0, h - 2)
    tu = jnp.where((u >= 0) & (u <= w - 1), u - u0, jnp.clip(u - u0, 0.0, 1.0))
    tv = jnp.where((v >= 0) & (v <= h - 1), v - v0, jnp.clip(v - v0, 0.0, 1.0))
    wu, dwu, ddwu = _keys_weights(tu)
    wv, dwv, ddwv = _keys_weights(tv)
    offsets = jnp.arange(-1, 3, dtype=jnp.int32)[:, None]
    cols = jnp.clip(u0.astype(jnp.int32)[None] + offsets, 0, w - 1)  # (4, K)
    rows = jnp.clip(v0.astype(jnp.int32)[None] + offsets, 0, h - 1)
    patch = jnp.take(field.reshape(-1), rows[:, None, :] * w + cols[None, :, :],
                     mode="clip")  # (4 rows, 4 cols, K)
    along_u = jnp.einsum("jk,ijk->ik", wu, patch)  # each row interpolated at u (4, K)
    d_along_u = jnp.einsum("jk,ijk->ik", dwu, patch)
    dd_along_u = jnp.einsum("jk,ijk->ik", ddwu, patch)
    value = jnp.sum(wv * along_u, axis=0)
    grad = jnp.stack([jnp.sum(wv * d_along_u, axis=0), jnp.sum(dwv * along_u, axis=0)])
    hess = jnp.stack([jnp.sum(wv * dd_along_u, axis=0), jnp.sum(dwv * d_along_u, axis=0),
                      jnp.sum(ddwv * along_u, axis=0)])
    return value, grad, hess, valid


@jax.custom_jvp
def bicubic_with_grad(
    field: jnp.ndarray, uv: jnp.ndarray
) -> tuple[jnp.ndarray, jnp.ndarray, jnp.ndarray]:
    """Catmull-Rom bicubic lookup: values (K,), the exact derivative of the interpolant
    d/d(u, v) (2, K) and the inside-mask (K,), with ``bilinear_with_grad``'s conventions.

    Each value mixes the 4 x 4 pixels around the point (rows and columns beyond the border
    repeat the border's). The interpolant passes through the pixel values, is C1 on
    [0, W-1] x [0, H-1] (its second derivative jumps at pixel boundaries), and reproduces
    polynomials of degree <= 2 in each of u, v exactly where the 4 x 4 pixels lie inside the
    field (1 <= u <= W-2, 1 <= v <= H-2). Differentiable to any order: the derivative
    rule gives d value = grad . d uv and d grad = Hessian d uv from the interpolant's own
    second derivatives (a few products per point, where differentiating the lookup itself
    costs reverse mode a chain of gathers per point), plus the lookup of a field tangent."""
    value, grad, _, valid = _bicubic_parts(field, uv)
    return value, grad, valid


def _bicubic_jvp(primals, tangents):
    field, uv = primals
    d_field, d_uv = tangents
    value, grad, hess, valid = _bicubic_parts(field, uv)
    if isinstance(d_uv, SymbolicZero):
        d_value, d_grad = jnp.zeros_like(value), jnp.zeros_like(grad)
    else:
        du, dv = d_uv[0], d_uv[1]
        d_value = grad[0] * du + grad[1] * dv
        d_grad = jnp.stack([hess[0] * du + hess[1] * dv, hess[1] * du + hess[2] * dv])
    if not isinstance(d_field, SymbolicZero):
        fv, fg, _, _ = _bicubic_parts(d_field, uv)
        d_value, d_grad = d_value + fv, d_grad + fg
    return (value, grad, valid), (d_value, d_grad, np.zeros(valid.shape, jax.dtypes.float0))


bicubic_with_grad.defjvp(_bicubic_jvp, symbolic_zeros=True)


def bicubic(field: jnp.ndarray, uv: jnp.ndarray) -> tuple[jnp.ndarray, jnp.ndarray]:
    """Field (H, W) at points uv (2, K) by ``bicubic_with_grad``: values (K,) and the
    inside-mask (K,)."""
    value, _, valid = bicubic_with_grad(field, uv)
    return value, valid


def nearest(field: jnp.ndarray, uv: jnp.ndarray) -> jnp.ndarray:
    """Field (H, W, C) at the pixel nearest to each point uv (2, K), clamped: (C, K)."""
    h, w, c = field.shape
    iu = jnp.clip(jnp.round(uv[0]), 0, w - 1).astype(jnp.int32)
    iv = jnp.clip(jnp.round(uv[1]), 0, h - 1).astype(jnp.int32)
    return jnp.take(field.reshape(h * w, c), iv * w + iu, axis=0, mode="clip").T


def nearest_edge_gradient(edges: EdgeMap, uv0: jnp.ndarray) -> tuple[jnp.ndarray, jnp.ndarray]:
    """Normalised gradient g(p') (2, K) of the nearest edge to level-0 pixels uv0 (2, K),
    and whether one was found (K,).

    The distance field's gradient points away from the nearest edge, so
    p' ~ p - D(p) grad D(p) / |grad D(p)| (one step, exact for a straight edge); the code
    map, filled one pixel around the edges, gives that edge's direction at round(p'). A
    nearest-pixel lookup: piecewise constant in uv0, so it is held constant under
    differentiation."""
    d, g, _ = bilinear_with_grad(edges.dist0, jax.lax.stop_gradient(uv0))
    return edge_direction_at(edges.code, uv0, d, g)


def edge_direction_at(
    code: jnp.ndarray, uv0: jnp.ndarray, d: jnp.ndarray, g: jnp.ndarray
) -> tuple[jnp.ndarray, jnp.ndarray]:
    """``nearest_edge_gradient`` from the distance d (K,) (level-0 px) and a vector g (2, K)
    along the distance field's gradient at uv0 (2, K), e.g. a coarser level's: the step is
    p' = uv0 - d g / |g|, and code (H, W) the direction map. Held constant under
    differentiation."""
    uv0, d, g = (jax.lax.stop_gradient(a) for a in (uv0, d, g))
    # two terms written out, not jnp.sum over the axis: XLA on CPU hands small reductions
    # of batched (vmapped) arrays to a library call that is slow at thousands of points
    norm = jnp.sqrt(g[0] * g[0] + g[1] * g[1])
    target = uv0 - g * (d / jnp.maximum(norm, 1e-6))
    c = nearest(code[..., None], target)[0].astype(jnp.int32)
    table = direction_table(uv0.dtype)
    return jnp.take(table, c, axis=1), c > 0


def direction_table(dtype) -> jnp.ndarray:
    """(2, 255) unit vectors of the direction codes (column 0, no edge, is zero)."""
    angle = np.arange(-1, 254) * (2.0 * np.pi / 254.0) - np.pi
    table = np.stack([np.cos(angle), np.sin(angle)])
    table[:, 0] = 0.0
    return jnp.asarray(table, dtype)


def stack_edge_maps(maps) -> EdgeMap:
    """EdgeMaps (numpy) stacked on a new leading axis: dist0 (n, H, W), code (n, H, W),
    depth (n, H, W) or None."""
    return EdgeMap(*(None if xs[0] is None else aligned_stack(xs)
                     for xs in zip(*maps, strict=True)))
