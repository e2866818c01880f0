"""Other RGB-D odometry methods, run frame to frame beside edgevo for comparison (the
benchmarks' peers).

- ``cv2_rgb``, ``cv2_depth``, ``cv2_rgbd``: OpenCV 5 ``cv2.Odometry`` with
  ``OdometryType_RGB`` / ``_DEPTH`` / ``_RGB_DEPTH`` (``OdometryAlgoType_COMMON``, default
  settings plus the sequence's camera matrix): one ``cv2.OdometryFrame`` (float32 depth in
  metres and, except for DEPTH, the gray image) per frame, then
  ``prepareFrames(previous, current)`` and ``compute(previous, current)``.
- ``o3d_color``, ``o3d_hybrid``: Open3D ``o3d.pipelines.odometry.compute_rgbd_odometry`` with
  ``RGBDOdometryJacobianFromColorTerm`` / ``...FromHybridTerm``, identity initial guess,
  default ``OdometryOption``; images from ``RGBDImage.create_from_color_and_depth(
  depth_scale=1.0, depth_trunc=4.0, convert_rgb_to_intensity=True)`` on depth in metres.

Both return Rt with ``Rt * p_src = p_dst`` (the pose of the source frame seen from the target
frame, T_dst_src; checked against ground truth on fr3_teddy frames 20 -> 25).
:func:`track_peer` chains them from a first pose, ``T_world_k = T_world_(k-1) @ inv(Rt_k)``;
a pair whose ``compute`` returns false, raises, or gives a non-finite matrix is a lost frame
and reuses the previous motion (constant velocity; identity before any success). The peers'
libraries are imported when a peer is made: a missing one is :class:`PeerMissing`.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import Any, Protocol

import numpy as np

__all__ = ["PEERS", "Cv2Odometry", "Open3dOdometry", "PeerMissing", "PeerTrack",
           "PeerTracker", "camera_matrix", "make_peer", "track_peer"]

PEERS = ("cv2_rgb", "cv2_depth", "cv2_rgbd", "o3d_color", "o3d_hybrid")
O3D_DEPTH_TRUNC_M = 4.0  # = OdometryOption().depth_max
MAX_FAILURES = 5  # failure messages a track keeps

Pose = np.ndarray  # (4, 4) float64


class PeerMissing(Exception):
    """The peer cannot run here (library absent or too old, unknown name)."""


class PeerTracker(Protocol):
    """A frame-to-frame odometry peer."""

    description: str

    def step(self, rgb: np.ndarray, depth: np.ndarray) -> Pose | None:
        """Feed the next frame (rgb uint8 RGB order, depth float32 metres). Returns Rt =
        T_current_previous, or None for the first frame or a failed pair."""
        ...


def camera_matrix(intrinsics: Sequence[float]) -> np.ndarray:
    """3x3 pinhole matrix from (fx, fy, cx, cy)."""
    fx, fy, cx, cy = (float(v) for v in intrinsics)
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


class Cv2Odometry:
    """OpenCV 5 ``cv2.Odometry``, frame to frame (``prepareFrames`` + ``compute``)."""

    MODES = {"cv2_rgb": "RGB", "cv2_depth": "DEPTH", "cv2_rgbd": "RGB_DEPTH"}

    def __init__(self, method: str, intrinsics: Sequence[float]) -> None:
        try:
            import cv2
        except ImportError as err:
            raise PeerMissing(f"cannot import cv2: {err}") from None
        missing = [n for n in ("Odometry", "OdometryFrame", "OdometrySettings")
                   if not hasattr(cv2, n)]
        if missing:
            raise PeerMissing(f"OpenCV {cv2.__version__} has no cv2.{', cv2.'.join(missing)} "
                              "(needs OpenCV 5)")
        self._cv2 = cv2
        mode = self.MODES[method]
        settings = cv2.OdometrySettings()
        settings.setCameraMatrix(camera_matrix(intrinsics).astype(np.float32))
        self._odo = cv2.Odometry(getattr(cv2, f"OdometryType_{mode}"), settings,
                                 cv2.OdometryAlgoType_COMMON)
        self._use_image = mode != "DEPTH"
        self._prev: tuple[Any, tuple[np.ndarray, ...]] | None = None
        self.description = (
            f"cv2.Odometry(cv2.OdometryType_{mode}, OdometrySettings(cameraMatrix=K), "
            "cv2.OdometryAlgoType_COMMON); frame = cv2.OdometryFrame(depth_m_float32"
            + (", gray_uint8" if self._use_image else "")
            + "); odo.prepareFrames(prev, cur); ok, Rt = odo.compute(prev, cur)"
        )

    def step(self, rgb: np.ndarray, depth: np.ndarray) -> Pose | None:
        """See :class:`PeerTracker`."""
        cv2 = self._cv2
        depth = np.ascontiguousarray(depth, np.float32)
        if self._use_image:
            gray = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
            frame, keep = cv2.OdometryFrame(depth, gray), (depth, gray)
        else:
            frame, keep = cv2.OdometryFrame(depth), (depth,)
        # the frame with the arrays it may point into, kept alive as long as the frame
        prev, self._prev = self._prev, (frame, keep)
        if prev is None:
            return None
        self._odo.prepareFrames(prev[0], frame)
        ok, rt = self._odo.compute(prev[0], frame)
        return np.asarray(rt, np.float64) if ok else None


class Open3dOdometry:
    """Open3D ``compute_rgbd_odometry`` (colour or hybrid term), frame to frame."""

    def __init__(self, method: str, intrinsics: Sequence[float], width: int, height: int) -> None:
        try:
            import open3d as o3d
        except (ImportError, OSError) as err:  # OSError: a missing system library
            raise PeerMissing(f"cannot import open3d: {err}") from None
        self._o3d = o3d
        odometry = o3d.pipelines.odometry
        term = "Color" if method == "o3d_color" else "Hybrid"
        self._jacobian = getattr(odometry, f"RGBDOdometryJacobianFrom{term}Term")()
        self._option = odometry.OdometryOption()
        fx, fy, cx, cy = (float(v) for v in intrinsics)
        self._intrinsic = o3d.camera.PinholeCameraIntrinsic(width, height, fx, fy, cx, cy)
        self._prev: Any = None
        self.description = (
            "o3d.pipelines.odometry.compute_rgbd_odometry(prev, cur, PinholeCameraIntrinsic, "
            f"np.eye(4), RGBDOdometryJacobianFrom{term}Term(), OdometryOption()); "
            "o3d.geometry.RGBDImage.create_from_color_and_depth(Image(rgb), Image(depth_m), "
            f"depth_scale=1.0, depth_trunc={O3D_DEPTH_TRUNC_M}, convert_rgb_to_intensity=True)"
        )

    def step(self, rgb: np.ndarray, depth: np.ndarray) -> Pose | None:
        """See :class:`PeerTracker`."""
        o3d = self._o3d
        cur = o3d.geometry.RGBDImage.create_from_color_and_depth(
            o3d.geometry.Image(np.ascontiguousarray(rgb)),
            o3d.geometry.Image(np.ascontiguousarray(depth, np.float32)),
            depth_scale=1.0, depth_trunc=O3D_DEPTH_TRUNC_M, convert_rgb_to_intensity=True,
        )
        prev, self._prev = self._prev, cur
        if prev is None:
            return None
        ok, trans, _info = o3d.pipelines.odometry.compute_rgbd_odometry(
            prev, cur, self._intrinsic, np.eye(4), self._jacobian, self._option)
        return np.asarray(trans, np.float64) if ok else None


def make_peer(method: str, intrinsics: Sequence[float], width: int, height: int) -> PeerTracker:
    """The peer tracker called ``method``; PeerMissing if unknown or its library is absent."""
    if method in Cv2Odometry.MODES:
        return Cv2Odometry(method, intrinsics)
    if method in ("o3d_color", "o3d_hybrid"):
        return Open3dOdometry(method, intrinsics, width, height)
    raise PeerMissing(f"unknown method {method!r} (peers: {', '.join(PEERS)})")


class PeerTrack:
    """A peer's pass over a sequence: T_world_cam poses (N, 4, 4), per-frame times (ms) of
    the peer's work and of decoding, each frame's state (``"OK"``; ``"LOST"`` for a frame
    after the first whose pair failed), the lost frames (a failure at frame 0 included) and
    the first few failure messages; ``description``: the peer's calls."""

    def __init__(self, first_pose: Pose, description: str = "") -> None:
        self.poses: list[Pose] = [np.asarray(first_pose, np.float64)]
        self.frame_ms: list[float] = []
        self.decode_ms: list[float] = []
        self.states: list[str] = []
        self.lost = 0
        self.failures: list[str] = []
        self.description = description


def track_peer(peer: PeerTracker, seq: Any, n: int, first_pose: Pose) -> PeerTrack:
    """Feed frames 0..n-1 of ``seq`` (a source with ``decode_frame`` and ``rectify_frame``)
    to ``peer`` and chain its motions from ``first_pose``.

    Times each frame from ``decode_frame``'s arrays to the pose (``rectify_frame`` included).
    A pair that fails (None, non-finite, or an exception) is a lost frame and repeats the
    previous motion (identity before the first success)."""
    track = PeerTrack(first_pose, getattr(peer, "description", ""))
    motion = np.eye(4)  # T_previous_current
    for i in range(n):
        t0 = time.perf_counter()
        rgb_raw, depth_raw = seq.decode_frame(i)
        t1 = time.perf_counter()
        error = None
        try:
            rt = peer.step(*seq.rectify_frame(rgb_raw, depth_raw))
        except Exception as err:  # a failing peer call is a lost frame, not a crash
            rt, error = None, f"frame {i}: {type(err).__name__}: {err}"
        t2 = time.perf_counter()
        track.decode_ms.append((t1 - t0) * 1e3)
        track.frame_ms.append((t2 - t1) * 1e3)
        rt = None if rt is None else np.asarray(rt, np.float64)
        usable = rt is not None and rt.shape == (4, 4) and bool(np.all(np.isfinite(rt)))
        if usable:
            motion = np.linalg.inv(rt)
        elif i > 0 or error is not None:  # frame 0 has no pair: None is expected there
            track.lost += 1
            if len(track.failures) < MAX_FAILURES:
                track.failures.append(error or f"frame {i}: no motion (false or non-finite)")
        track.states.append("OK" if usable or i == 0 else "LOST")
        if i > 0:
            track.poses.append(track.poses[-1] @ motion)
    return track
