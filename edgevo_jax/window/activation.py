"""Edge activation for the local window (EdgeVO, after DSO).

When a keyframe joins the window, the edges of the earlier keyframes are re-projected into it
and activated per ``cell`` x ``cell`` pixel cell of the new keyframe when all of these hold:
1. their geometric residual (distance to the nearest edge of the new keyframe) is under the
   median of all the re-projected residuals;
2. their gradient direction, carried into the new keyframe, is within ``max_angle_deg`` of the
   gradient of the nearest edge there;
3. among the candidates of a cell, the edge tracked longest (largest track count) wins; ties
   go to the smaller residual, then to the lower index (deterministic).
Pure JAX with fixed shapes: the per-cell choice is one segment_max.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp

from ..camera import Intrinsics
from ..frontend.residuals import warp
from ..frontend.shutter import RowMotion, shutter_warp
from ..geometry import Pose
from ..image.interp import bilinear, nearest_edge_gradient


def carried_gradient(
    intr: Intrinsics, T_new_host: Pose, pts_host: jnp.ndarray, grad: jnp.ndarray
) -> jnp.ndarray:
    """Normalised gradient directions (2, N) of host edges after the warp into the new
    keyframe: the image of a small step along the host gradient (first-order warp)."""
    eps = 0.5  # pixels: the step whose image gives the direction
    z = pts_host[2]
    step = jnp.stack([grad[0] * eps / intr.fx * z, grad[1] * eps / intr.fy * z,
                      jnp.zeros_like(z)])
    uv_a, _ = warp(intr, T_new_host, pts_host)
    uv_b, _ = warp(intr, T_new_host, pts_host + step)
    d = uv_b - uv_a
    return d / jnp.maximum(jnp.linalg.norm(d, axis=0), 1e-9)


def reproject(
    intr: Intrinsics, T_new_host: Pose, pts_host: jnp.ndarray, grad: jnp.ndarray,
    field: jnp.ndarray, edge_map: jnp.ndarray, rows: RowMotion | None = None,
) -> tuple[jnp.ndarray, jnp.ndarray, jnp.ndarray, jnp.ndarray]:
    """Host edges (points (3, N) in the host camera, gradients (2, N)) seen from the new
    keyframe: pixels (2, N), residuals (N,) in the new keyframe's level-0 distance field,
    cosine (N,) between the carried gradient and the nearest edge's, and visibility (N,).
    ``rows``: the new keyframe's rolling shutter (``frontend.shutter``; None: global)."""
    if rows is None:
        uv, pts = warp(intr, T_new_host, pts_host)
    else:
        uv, pts, _ = shutter_warp(intr, T_new_host, pts_host, rows)
    r, inside = bilinear(field, uv)
    g_near, found = nearest_edge_gradient(edge_map, uv)
    cos = jnp.where(found, jnp.sum(carried_gradient(intr, T_new_host, pts_host, grad)
                                   * g_near.astype(r.dtype), axis=0), -1.0)
    return uv, r, cos, inside & (pts[2] > 1e-6)


def activate(
    uv: jnp.ndarray, residual: jnp.ndarray, cos: jnp.ndarray, track_count: jnp.ndarray,
    valid: jnp.ndarray, *, width: int, height: int, cell: int = 20,
    max_angle_deg: float = 30.0,
) -> jnp.ndarray:
    """Mask (N,) of the edges activated: at most one per cell, by the three rules above.

    uv (2, N) pixels in the new keyframe; residual (N,) px; cos (N,) gradient agreement;
    track_count (N,) int; valid (N,) edges that exist and are visible.
    """
    n = residual.shape[0]
    r_valid = jnp.where(valid, residual, jnp.nan)
    median = jnp.nanmedian(r_valid)
    eligible = valid & (residual < median) & (cos >= math.cos(math.radians(max_angle_deg)))
    cols, rows = -(-width // cell), -(-height // cell)
    cu = jnp.clip(jnp.floor((uv[0] + 0.5) / cell), 0, cols - 1).astype(jnp.int32)
    cv = jnp.clip(jnp.floor((uv[1] + 0.5) / cell), 0, rows - 1).astype(jnp.int32)
    cell_id = cv * cols + cu
    # one sortable key per edge: longest tracked, then smallest residual, then lowest index
    rank_r = jnp.argsort(jnp.argsort(jnp.where(eligible, residual, jnp.inf)))
    key = track_count.astype(jnp.int32) * (2 * n) + (n - 1 - rank_r)  # ranks are unique
    key = jnp.where(eligible, key, -1)
    best = jax.ops.segment_max(key, cell_id, num_segments=rows * cols)
    return eligible & (key == best[cell_id])
