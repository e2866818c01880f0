"""Checks of what a user hands the trackers: frames and rigid transforms, refused with an
error naming the problem before any JAX code runs."""

from __future__ import annotations

import numpy as np

from ..geometry import orthonormalise_np

#: largest |R^T R - I| and |last row - [0, 0, 0, 1]| of a matrix taken as a rigid transform
#: (a float32 rotation is orthonormal to ~1e-7; an IMU's integrated one to ~1e-6)
RIGID_TOL = 1e-4


def rigid_transform(value, *, name: str) -> np.ndarray:
    """``value`` as a (4, 4) float64 rigid transform (rotation re-orthonormalised); ValueError
    naming ``name`` when it is not one: another shape, a non-finite entry, a rotation block
    that is no rotation (|R^T R - I| or its determinant's distance from 1 over ``RIGID_TOL``)
    or a last row other than [0, 0, 0, 1]."""
    T = np.asarray(value, np.float64) if value is not None else None
    if T is None or T.shape != (4, 4):
        shape = None if T is None else T.shape
        raise ValueError(f"{name} must be a 4x4 rigid transform, got shape {shape}")
    if not np.all(np.isfinite(T)):
        raise ValueError(f"{name} has non-finite entries (NaN or inf): {T.tolist()}")
    R = T[:3, :3]
    err = max(float(np.max(np.abs(R.T @ R - np.eye(3)))), abs(float(np.linalg.det(R)) - 1.0))
    if err > RIGID_TOL:
        raise ValueError(f"{name} is not rigid: its rotation block is off a rotation by "
                         f"{err:.2g} (R^T R = I, det R = 1 within {RIGID_TOL:g})")
    if float(np.max(np.abs(T[3] - [0.0, 0.0, 0.0, 1.0]))) > RIGID_TOL:
        raise ValueError(f"{name} is not rigid: its last row is {T[3].tolist()}, not "
                         "[0, 0, 0, 1]")
    return orthonormalise_np(T)


def check_frame(rgb, depth, timestamp, shape: tuple[int, int] | None) -> tuple[int, int]:
    """Clear errors for frames the pipeline cannot take (``Odometry.track``): rgb uint8
    (H, W, 3) or (H, W), depth float metres (H, W) of the same size and of the size ``shape``
    of the earlier frames (None: the first), a finite timestamp. Returns the frame's (H, W)."""
    rgb, depth = np.asarray(rgb), np.asarray(depth)
    if rgb.dtype != np.uint8 or not (rgb.ndim == 2 or (rgb.ndim == 3 and rgb.shape[2] == 3)):
        raise ValueError(f"rgb must be uint8 (H, W, 3) or (H, W), got {rgb.dtype} "
                         f"{rgb.shape}")
    if depth.ndim != 2 or depth.dtype.kind != "f":
        hint = " (raw TUM depth PNGs: divide by 5000 for metres)" \
            if depth.dtype.kind in "ui" else ""
        raise ValueError(f"depth must be float metres (H, W), got {depth.dtype} "
                         f"{depth.shape}{hint}")
    if depth.shape != rgb.shape[:2]:
        raise ValueError(f"rgb is {rgb.shape[1]}x{rgb.shape[0]} but depth is "
                         f"{depth.shape[1]}x{depth.shape[0]} (width x height)")
    if shape is not None and depth.shape != shape:
        raise ValueError(f"frame is {depth.shape[1]}x{depth.shape[0]}, earlier frames were "
                         f"{shape[1]}x{shape[0]} (width x height)")
    if not np.isfinite(float(timestamp)):
        raise ValueError(f"timestamp must be finite, got {timestamp}")
    return depth.shape


def increasing(timestamp, last: float | None) -> float:
    """``timestamp`` as a float; ValueError when it does not increase after ``last``."""
    timestamp = float(timestamp)
    if last is not None and timestamp <= last:
        raise ValueError(f"timestamp {timestamp:.6f} does not increase (last was {last:.6f})")
    return timestamp
