"""Depth registration: a depth map re-rendered as another camera, at another pose, would see
it (host side, numpy).

Conventions (docs/architecture.md): ``T_color_depth`` maps points from the depth frame to the
colour camera's (p_color = R p_depth + t, metres); pixels (u, v) = (column, row) with the
origin at the centre of the top-left pixel; depth is z in metres, 0 (or non-finite) = none.
"""

from __future__ import annotations

import numpy as np

from .camera import Intrinsics, checked_pose

__all__ = ["register_depth"]


def register_depth(
    depth: np.ndarray,
    intrinsics_depth: Intrinsics,
    intrinsics_color: Intrinsics,
    T_color_depth: np.ndarray,
    *,
    shape: tuple[int, int] | None = None,
) -> np.ndarray:
    """``depth`` (H, W), seen by a pinhole camera ``intrinsics_depth``, re-rendered as the
    colour camera sees it: float32 depth in metres in the colour camera's frame, of
    ``shape`` (height, width; None: ``depth``'s).

    Every valid pixel (finite, > 0) is back-projected at its centre, moved by
    ``T_color_depth`` (p_color = T p_depth, 4x4 rigid, metres) and projected into the colour
    camera onto the nearest pixel; where several land on one pixel the nearest surface (least
    z) wins. Pixels nothing lands on, and points at or behind the colour camera, are 0
    (missing): a forward splat, so a rotation or a finer colour grid leaves one-pixel cracks
    rather than inventing depth. With the identity and equal intrinsics, valid pixels come
    back exactly. ValueError for a depth that is not 2-D or a transform that is not rigid."""
    d = np.asarray(depth)
    if d.ndim != 2:
        raise ValueError(f"depth must be a 2-D (H, W) array, got shape {d.shape}")
    M = checked_pose(T_color_depth, "T_color_depth")
    height, width = d.shape if shape is None else (int(shape[0]), int(shape[1]))
    out = np.zeros((height, width), np.float32)
    v, u = np.nonzero(np.isfinite(d) & (d > 0))
    if v.size == 0:
        return out
    z = d[v, u].astype(np.float64)
    fx, fy, cx, cy = (float(x) for x in intrinsics_depth)
    pts = np.stack([(u - cx) / fx * z, (v - cy) / fy * z, z])
    pc = M[:3, :3] @ pts + M[:3, 3:4]
    front = pc[2] > 1e-6
    pc = pc[:, front]
    fx, fy, cx, cy = (float(x) for x in intrinsics_color)
    uc = np.rint(fx * pc[0] / pc[2] + cx)
    vc = np.rint(fy * pc[1] / pc[2] + cy)
    inside = (uc >= 0) & (uc < width) & (vc >= 0) & (vc < height)
    flat = vc[inside].astype(np.int64) * width + uc[inside].astype(np.int64)
    zc = pc[2, inside]
    order = np.lexsort((zc, flat))  # by pixel, nearest first
    flat, zc = flat[order], zc[order]
    first = np.ones(flat.size, bool)
    first[1:] = flat[1:] != flat[:-1]
    out.reshape(-1)[flat[first]] = zc[first]
    return out
