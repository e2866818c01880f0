"""Pinhole camera with inverse-depth back-projection, undistortion maps, and the cameras a
source can have (``Camera``: pinhole, lens distortion, rolling shutter) with the one table of
presets (``CAMERAS``).

Conventions (docs/architecture.md): pixels (u, v) = (column, row), the origin at the centre of the
top-left pixel; rho = 1 / z. Device-side arrays of many points are struct-of-arrays, (3, K)
points and (2, K) pixels: XLA on CPU vectorises over the last axis.
"""

from __future__ import annotations

import math
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


Distortion = tuple[float, ...]
#: Lengths of an OpenCV distortion vector (k1 k2 p1 p2 [k3 [k4 k5 k6 [s1..s4 [tx ty]]]]).
DISTORTION_LENGTHS = (4, 5, 8, 12, 14)


class Camera(NamedTuple):
    """A source's colour camera (host side): ``intrinsics``, the pinhole of the images the
    tracker sees; ``distortion``, the raw images' lens distortion as OpenCV coefficients
    (k1 k2 p1 p2 [k3 ...]; None: the images are undistorted already), which the source
    removes (``undistortion_maps``) before tracking; ``readout_s``, the rolling shutter's
    readout time in seconds (0: a global shutter; ``Config.readout_s`` None takes it).

    And how its depth images relate to it: ``depth_scale``, the factor metric depth (the
    file's value / depth_factor) is multiplied by (true z = scale * z read);
    ``depth_time_offset_s``, seconds added to the depth timestamps before rgb and depth are
    associated (t_depth_true = t_depth_file + offset); ``T_color_depth``, the depth camera's
    pose in the colour camera (4x4 rigid, metres: p_color = T p_depth), the depth image being
    taken as seen by a camera with the colour camera's intrinsics and size at that pose (a
    residual pose of a nearly registered sensor); None: depth is registered to the colour
    camera already. The defaults (1, 0, None) apply nothing. Sources that cannot apply a
    non-default one refuse it (``depth_fields``). Equality with a ``T_color_depth`` set
    compares arrays: compare the fields instead.

    Device code takes the 4 numbers of ``intrinsics`` only (an ``Intrinsics`` pytree); the
    distortion and the depth fields never leave the host."""

    intrinsics: Intrinsics
    distortion: Distortion | None = None
    readout_s: float = 0.0
    depth_scale: float = 1.0
    depth_time_offset_s: float = 0.0
    T_color_depth: np.ndarray | None = None

    def validate(self, *, width: int | None = None, height: int | None = None) -> Camera:
        """The camera with float values, or ValueError: intrinsics as ``Intrinsics.validate``,
        distortion of 4, 5, 8, 12 or 14 finite coefficients, readout finite and >= 0, depth
        scale finite and > 0, depth time offset finite, ``T_color_depth`` None or a 4x4
        rigid transform (``checked_pose``; then a read-only float64 array)."""
        intr = Intrinsics(*(float(v) for v in self.intrinsics)).validate(width=width,
                                                                         height=height)
        dist = None
        if self.distortion is not None:
            dist = tuple(float(v) for v in self.distortion)
            if len(dist) not in DISTORTION_LENGTHS or not all(math.isfinite(v) for v in dist):
                raise ValueError("distortion must be 4, 5, 8, 12 or 14 finite OpenCV "
                                 f"coefficients (k1 k2 p1 p2 [k3 ...]), got {dist}")
        scale = float(self.depth_scale)
        if not (math.isfinite(scale) and scale > 0):
            raise ValueError(f"depth_scale must be finite and > 0 (true depth = scale * depth "
                             f"read), got {self.depth_scale}")
        offset = float(self.depth_time_offset_s)
        if not math.isfinite(offset):
            raise ValueError(f"depth_time_offset_s must be finite, got "
                             f"{self.depth_time_offset_s}")
        pose = self.T_color_depth
        if pose is not None:
            pose = checked_pose(pose, "T_color_depth")
            pose.setflags(write=False)
        return Camera(intr, dist, checked_readout(self.readout_s), scale, offset, pose)

    def depth_fields(self) -> list[str]:
        """The names of the depth fields that differ from their defaults (``depth_scale`` 1,
        ``depth_time_offset_s`` 0, ``T_color_depth`` None): what a source must apply."""
        return [name for name, off in (("depth_scale", self.depth_scale != 1.0),
                                       ("depth_time_offset_s", self.depth_time_offset_s != 0.0),
                                       ("T_color_depth", self.T_color_depth is not None))
                if off]


def checked_pose(T: np.ndarray, name: str) -> np.ndarray:
    """``T`` as a new float64 4x4 rigid transform, or ValueError naming ``name`` and what is
    wrong: not 4x4, not finite, a last row other than [0, 0, 0, 1], or a rotation block that
    is not orthonormal with determinant +1 (tolerance 1e-6)."""
    M = np.array(T, np.float64)
    if M.shape != (4, 4):
        raise ValueError(f"{name} must be a 4x4 matrix, got shape {M.shape}")
    if not np.all(np.isfinite(M)):
        raise ValueError(f"{name} must be finite, got {M.tolist()}")
    if not np.allclose(M[3], [0.0, 0.0, 0.0, 1.0], atol=1e-9):
        raise ValueError(f"{name}: the last row must be [0, 0, 0, 1], got {M[3].tolist()}")
    R = M[:3, :3]
    if not (np.allclose(R @ R.T, np.eye(3), atol=1e-6) and abs(np.linalg.det(R) - 1) < 1e-6):
        raise ValueError(f"{name}: the 3x3 block must be a rotation (orthonormal, det +1), "
                         f"got {R.tolist()}")
    return M


def checked_readout(readout_s: float) -> float:
    """``readout_s`` (a rolling shutter's readout time, s) as a float; ValueError unless it is
    finite and >= 0 (0: a global shutter)."""
    readout = float(readout_s)
    if not (math.isfinite(readout) and readout >= 0):
        raise ValueError(f"readout_s must be finite and >= 0 (0: a global shutter), got "
                         f"{readout_s}")
    return readout


#: Rolling-shutter readout time (s) of the TUM benchmark's colour cameras (Kinect-type sensors
#: reading their rows one after another): 20 ms, measured without ground truth on fr1 and fr3
#: clips (docs/decisions.md); ``edgevo calibrate`` estimates another camera's.
FREIBURG_READOUT_S = 0.020


class Preset(NamedTuple):
    """A named camera of ``CAMERAS``: the ``camera`` and what it is (``about``)."""

    camera: Camera
    about: str


#: The camera presets, by the name ``edgevo run --camera`` and ``load_sequence(camera=...)``
#: take. fr1 / fr2 / fr3: the TUM RGB-D benchmark's factory calibrations (the folder names
#: freiburg1/2/3 pick them too); fr3's images are undistorted already. kinect: the default
#: calibration TUM gives for its Kinect (https://cvg.cit.tum.de/data/datasets/rgbd-dataset/
#: file_formats, "ROS default": fx = fy = 525, cx = 319.5, cy = 239.5, no distortion) for a
#: Kinect-type camera without a calibration of its own; its readout is the Freiburg cameras'
#: 20 ms, as those are Kinect-type sensors of the same rolling-shutter design (set
#: ``Config.readout_s`` for another). ETH3D sequences bring their own calibration.txt.
CAMERAS: dict[str, Preset] = {
    "fr1": Preset(Camera(Intrinsics(517.3, 516.5, 318.6, 255.3),
                         (0.2624, -0.9531, -0.0054, 0.0026, 1.1633), FREIBURG_READOUT_S),
                  "TUM RGB-D freiburg1: its lens distortion and 20 ms rolling shutter"),
    "fr2": Preset(Camera(Intrinsics(520.9, 521.0, 325.1, 249.7),
                         (0.2312, -0.7849, -0.0033, -0.0001, 0.9172), FREIBURG_READOUT_S),
                  "TUM RGB-D freiburg2: its lens distortion and 20 ms rolling shutter"),
    "fr3": Preset(Camera(Intrinsics(535.4, 539.2, 320.1, 247.6), None, FREIBURG_READOUT_S),
                  "TUM RGB-D freiburg3: images undistorted already, 20 ms rolling shutter"),
    "kinect": Preset(Camera(Intrinsics(525.0, 525.0, 319.5, 239.5), None, FREIBURG_READOUT_S),
                     "a Kinect's default calibration (fx = fy = 525, cx = 319.5, cy = 239.5, "
                     "no distortion), 20 ms rolling shutter"),
}


def camera_preset(name: str) -> Camera:
    """The camera of preset ``name`` (a key of ``CAMERAS``); ValueError listing the presets
    for any other name."""
    if name not in CAMERAS:
        raise ValueError(f"camera={name!r} is not a preset; the presets are "
                         f"{', '.join(CAMERAS)} (or pass a Camera)")
    return CAMERAS[name].camera

