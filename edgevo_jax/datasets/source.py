"""What the pipeline reads: a ``Source`` of timestamped rgb and metric depth frames with the
camera's intrinsics and, optionally, ground truth; and ``open_source``, which picks the
reader for a path (a TUM or ETH3D folder, a ROS1 or ROS2 bag, a live RealSense).

This module sits above the readers (it imports them, none imports it); what they share
(``Source``, ``SourceError``, ``UnknownCameraError``, the topic names, ``camera_readout``)
lives below them in ``base`` and is importable from here as well."""

from __future__ import annotations

import os
from pathlib import Path

from ..camera import Camera, Intrinsics
from .base import (
    DEPTH_TOPIC,
    INFO_TOPIC,
    REALSENSE,
    RGB_TOPIC,
    Source,
    SourceError,
    UnknownCameraError,
    camera_readout,
    depth_lags,
)

__all__ = [
    "DEPTH_TOPIC",
    "INFO_TOPIC",
    "REALSENSE",
    "RGB_TOPIC",
    "Source",
    "SourceError",
    "UnknownCameraError",
    "camera_readout",
    "depth_lags",
    "is_bag",
    "open_source",
]


def is_bag(path: str | os.PathLike[str]) -> bool:
    """A ROS1 bag file (``.bag``), a ROS2 bag folder (``metadata.yaml``) or a ROS2 storage
    file (``.db3``, ``.mcap``)."""
    p = Path(path)
    if p.is_dir():
        return (p / "metadata.yaml").is_file()
    return p.suffix in (".bag", ".db3", ".mcap")


def open_source(
    path: str | os.PathLike[str],
    *,
    camera: Camera | str | None = None,
    intrinsics: Intrinsics | None = None,
    depth_factor: float = 5000.0,
    frame_step: int = 1,
    rgb_topic: str = RGB_TOPIC,
    depth_topic: str = DEPTH_TOPIC,
    info_topic: str = INFO_TOPIC,
    groundtruth: str | os.PathLike[str] | None = None,
    max_frames: int | None = None,
) -> Source:
    """The reader for ``path``: a ROS bag (``is_bag``: ``bag.load_bag`` with the topics), the
    string ``realsense`` or ``realsense:SERIAL`` (``realsense.open_realsense``; ``max_frames``
    frames, None: until stopped), else a TUM or ETH3D folder (``tum.load_sequence``).
    The camera: ``camera`` (a ``Camera`` or a preset name of ``camera.CAMERAS``) or
    ``intrinsics`` (a pinhole) when given, else the source's own (a folder's calibration.txt
    or name, a bag's camera_info, a RealSense's calibration; ``UnknownCameraError`` when it
    has none). ``groundtruth``: a TUM trajectory file for bags and cameras (folders read
    their own)."""
    text = os.fspath(path)
    if text == REALSENSE or text.startswith(REALSENSE + ":"):
        from .realsense import open_realsense

        serial = text.partition(":")[2] or None
        return open_realsense(serial=serial, max_frames=max_frames, camera=camera,
                              intrinsics=intrinsics, groundtruth=groundtruth)
    if is_bag(path):
        from .bag import load_bag

        return load_bag(path, rgb_topic=rgb_topic, depth_topic=depth_topic,
                        info_topic=info_topic, camera=camera, intrinsics=intrinsics,
                        groundtruth=groundtruth, frame_step=frame_step)
    from .tum import load_sequence

    if groundtruth is not None:
        raise SourceError(f"{path}: a folder reads its own groundtruth.txt",
                          api="pass groundtruth= for bags and cameras only",
                          cli="pass --groundtruth for bags and cameras only")
    return load_sequence(path, camera=camera, intrinsics=intrinsics, depth_factor=depth_factor,
                         frame_step=frame_step)
