"""Rolling shutter: the camera moves while an image is read out, row after row.

A rolling-shutter camera (the Kinect and most consumer RGB-D colour cameras) reads its rows
from top to bottom over a readout time tau; a row d rows below the middle one is seen
tau d / H later (H rows) by a camera that has moved on. Under rotation each image is sheared
by its own angular velocity, and two images taken at different velocities no longer align
rigidly: an alignment that ignores it turns the shear into a wrong pose (docs/decisions.md,
issue 29: slow frames tracked against keyframes made at speed).

The pose of a frame is that of its middle row. The velocity is the frame's motion from the
previous frame (the tracker knows no better), so the camera moves per row by

    twist_row = rate log(T_prev_cur),    rate = tau / (H dt)    (level-0 rows; ``Shutter``)

- a keyframe's edges are moved, once, to the time of its middle row (``unroll_edges``,
  host): P = exp(d twist_row) P_d;
- a frame being solved sees a keyframe point P' = T P, landing d rows from the middle, as
  P'' = exp(-d twist_row) P' (``shutter_warp``), its twist read from the pose being solved
  (``row_motion``).
First order in d |twist_row| (under 0.02 rad at 75 deg/s with a 30 ms readout). tau = 0 is
a global shutter.
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

from ..camera import Intrinsics, project
from ..geometry import Pose


class Shutter(NamedTuple):
    """The rolling shutter of a frame being solved (a pytree): ``prev`` (4, 4), the previous
    frame's pose relative to the keyframe, T_prev_kf, and ``rate`` (), the readout time of
    one level-0 row over the time since the previous frame, tau / (H dt) (0: a global
    shutter)."""

    prev: jnp.ndarray
    rate: jnp.ndarray


class RowMotion(NamedTuple):
    """The camera's motion per row of a frame at one pyramid level: ``twist`` (6,) [v, w]
    per row of the level; ``ref`` (), the level's middle row (the frame pose's time);
    ``rate`` (), d twist / d pose (see ``shutter_warp``)."""

    twist: jnp.ndarray
    ref: jnp.ndarray
    rate: jnp.ndarray


def shutter_rate(readout_s: float, height: int, dt: float) -> float:
    """``Shutter.rate`` of a frame ``dt`` seconds after the previous one, for a camera reading
    ``height`` rows in ``readout_s`` seconds (dt floored at 1 ms)."""
    return readout_s / (height * max(dt, 1e-3))


def row_motion(T: Pose, shutter: Shutter, level: int, height: int) -> RowMotion:
    """The per-row motion of a frame at pose T = T_cur_kf, at pyramid level ``level`` of
    ``height`` rows: log(T_prev_kf T^-1) = log(T_prev_cur) times the rate per row of the
    level, about its middle row."""
    rate = shutter.rate * (2.0**level)
    motion = Pose.from_matrix(shutter.prev, orthonormalise=None) @ T.inverse()
    return RowMotion(twist=motion.log() * rate,
                     ref=jnp.asarray(0.5 * (height - 1), rate.dtype), rate=rate)


def shutter_warp(
    intr: Intrinsics, T_c_k: Pose, pts_k: jnp.ndarray, rows: RowMotion
) -> tuple[jnp.ndarray, jnp.ndarray, jnp.ndarray]:
    """Keyframe points (3, K) into a rolling-shutter frame (module doc): P' = T P lands
    d = v - ``rows.ref`` rows from the middle, where the camera had moved by exp(d twist):
    P'' = P' - d (w x P' + v), with v the row of P'' itself (one fixed-point round from the
    row of P': 0.2 px closer at 90 deg/s). Returns the pixels (2, K), P''
    (3, K) and each point's Jacobian scale 1 + d rate (K,): moving the pose by delta moves
    the frame's velocity, and so the row's pose, by -rate delta too (left out: the row's own
    move with the pose, a term of relative size f |twist| per row, ~3 % at 90 deg/s)."""
    pts = T_c_k.apply(pts_k)
    v, w = rows.twist[:3], rows.twist[3:]
    moved = jnp.stack([w[1] * pts[2] - w[2] * pts[1] + v[0],
                       w[2] * pts[0] - w[0] * pts[2] + v[1],
                       w[0] * pts[1] - w[1] * pts[0] + v[2]])
    d = _row(intr, pts) - rows.ref
    d = _row(intr, pts - d * moved) - rows.ref  # the row it lands on, once more
    out = pts - d * moved
    return project(intr, out), out, 1.0 + d * rows.rate


def _row(intr: Intrinsics, pts: jnp.ndarray) -> jnp.ndarray:
    """The image row (K,) of points (3, K) (0 behind the camera: masked by the callers)."""
    return intr.fy * pts[1] / jnp.where(pts[2] > 1e-6, pts[2], 1.0) + intr.cy


def _edge_points(edges, intr: Intrinsics):
    """A keyframe's edges (``selection.KeyframeEdges`` of numpy arrays) as float64 pixels
    (2, K), inverse depths (K,), validity (K,) and points (3, K) in its camera (invalid
    slots at depth 1)."""
    uv = np.asarray(edges.uv, np.float64)
    rho = np.asarray(edges.rho, np.float64)
    valid = np.asarray(edges.valid)
    z = 1.0 / np.where(valid, rho, 1.0)
    P = np.stack([(uv[0] - intr.cx) / intr.fx * z, (uv[1] - intr.cy) / intr.fy * z, z])
    return uv, rho, valid, P


def depths_at_colour_time(edges, velocity: np.ndarray, lag_s: float, intr: Intrinsics):
    """A keyframe's edges (``selection.KeyframeEdges`` of numpy arrays) whose depths come from
    a depth image taken ``lag_s`` seconds after the colour image (its middle row), moved to
    the colour image's time by the camera's ``velocity`` (6,) [v, w] per second (body
    twist): an edge keeps its pixel (a smooth surface: the depth camera's pixel for it is
    near) and takes the depth of P + lag_s (w x P + v), P its point as read (first order;
    ``learn.camera``'s model of the depth time offset). Returns the edges with new rho
    (valid slots whose depth stays positive; the rest as they were)."""
    _, rho, valid, P = _edge_points(edges, intr)
    v, w = np.asarray(velocity[:3], np.float64), np.asarray(velocity[3:], np.float64)
    z_new = (P + lag_s * (np.cross(w[:, None], P, axis=0) + v[:, None]))[2]
    ok = valid & (z_new > 1e-6)
    return edges._replace(rho=np.where(ok, 1.0 / np.where(ok, z_new, 1.0), rho).astype(np.float32))


def unroll_edges(edges, twist: np.ndarray, intr: Intrinsics, height: int):
    """A keyframe's edges (``selection.KeyframeEdges`` of numpy arrays) as the camera at the
    time of its middle row sees them: an edge d rows below it was seen by the camera moved
    by exp(d twist) (``twist`` (6,) [v, w] per level-0 row), so its point is
    P = exp(d twist) P_d ~ P_d + d (w x P_d + v). Returns the edges with new uv and rho
    (valid slots whose point stays in front of the camera; the rest as they were)."""
    uv, rho, valid, P = _edge_points(edges, intr)
    d = uv[1] - 0.5 * (height - 1)
    v, w = np.asarray(twist[:3], np.float64), np.asarray(twist[3:], np.float64)
    P = P + d * (np.cross(w[:, None], P, axis=0) + v[:, None])
    ok = valid & (P[2] > 1e-6)
    zc = np.where(ok, P[2], 1.0)
    new_uv = np.stack([intr.fx * P[0] / zc + intr.cx, intr.fy * P[1] / zc + intr.cy])
    return edges._replace(uv=np.where(ok, new_uv, uv).astype(np.float32),
                          rho=np.where(ok, 1.0 / zc, rho).astype(np.float32))
