"""A live Intel RealSense camera as a ``Source``, through ``pyrealsense2``
(``pip install 'edgevo_jax[realsense]'``).

Colour (rgb8) and depth (z16) streams at the same size and rate; depth is aligned to the
colour camera (``rs.align``), whose intrinsics are the source's. Frames are read in order as
they arrive: ``decode_frame(i)`` waits for the next frameset and must be called with
i = 0, 1, 2, ... Timestamps are the frameset's (the device clock, in seconds).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..camera import Camera, Distortion, Intrinsics
from ..io import read_trajectory
from .base import UnknownCameraError
from .calibration import refuse_depth_fields, source_camera, undistort

#: frames of a live run when no count is given (stop earlier with Ctrl-C)
UNBOUNDED = 10**9


def _pyrealsense2() -> Any:
    try:
        import pyrealsense2
    except ImportError:
        raise ImportError("a live RealSense needs the pyrealsense2 package: "
                          "pip install 'edgevo_jax[realsense]'") from None
    return pyrealsense2


@dataclass(eq=False)
class RealSenseSource:
    """A started RealSense pipeline (use :func:`open_realsense`); a ``Source``."""

    rs: Any  # the pyrealsense2 module (or one with the same interface)
    pipeline: Any
    align: Any
    depth_scale: float  # metres per z16 unit
    name: str
    intrinsics: Intrinsics
    width: int
    height: int
    frames: int
    groundtruth: tuple[np.ndarray, np.ndarray] | None = None
    timestamps: list[float] = field(default_factory=list)
    distortion: Distortion | None = None  # a given camera's; the stream's must be none
    readout_s: float = 0.0  # the colour camera's rolling-shutter readout time (s)

    def __len__(self) -> int:
        return self.frames

    def decode_frame(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """The next frame (i must be the number of frames read so far): rgb uint8 (H, W, 3)
        and depth uint16 (H, W) in the camera's units, aligned to the colour image."""
        if i != len(self.timestamps):
            raise IndexError(f"a live camera is read in order: frame {i} asked, "
                             f"{len(self.timestamps)} read so far")
        frameset = self.align.process(self.pipeline.wait_for_frames())
        colour, depth = frameset.get_color_frame(), frameset.get_depth_frame()
        if not colour or not depth:
            raise ValueError(f"{self.name}: frame {i} lacks its "
                             f"{'colour' if not colour else 'depth'} image")
        rgb = np.array(colour.get_data(), np.uint8, copy=True)
        raw = np.array(depth.get_data(), np.uint16, copy=True)
        if rgb.shape[:2] != raw.shape or raw.shape != (self.height, self.width):
            raise ValueError(f"{self.name}: frame {i} is {rgb.shape[1]}x{rgb.shape[0]} colour "
                             f"and {raw.shape[1]}x{raw.shape[0]} depth, the stream "
                             f"{self.width}x{self.height}")
        t = float(frameset.get_timestamp()) * 1e-3
        if self.timestamps and t <= self.timestamps[-1]:
            t = self.timestamps[-1] + 1e-6  # a repeated device time: keep them increasing
        self.timestamps.append(t)
        return rgb, raw

    def rectify_frame(self, rgb: np.ndarray, raw: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Depth in float32 metres (0: no measurement); both undistorted when ``distortion``
        is set (a given camera's)."""
        rgb, raw = undistort(rgb, raw, self.intrinsics, self.distortion)
        return rgb, raw.astype(np.float32) * np.float32(self.depth_scale)

    def close(self) -> None:
        """Stop the camera."""
        self.pipeline.stop()


def open_realsense(
    *,
    serial: str | None = None,
    width: int = 640,
    height: int = 480,
    fps: int = 30,
    max_frames: int | None = None,
    camera: Camera | str | None = None,
    intrinsics: Intrinsics | None = None,
    groundtruth: str | os.PathLike[str] | None = None,
    rs: Any = None,
) -> RealSenseSource:
    """Start a RealSense camera (``serial``: that one; None: the first) streaming colour and
    depth at ``width`` x ``height`` and ``fps``. ``max_frames`` frames are tracked (None:
    until stopped). The camera is ``camera`` (a ``Camera`` or a preset name of
    ``camera.CAMERAS``) or ``intrinsics`` (a pinhole) when given, else the colour stream's
    calibration with readout 0; a colour stream with lens distortion is then refused
    (UnknownCameraError; the D400 colour streams report none). ``rs``: the pyrealsense2
    module (tests pass a replay)."""
    given = source_camera(camera=camera, intrinsics=intrinsics)
    refuse_depth_fields(given, "a RealSense camera")
    rs = _pyrealsense2() if rs is None else rs
    config = rs.config()
    if serial:
        config.enable_device(serial)
    config.enable_stream(rs.stream.color, width, height, rs.format.rgb8, fps)
    config.enable_stream(rs.stream.depth, width, height, rs.format.z16, fps)
    pipeline = rs.pipeline()
    try:
        profile = pipeline.start(config)
    except RuntimeError as err:
        raise ValueError(f"cannot start the RealSense camera{f' {serial}' if serial else ''} "
                         f"({width}x{height} at {fps} Hz): {err}") from None
    depth_scale = float(profile.get_device().first_depth_sensor().get_depth_scale())
    stream = profile.get_stream(rs.stream.color).as_video_stream_profile().get_intrinsics()
    if given is None:
        if any(abs(float(c)) > 0 for c in stream.coeffs):
            pipeline.stop()
            raise UnknownCameraError(f"the RealSense colour stream reports lens distortion "
                                     f"({stream.model}, {list(stream.coeffs)}), which is not "
                                     "removed")
        given = Camera(Intrinsics(float(stream.fx), float(stream.fy), float(stream.ppx),
                                  float(stream.ppy)))
    gt = read_trajectory(groundtruth) if groundtruth is not None else None
    return RealSenseSource(
        rs=rs, pipeline=pipeline, align=rs.align(rs.stream.color), depth_scale=depth_scale,
        name=f"realsense_{serial}" if serial else "realsense",
        intrinsics=given.intrinsics.validate(width=width, height=height), width=width,
        height=height, frames=UNBOUNDED if max_frames is None else int(max_frames),
        groundtruth=gt, distortion=given.distortion, readout_s=given.readout_s)
