"""The depth residual (``Config.depth_residual``, on by default): point-to-plane ICP of
keyframe depth points against the frame's depth map, added to the edge residual's normal
equations at the finest pyramid level (as REVO and its successors combine them; at the
coarse levels the start is still far and the nearest-pixel matches are wrong).

A keyframe brings M points p_k with normals n_k (keyframe camera, metres; ``depth_points``).
At pose T = T_cur_kf the point q = T p_k projects into the frame; the nearest pixel with its
depth, back-projected, is p_c, the residual is the distance of p_c from the
point's plane, n_c . (q - p_c) with n_c = R n_k, expressed in pixels of the level
(x f_l / q_z, the image-plane size of that distance) so that it is weighed, gated and
Huber-weighted like an edge residual. Its Jacobian for the left update T <- exp(xi) T is
f_l / q_z [n_c, q x n_c] (p_c held, as point-to-plane ICP does).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from ..camera import Intrinsics
from ..geometry import Pose

#: the second opinion (``depth_agreement``): points drawn from the previous frame's depth, and
#: the fewest that must be judged (in view, in front of no other surface) for an answer
AGREEMENT_POINTS = 1024
AGREEMENT_MIN_JUDGED = 64
#: a point this many tolerances behind the surface seen is occluded (not judged); one nearer
#: to it than that but off it disagrees, as one in front of it does
OCCLUDED = 4.0
#: depth (m) at which the agreement's tolerance is its nominal value; it grows with the
#: square of depth beyond, as a structured-light sensor's noise does
AGREEMENT_NOMINAL_Z = 1.5

#: grid step (px) of the keyframe's candidate depth points, and the largest relative depth
#: change between a pixel's neighbours for its normal to count (a depth step is no plane)
GRID_STEP = 4
MAX_RELATIVE_STEP = 0.05


def depth_points(depth: np.ndarray, intr: Intrinsics, count: int, *, min_depth: float,
                 max_depth: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """``count`` keyframe points (3, count) with unit normals (3, count), float32, keyframe
    camera, metres, from a depth map (H, W) (outside [min_depth, max_depth] or NaN =
    missing): pixels on a ``GRID_STEP`` grid whose four neighbours have depth within
    ``MAX_RELATIVE_STEP`` of it, normals from the cross product of the central differences,
    ``count`` of them drawn with ``seed``. Padding slots (fewer candidates) have zero normals
    (``depth_valid``)."""
    depth = np.asarray(depth)
    h, w = depth.shape
    fx, fy, cx, cy = (float(v) for v in intr)
    # the grid's pixels and their four neighbours, as strided views (no copy of the image)
    g = GRID_STEP
    v, u = np.mgrid[g:h - 1:g, g:w - 1:g]
    u, v = u.ravel(), v.ravel()

    def at(dv: int, du: int) -> np.ndarray:
        z = depth[g + dv:h - 1 + dv:g, g + du:w - 1 + du:g].astype(np.float64).ravel()
        return np.where(np.isfinite(z) & (z >= min_depth) & (z <= max_depth), z, 0.0)

    z, zl, zr, zu, zd = at(0, 0), at(0, -1), at(0, 1), at(-1, 0), at(1, 0)
    ok = (z > 0) & (zl > 0) & (zr > 0) & (zu > 0) & (zd > 0)
    ok &= np.maximum.reduce([abs(zl - z), abs(zr - z), abs(zu - z), abs(zd - z)]) \
        <= MAX_RELATIVE_STEP * np.maximum(z, 1e-9)

    def back(uu, vv, zz):
        return np.stack([(uu - cx) / fx * zz, (vv - cy) / fy * zz, zz])

    # normals of the candidates only, points of the chosen only (column by column as one)
    idx = np.flatnonzero(ok)
    u, v, z, zl, zr, zu, zd = (a[idx] for a in (u, v, z, zl, zr, zu, zd))
    du = back(u + 1, v, zr) - back(u - 1, v, zl)
    dv = back(u, v + 1, zd) - back(u, v - 1, zu)
    n = np.cross(du, dv, axis=0)
    norm = np.linalg.norm(n, axis=0)
    keep = np.flatnonzero(norm > 0)
    if keep.size > count:
        # (the draw picks positions: the same ones whether among keep or idx[keep])
        keep = np.sort(np.random.default_rng(seed).choice(keep, count, replace=False))
    n = n[:, keep] / np.maximum(norm[keep], 1e-12)
    n = np.where(n[2] > 0, -n, n)  # facing the camera
    p = back(u[keep], v[keep], z[keep])
    pts = np.zeros((3, count), np.float32)
    normals = np.zeros((3, count), np.float32)
    pts[2] = 1.0
    pts[:, :keep.size], normals[:, :keep.size] = p, n
    return pts, normals


def depth_agreement(previous: np.ndarray, depth: np.ndarray, T_cur_prev: np.ndarray,
                    intr: Intrinsics, *, tol_m: float, min_depth: float, max_depth: float,
                    seed: int) -> float | None:
    """The share of the previous frame's depth points (``AGREEMENT_POINTS`` drawn with their
    normals by ``depth_points``, ``seed``) that the frame's depth map (H, W, metres) puts on
    their plane at the relative pose ``T_cur_prev`` (4, 4; p_cur = T p_prev): within
    ``tol_m`` (x (z / ``AGREEMENT_NOMINAL_Z``)^2 beyond that depth) of it, among the points
    judged: in view, with depth there, and not ``OCCLUDED`` tolerances or more behind the
    surface seen (occluded points say nothing). None when fewer than
    ``AGREEMENT_MIN_JUDGED`` are judged. A second opinion on a solve that the distance field
    cannot give: two depth images, no edge in it."""
    pts, normals = depth_points(previous, intr, AGREEMENT_POINTS, min_depth=min_depth,
                                max_depth=max_depth, seed=seed)
    T = np.asarray(T_cur_prev, np.float64)
    valid = np.sum(normals * normals, axis=0) > 0
    q = T[:3, :3] @ pts[:, valid] + T[:3, 3:4]
    n = T[:3, :3] @ normals[:, valid]
    fx, fy, cx, cy = (float(v) for v in intr)
    h, w = depth.shape
    z = q[2]
    zs = np.where(z > 1e-6, z, 1.0)
    ui, vi = np.round(fx * q[0] / zs + cx), np.round(fy * q[1] / zs + cy)
    inside = (z > 1e-6) & (ui >= 0) & (ui <= w - 1) & (vi >= 0) & (vi <= h - 1)
    ui, vi, q, n = ui[inside].astype(int), vi[inside].astype(int), q[:, inside], n[:, inside]
    d = np.asarray(depth, np.float64)[vi, ui]
    d = np.where(np.isfinite(d) & (d >= min_depth) & (d <= max_depth), d, 0.0)
    p_c = np.stack([(ui - cx) / fx * d, (vi - cy) / fy * d, d])
    tol = tol_m * np.maximum(1.0, (d / AGREEMENT_NOMINAL_Z) ** 2)
    judged = (d > 0) & (q[2] - d <= OCCLUDED * tol)
    if int(judged.sum()) < AGREEMENT_MIN_JUDGED:
        return None
    r = np.abs(np.sum(n * (q - p_c), axis=0))
    return float(np.mean(r[judged] <= tol[judged]))


def depth_valid(normals: jnp.ndarray) -> jnp.ndarray:
    """(M,) which depth point slots hold a point (padding has a zero normal)."""
    return jnp.sum(normals * normals, axis=0) > 0


def point_to_plane(T: Pose, pts: jnp.ndarray, normals: jnp.ndarray, depth: jnp.ndarray,
                   intr: Intrinsics, level: int
                   ) -> tuple[jnp.ndarray, jnp.ndarray, jnp.ndarray]:
    """Residuals r (M,) in pixels of ``level``, their Jacobians (6, M) and validity (M,) of
    the keyframe depth points (3, M) with normals (3, M) against the frame's depth map
    (H, W, metres, 0 = missing) at pose T = T_cur_kf; intr of level 0."""
    q = T.apply(pts)
    n = T.R @ normals
    z = q[2]
    zs = jnp.where(z > 1e-6, z, 1.0)
    u = intr.fx * q[0] / zs + intr.cx
    v = intr.fy * q[1] / zs + intr.cy
    h, w = depth.shape
    inside = (z > 1e-6) & (u >= 0) & (u <= w - 1) & (v >= 0) & (v <= h - 1)
    ui = jnp.clip(jnp.round(u), 0, w - 1).astype(jnp.int32)
    vi = jnp.clip(jnp.round(v), 0, h - 1).astype(jnp.int32)
    d = depth[vi, ui]
    p_c = jnp.stack([(ui - intr.cx) / intr.fx * d, (vi - intr.cy) / intr.fy * d, d])
    scale = jnp.sqrt(intr.fx * intr.fy) * 0.5**level / zs
    r = scale * jnp.sum(n * (q - p_c), axis=0)
    J = scale * jnp.concatenate([n, jnp.cross(q, n, axis=0)], axis=0)
    ok = inside & (d > 0) & depth_valid(normals)
    return jnp.where(ok, r, 0.0), jnp.where(ok, J, 0.0), ok
