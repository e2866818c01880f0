"""A run seen in rerun (``pip install 'edgevo_jax[rerun]'``): a recording file (``.rrd``)
and, where a display exists, the live viewer.

What a recording holds (timelines ``frame`` and ``time``, the source's seconds):

- ``world/camera``: the camera pose T_world_cam; under it a pinhole of the source's
  intrinsics with the current frame (JPEG) and its Canny edges (green points);
- ``world/estimate``: the camera path so far; ``world/groundtruth``: the ground-truth path
  of the source's time span (static), in the same world frame (the run starts at the
  ground-truth pose of its first frame);
- ``world/keyframes``: the keyframes' positions; ``keyframe/image``: the current keyframe's
  image with its selected edges (orange points);
- ``tracking/state`` (0 OK, 1 WEAK, 2 LOST), ``tracking/inliers``, ``tracking/ms``, and a
  text log line with the reason of every frame not OK and of every new keyframe.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ..datasets.source import Source
from ..io import poses7_to_matrices
from ..tracking.results import LOST, OK, WEAK, FrameResult

_STATE_CODE = {OK: 0, WEAK: 1, LOST: 2}
_EDGE_POINTS = 4000  # at most this many of a frame's edges are drawn (evenly spaced)


def _rerun() -> Any:
    try:
        import rerun
    except ImportError:
        raise ImportError("a rerun recording needs the rerun-sdk package: "
                          "pip install 'edgevo_jax[rerun]'") from None
    return rerun


def has_display() -> bool:
    """Whether a viewer window can open here (X11 or Wayland, or not Linux)."""
    import sys

    return not sys.platform.startswith("linux") or bool(
        os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


class RerunRecording:
    """Logs each frame of a run (``run_sequence(on_frame=recording)``) to ``path`` (.rrd)
    and/or a spawned viewer (``spawn``; ValueError without a display). Use as a context
    manager, or call ``close``."""

    def __init__(self, seq: Source, *, path: str | os.PathLike[str] | None = None,
                 spawn: bool = False, jpeg_quality: int = 85) -> None:
        if path is None and not spawn:
            raise ValueError("a rerun recording needs a file (path=) or a viewer (spawn=True)")
        if spawn and not has_display():
            raise ValueError("no display for the rerun viewer here: write a file instead "
                             "(--rerun FILE.rrd) and open it with `rerun FILE.rrd`")
        rr = self.rr = _rerun()
        self.rec = rr.RecordingStream("edgevo_jax", recording_id=seq.name)
        if path is not None:
            Path(path).parent.mkdir(parents=True, exist_ok=True)
            self.rec.save(os.fspath(path))
        if spawn:
            self.rec.spawn(connect=path is None)
        self.quality = int(jpeg_quality)
        self._path: list[np.ndarray] = []
        self._keyframes: list[np.ndarray] = []
        self._count = 0
        intr = seq.intrinsics
        K = np.array([[intr.fx, 0, intr.cx], [0, intr.fy, intr.cy], [0, 0, 1]], np.float32)
        self.rec.log("world/camera/image", rr.Pinhole(image_from_camera=K,
                                                      resolution=[seq.width, seq.height]),
                     static=True)
        self.rec.log("keyframe/image", rr.Pinhole(image_from_camera=K,
                                                  resolution=[seq.width, seq.height]),
                     static=True)
        if seq.groundtruth is not None and len(seq.timestamps):
            gt_t, gt_p = seq.groundtruth
            t = np.asarray(seq.timestamps)
            span = (gt_t >= t[0] - 0.05) & (gt_t <= t[-1] + 0.05)
            order = np.argsort(gt_t[span])
            xyz = poses7_to_matrices(gt_p[span][order])[:, :3, 3]
            if len(xyz) > 1:
                self.rec.log("world/groundtruth", rr.LineStrips3D([xyz], colors=[[120, 120, 120]]),
                             static=True)

    def __call__(self, result: FrameResult, rgb: np.ndarray, frame: Any, odometry: Any) -> None:
        """Log one concluded frame (the ``run_sequence`` ``on_frame`` hook)."""
        rr, rec = self.rr, self.rec
        rec.set_time("frame", sequence=self._count)
        rec.set_time("time", duration=float(result.timestamp))
        self._count += 1
        pose = np.asarray(result.pose, np.float64)
        rec.log("world/camera", rr.Transform3D(translation=pose[:3, 3], mat3x3=pose[:3, :3]))
        rec.log("world/camera/image/rgb", self._jpeg(rgb))
        uv = np.asarray(frame.edge_uv)
        step = max(1, len(uv) // _EDGE_POINTS)
        rec.log("world/camera/image/edges", rr.Points2D(uv[::step], colors=[[60, 220, 60]],
                                                         radii=1.0))
        self._path.append(pose[:3, 3])
        if len(self._path) < 1000 or self._count % 10 == 0:  # the whole path: keep it cheap
            rec.log("world/estimate", rr.LineStrips3D([np.asarray(self._path)],
                                                      colors=[[40, 120, 255]]))
        rec.log("tracking/state", rr.Scalars(_STATE_CODE.get(result.state, 2)))
        rec.log("tracking/inliers", rr.Scalars(result.inliers))
        rec.log("tracking/ms", rr.Scalars(result.total_ms))
        if result.state != OK:
            rec.log("tracking/log", rr.TextLog(f"{result.state}: {result.reason}",
                                               level="ERROR" if result.state == LOST else "WARN"))
        keyframe = odometry.keyframe if result.keyframe is not None else None
        if keyframe is not None:
            self._keyframes.append(pose[:3, 3])
            rec.log("world/keyframes", rr.Points3D(np.asarray(self._keyframes),
                                                   colors=[[255, 150, 30]], radii=0.01))
            rec.log("keyframe/image/rgb", self._jpeg(rgb))
            rec.log("keyframe/image/edges", rr.Points2D(keyframe[2], colors=[[255, 150, 30]],
                                                        radii=1.5))
            rec.log("tracking/log", rr.TextLog(f"keyframe ({result.keyframe})", level="INFO"))

    def _jpeg(self, rgb: np.ndarray) -> Any:
        ok, buf = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR),
                               [cv2.IMWRITE_JPEG_QUALITY, self.quality])
        if not ok:
            raise ValueError("cannot encode the frame as JPEG for rerun")
        return self.rr.EncodedImage(contents=buf.tobytes(), media_type="image/jpeg")

    def close(self) -> None:
        """Write out everything logged (the .rrd file is whole after this)."""
        self.rec.flush()
        self.rec.disconnect()

    def __enter__(self) -> RerunRecording:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
