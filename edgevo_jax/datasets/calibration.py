"""A source's camera: the one a reader is given (a ``Camera``, a preset name of
``camera.CAMERAS`` or pinhole intrinsics), read from a calibration file (ETH3D's
``calibration.txt``, OpenCV's distortion), or named by a folder or bag name (the TUM
benchmark's Freiburg cameras); and frames undistorted onto its pinhole intrinsics. Shared by
the readers (``tum``, ``bag``, ``realsense``); host side: numpy + OpenCV."""

from __future__ import annotations

import functools
import os
import re
from pathlib import Path

import cv2
import numpy as np

from ..camera import (
    CAMERAS,
    Camera,
    Distortion,
    Intrinsics,
    camera_preset,
    undistortion_maps,
)
from ..camera_file import read_camera_toml
from .base import UnknownCameraError

__all__ = [
    "CALIBRATION",
    "camera_from_name",
    "read_calibration",
    "refuse_depth_fields",
    "source_camera",
    "undistort",
]

_CAMERA_RE = re.compile(r"freiburg([123])|(?<![a-z0-9])fr([123])(?![a-z0-9])")


CALIBRATION = "calibration.txt"


def read_calibration(path: str | os.PathLike[str]) -> Camera:
    """The camera of a calibration file: 4 numbers ``fx fy cx cy`` (ETH3D's
    ``calibration.txt``: undistorted images) or 9, ``fx fy cx cy k1 k2 p1 p2 k3`` (OpenCV's
    distortion of the raw images), on one line or several, separated by spaces or commas;
    blank lines and '#' comments are skipped. The readout is 0 (a global shutter: set
    ``Config.readout_s`` for a rolling one). A path ending in ``.toml`` is a camera file
    (``camera_file.read_camera_toml``, docs/camera_file.md: readout and depth fields too).
    FileNotFoundError, or ValueError naming the file and what is wrong with it."""
    p = Path(path)
    if p.suffix.lower() == ".toml":
        return read_camera_toml(p)
    if not p.is_file():
        raise FileNotFoundError(f"calibration file not found: {p}")
    fields = [v for ln in p.read_text(encoding="utf-8", errors="replace").splitlines()
              if ln.strip() and not ln.lstrip().startswith("#")
              for v in ln.replace(",", " ").split()]
    if len(fields) not in (4, 9):
        raise ValueError(f"{p}: expected 4 numbers (fx fy cx cy) or 9 (fx fy cx cy k1 k2 p1 p2 "
                         f"k3), got {len(fields)}: {' '.join(fields)[:80]!r}")
    try:
        values = [float(v) for v in fields]
    except ValueError:
        raise ValueError(f"{p}: 'fx fy cx cy [k1 k2 p1 p2 k3]' must be numbers, got "
                         f"{' '.join(fields)!r}") from None
    try:
        return Camera(Intrinsics(*values[:4]), tuple(values[4:]) or None).validate()
    except ValueError as err:
        raise ValueError(f"{p}: {err}") from None


def refuse_depth_fields(camera: Camera | None, source: str) -> None:
    """ValueError when ``camera`` sets a depth field (``Camera.depth_fields``) that the
    ``source`` (its kind, for the message) cannot apply; TUM folders apply them all."""
    fields = [] if camera is None else camera.depth_fields()
    if fields:
        raise ValueError(f"{source} cannot apply the camera's {', '.join(fields)}; only TUM "
                         "sequence folders apply depth_scale, depth_time_offset_s and "
                         "T_color_depth (leave them at 1, 0 and none here)")


def camera_from_name(name: str) -> Camera:
    """The TUM benchmark camera a folder (or bag) name names: ``freiburgN`` or ``frN`` picks
    preset ``frN`` of ``camera.CAMERAS``. UnknownCameraError if no (or more than one) camera
    is named."""
    found = {a or b for a, b in _CAMERA_RE.findall(name.lower())}
    if len(found) != 1:
        what = "no Freiburg camera" if not found else f"several cameras ({sorted(found)})"
        raise UnknownCameraError(
            f"cannot tell the camera from the name {name!r}: {what} named (expected "
            "'freiburg1/2/3' or 'fr1/2/3')")
    return CAMERAS[f"fr{found.pop()}"].camera


@functools.lru_cache(maxsize=8)
def _cached_maps(
    intr: Intrinsics, dist: Distortion, width: int, height: int
) -> tuple[np.ndarray, np.ndarray]:
    map1, map2 = undistortion_maps(intr, dist, width, height)
    map1.setflags(write=False)
    map2.setflags(write=False)
    return map1, map2


def undistort(rgb: np.ndarray, depth: np.ndarray, intr: Intrinsics,
              distortion: Distortion | None) -> tuple[np.ndarray, np.ndarray]:
    """rgb (bilinear) and depth (nearest neighbour: no depth values blended) remapped onto
    the pinhole ``intr`` from a camera with OpenCV ``distortion`` (None: as they are)."""
    if distortion is None:
        return rgb, depth
    h, w = depth.shape
    map1, map2 = _cached_maps(intr, tuple(distortion), w, h)
    return (cv2.remap(rgb, map1, map2, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                      borderValue=0),
            cv2.remap(depth, map1, map2, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT,
                      borderValue=0))


def source_camera(*, camera: Camera | str | None,
                  intrinsics: Intrinsics | None) -> Camera | None:
    """The camera a reader was given, checked: ``camera`` (a ``Camera`` or a preset name of
    ``camera.CAMERAS``), else ``intrinsics`` as a pinhole camera (no distortion, readout 0);
    None when neither is given. ValueError naming the argument: both given, an unknown
    preset, a bad value."""
    if camera is not None and intrinsics is not None:
        raise ValueError("pass camera= or intrinsics=, not both (a Camera holds intrinsics)")
    if camera is None and intrinsics is None:
        return None
    if isinstance(camera, str):
        cam = camera_preset(camera)
    elif camera is not None:
        if not isinstance(camera, Camera):
            raise ValueError(f"camera= must be a Camera or a preset name "
                             f"({', '.join(CAMERAS)}), got {type(camera).__name__}")
        cam = camera
    else:
        cam = Camera(intrinsics)  # type: ignore[arg-type]
    return cam.validate()
