"""Pinhole camera with inverse-depth back-projection, and undistortion maps.

Conventions (DESIGN.md): pixels (u, v) = (column, row) with the origin at the centre of the
top-left pixel; rho = 1 / z. Device-side arrays of many points are struct-of-arrays, (3, K)
points and (2, K) pixels: XLA on CPU vectorises over the last axis.
"""

from __future__ import annotations

from typing import NamedTuple

import cv2
import jax.numpy as jnp
import numpy as np


class Intrinsics(NamedTuple):
    """Pinhole intrinsics in pixels (a JAX pytree, being a NamedTuple)."""

    fx: float
    fy: float
    cx: float
    cy: float

    def at_level(self, level: int) -> Intrinsics:
        """Intrinsics of pyramid level ``level`` (each level halves the image).

        With the pixel-centre origin, u_l = (u_0 + 0.5) / 2**l - 0.5.
        """
        s = 0.5**level
        return Intrinsics(
            self.fx * s, self.fy * s, (self.cx + 0.5) * s - 0.5, (self.cy + 0.5) * s - 0.5
        )

    def matrix(self) -> np.ndarray:
        """3x3 camera matrix K (numpy, float64)."""
        return np.array(
            [[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]], np.float64
        )

    def validate(self, *, width: int | None = None, height: int | None = None) -> Intrinsics:
        """Raise ValueError unless every value is finite and positive; with the image size,
        also unless the principal point lies inside the image. Returns self."""
        vals = np.asarray(self, np.float64)
        if not np.all(np.isfinite(vals)):
            raise ValueError(f"intrinsics must be finite, got {self}")
        if self.fx <= 0 or self.fy <= 0:
            raise ValueError(
                f"intrinsics: focal lengths must be positive, got fx={self.fx}, fy={self.fy}"
            )
        if self.cx <= 0 or self.cy <= 0:
            raise ValueError(
                f"intrinsics: principal point must be positive, got cx={self.cx}, cy={self.cy}"
            )
        if (width is not None and self.cx >= width) or (height is not None and self.cy >= height):
            raise ValueError(
                f"intrinsics: principal point (cx={self.cx}, cy={self.cy}) lies outside the "
                f"{width}x{height} image (given in the order FX FY CX CY?)"
            )
        return self


def unproject(intr: Intrinsics, uv: jnp.ndarray, rho: jnp.ndarray) -> jnp.ndarray:
    """Back-project pixels with inverse depth: pi^-1(p, rho) = ((u-cx)/fx, (v-cy)/fy, 1) / rho.

    uv: (2, K) pixels; rho: (K,) inverse depth in 1/m. Returns (3, K) points in metres.
    """
    z = 1.0 / rho
    return jnp.stack([(uv[0] - intr.cx) / intr.fx * z, (uv[1] - intr.cy) / intr.fy * z, z])


def project(intr: Intrinsics, pts: jnp.ndarray) -> jnp.ndarray:
    """Project camera-frame points (3, K) to pixels (2, K): (fx X/Z + cx, fy Y/Z + cy).

    Points at or behind the camera (Z <= 1e-6) give finite but meaningless pixels: callers
    mask them with ``pts[2] > 1e-6``.
    """
    iz = 1.0 / jnp.where(pts[2] > 1e-6, pts[2], 1.0)
    return jnp.stack([intr.fx * pts[0] * iz + intr.cx, intr.fy * pts[1] * iz + intr.cy])


def undistortion_maps(
    intr: Intrinsics, dist: tuple[float, ...], width: int, height: int
) -> tuple[np.ndarray, np.ndarray]:
    """cv2.remap maps that undistort a raw image onto the same pinhole intrinsics.

    dist: OpenCV order (k1, k2, p1, p2, k3). Use with INTER_LINEAR for colour and
    INTER_NEAREST for depth (depth must not be blended across discontinuities).
    """
    return cv2.initUndistortRectifyMap(
        intr.matrix(), np.asarray(dist, np.float64), None, intr.matrix(), (width, height),
        cv2.CV_32FC1,
    )
