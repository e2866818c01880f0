"""TUM RGB-D benchmark sequences and ETH3D SLAM-style folders (host side: numpy + OpenCV).

Layout: ``rgb.txt``, ``depth.txt`` (``timestamp filename`` lines), ``rgb/``, ``depth/`` and an
optional ``groundtruth.txt`` (``timestamp tx ty tz qx qy qz qw``, T_world_cam). Depth PNGs are
16-bit with ``value / depth_factor`` metres (5000 in the benchmark) and 0 for no measurement.
Images are PNG (checked whole before tracking) or JPEG (likewise) or any format OpenCV reads.
ETH3D SLAM folders add ``calibration.txt`` (one line ``fx fy cx cy``, undistorted images);
any folder holding one takes its camera from it (``read_calibration``).
"""

from __future__ import annotations

import dataclasses
import math
import os
import warnings
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from ..camera import Camera, Distortion, Intrinsics
from ..depth_registration import register_depth
from ..io import read_trajectory
from ..metrics import associate_timestamps
from .calibration import (
    CALIBRATION,
    camera_from_name,
    read_calibration,
    source_camera,
    undistort,
)
from .images import check_files, describe, read_image

__all__ = [
    "EmptyDepthWarning",
    "TumSequence",
    "camera_from_name",
    "empty_depth_note",
    "load_sequence",
    "read_calibration",
    "read_file_list",
]

# The project's development clips (in ../shared/data/tum next to a checkout; not shipped).
SHARED_CLIPS = (
    "rgbd_dataset_freiburg3_teddy_first200",
    "rgbd_dataset_freiburg1_xyz_first10",
    "rgbd_dataset_freiburg1_desk_clip9",
)
SHARED_TUM = Path(__file__).resolve().parents[3] / "shared" / "data" / "tum"


class EmptyDepthWarning(UserWarning):
    """A depth image without a single measurement (all zero): the run goes on, the frame can
    be tracked against the keyframe but cannot become one."""


def read_file_list(path: str | os.PathLike[str]) -> tuple[np.ndarray, list[str]]:
    """Read a TUM list (``rgb.txt``/``depth.txt``): timestamps (N,) and the rest of each line.

    Skips blank lines and '#' comments; commas and tabs count as spaces (as ``associate.py``).
    Raises FileNotFoundError naming the file, ValueError naming ``path:line`` for a line without
    a finite timestamp and a filename, and ValueError if timestamps are not strictly increasing.
    """
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"file list not found: {p}")
    stamps: list[float] = []
    rest: list[str] = []
    linenos: list[int] = []
    with p.open("r", encoding="utf-8", errors="replace") as f:
        for lineno, raw in enumerate(f, start=1):
            line = raw.strip()
            if not line or line.startswith("#"):
                continue
            fields = line.replace(",", " ").replace("\t", " ").split()
            if len(fields) < 2:
                raise ValueError(f"{p}:{lineno}: expected 'timestamp filename', got {line!r}")
            try:
                t = float(fields[0])
            except ValueError as exc:
                raise ValueError(f"{p}:{lineno}: bad timestamp {fields[0]!r}") from exc
            if not math.isfinite(t):
                raise ValueError(f"{p}:{lineno}: non-finite timestamp {fields[0]!r}")
            if stamps and t <= stamps[-1]:
                raise ValueError(
                    f"{p}:{lineno}: timestamps must be strictly increasing, {fields[0]} follows "
                    f"{stamps[-1]:.6f} (line {linenos[-1]})"
                )
            stamps.append(t)
            rest.append(" ".join(fields[1:]))
            linenos.append(lineno)
    return np.asarray(stamps, np.float64), rest


def empty_depth_note(raw: np.ndarray, path: str | os.PathLike[str]) -> str | None:
    """A message when a depth image holds no measurement at all (every pixel 0 or NaN),
    else None."""
    valid = np.isfinite(raw) & (raw > 0) if raw.dtype.kind == "f" else raw != 0
    if np.any(valid):
        return None
    return (f"depth image {path} has no depth measurement (all zero): the frame can be "
            "tracked but cannot become a keyframe")


@dataclass(frozen=True, eq=False)
class TumSequence:
    """An associated TUM RGB-D sequence (use :func:`load_sequence`).

    ``timestamps`` are the rgb timestamps of the associated rgb/depth pairs,
    ``depth_timestamps`` their depth images' (depth.txt's plus ``depth_time_offset_s``: the
    times the association used); ``groundtruth`` is (timestamps, poses7) or None;
    ``readout_s`` the colour camera's rolling-shutter readout time (s, 0: a global shutter);
    ``depth_scale`` and ``T_color_depth`` the camera's (``camera.Camera``), applied by
    ``rectify_frame``. Equality is identity (fields hold arrays).
    """

    root: Path
    name: str
    intrinsics: Intrinsics
    distortion: Distortion | None
    depth_factor: float
    timestamps: np.ndarray
    rgb_files: tuple[Path, ...]
    depth_files: tuple[Path, ...]
    groundtruth: tuple[np.ndarray, np.ndarray] | None
    width: int
    height: int
    depth_timestamps: np.ndarray | None = None
    readout_s: float = 0.0
    depth_scale: float = 1.0
    depth_time_offset_s: float = 0.0
    T_color_depth: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.rgb_files)

    def load_frame(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """Frame i: rgb uint8 (H, W, 3) in RGB order and depth float32 metres (H, W), 0 = none.

        Undistorted onto the same pinhole intrinsics when ``distortion`` is set (rgb bilinear,
        depth nearest-neighbour so no depth values are blended).
        """
        return self.rectify_frame(*self.decode_frame(i))

    def decode_frame(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """Frame i as stored: rgb uint8 (H, W, 3) in RGB order and raw uint16 depth (H, W),
        checked (file present and readable, 16-bit single-channel depth, matching sizes).

        A depth image without any measurement (all zero) is not an error: it warns with
        :class:`EmptyDepthWarning` naming the file, and the frame is returned as it is.
        """
        n = len(self)
        if not -n <= i < n:
            raise IndexError(f"frame {i} out of range for {self.name} ({n} frames)")
        rgb_path, depth_path = self.rgb_files[i], self.depth_files[i]
        bgr = read_image(rgb_path, cv2.IMREAD_COLOR, "rgb")
        raw = read_image(depth_path, cv2.IMREAD_UNCHANGED, "depth")
        if raw.ndim != 2 or raw.dtype != np.uint16:
            raise ValueError(
                f"depth image {depth_path} must be single-channel 16-bit, got {describe(raw)}"
            )
        if bgr.shape[:2] != raw.shape:
            raise ValueError(
                f"rgb {rgb_path} is {bgr.shape[1]}x{bgr.shape[0]} but depth {depth_path} is "
                f"{raw.shape[1]}x{raw.shape[0]} (width x height)"
            )
        if raw.shape != (self.height, self.width):
            raise ValueError(
                f"frame {rgb_path} is {raw.shape[1]}x{raw.shape[0]}, the sequence is "
                f"{self.width}x{self.height} (width x height)"
            )
        note = empty_depth_note(raw, depth_path)
        if note is not None:
            warnings.warn(f"frame {i % n}: {note}", EmptyDepthWarning, stacklevel=2)
        return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), raw

    def rectify_frame(self, rgb: np.ndarray, raw: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Undistort a decoded frame (when ``distortion`` is set) and scale depth to metres:
        raw / ``depth_factor`` * ``depth_scale``, then, when ``T_color_depth`` is set,
        re-rendered into the colour camera (``register_depth``, the depth image taken to have
        the colour camera's intrinsics: pixels nothing lands on become 0)."""
        rgb, raw = undistort(rgb, raw, self.intrinsics, self.distortion)
        depth = raw.astype(np.float32) / np.float32(self.depth_factor)
        if self.depth_scale != 1.0:
            depth *= np.float32(self.depth_scale)
        if self.T_color_depth is not None:
            depth = register_depth(depth, self.intrinsics, self.intrinsics, self.T_color_depth)
        return rgb, depth


def subsequence(seq: TumSequence, start: int, stop: int, *, step: int = 1) -> TumSequence:
    """Frames ``start``, ``start + step``, ... below ``stop`` of ``seq`` (its associated pairs;
    clipped to its length) as a sequence of their own, with the same camera and ground truth
    (metrics associate by time). ``step`` strides over the associated pairs; to lower the
    frame rate as the benchmark's lists would, use ``load_sequence(..., frame_step=k)``,
    which keeps every k-th line of rgb.txt and depth.txt before associating them (where the
    lists have gaps, the two differ). Nothing is copied: the frames are read from the same
    files."""
    if step < 1:
        raise ValueError(f"step must be a positive integer, got {step}")
    n = len(seq)
    start, stop = max(0, min(start, n)), max(0, min(stop, n))
    if start >= stop:
        raise ValueError(f"no frames in {start}:{stop} of {seq.name} ({n} frames)")
    part = slice(start, stop, step)
    name = f"{seq.name}_frames{start}-{stop}" + (f"_every{step}" if step > 1 else "")
    return dataclasses.replace(
        seq, name=name, timestamps=seq.timestamps[part],
        rgb_files=seq.rgb_files[part], depth_files=seq.depth_files[part],
        depth_timestamps=None if seq.depth_timestamps is None else seq.depth_timestamps[part])


def load_sequence(
    path: str | os.PathLike[str],
    *,
    camera: Camera | str | None = None,
    intrinsics: Intrinsics | None = None,
    depth_factor: float = 5000.0,
    max_diff: float = 0.02,
    check_images: bool = True,
    frame_step: int = 1,
    readout_s: float | None = None,
) -> TumSequence:
    """Load a TUM RGB-D sequence folder, associating rgb and depth like ``associate.py``.

    ``frame_step`` k > 1 keeps every k-th line of rgb.txt and of depth.txt before they are
    associated (the sequence at 1/k of its frame rate, as the benchmark's lists would be
    recorded; where the lists have gaps, pairs that no longer associate are dropped, so the
    motion between tracked frames can span more than k frames). The name gets ``_everyk``.

    The camera (pinhole intrinsics, lens distortion removed from every frame, rolling-shutter
    readout) is ``camera`` when given: a ``Camera`` or the name of a preset of
    ``camera.CAMERAS`` ('fr1', 'fr2', 'fr3', 'kinect'); else ``intrinsics`` (a pinhole
    camera: no distortion, readout 0); else the folder's ``calibration.txt``
    (``read_calibration``; ETH3D's cameras have global shutters: readout 0); else the camera
    the folder name names (``camera_from_name``: freiburg1/2/3 or fr1/2/3), else
    UnknownCameraError (a ValueError). ``readout_s`` (s), when given, replaces the camera's
    readout. The camera's depth fields are applied: ``depth_time_offset_s`` is added to
    depth.txt's timestamps before they are associated with rgb.txt's, ``depth_scale`` and
    ``T_color_depth`` to every frame (``TumSequence.rectify_frame``). Ground truth is read
    when ``groundtruth.txt`` exists (None otherwise: runs go on without ATE).

    Everything that can be checked without tracking is checked here, so that a bad input stops
    the run before any JAX code: FileNotFoundError for a missing folder, list or image;
    ValueError (naming the file, and the line for text files) for an unparsable or unsorted
    list, a bad ground-truth line, non-finite or non-positive intrinsics, a principal point
    outside the image, when no rgb/depth pair associates within ``max_diff``, and for any image
    that is not a whole PNG or JPEG (truncated, not one), a depth image that is not 16-bit single
    channel or images of different sizes (``check_images=False`` skips the image checks
    except on the first frame, which is always decoded).
    """
    root = Path(path)
    _check_folder(root, depth_factor)
    name = Path(os.path.abspath(root)).name  # normalise '.'/'..' but keep symlink names
    cam, from_name = _folder_camera(root, name, camera, intrinsics, readout_s)
    if not (isinstance(frame_step, int) and frame_step >= 1):
        raise ValueError(f"frame_step must be a positive integer, got {frame_step!r}")
    if frame_step > 1:
        name = f"{name}_every{frame_step}"
    rgb_t, depth_t, rgb_files, depth_files = _associated(root, cam, frame_step, max_diff)
    groundtruth = _groundtruth(root)
    if check_images:
        check_files(rgb_files, depth_files)
    first = read_image(rgb_files[0], cv2.IMREAD_COLOR, "rgb")
    seq = TumSequence(
        root=root, name=name, intrinsics=cam.intrinsics, distortion=cam.distortion,
        depth_factor=float(depth_factor), timestamps=rgb_t, rgb_files=rgb_files,
        depth_files=depth_files, groundtruth=groundtruth, width=int(first.shape[1]),
        height=int(first.shape[0]), depth_timestamps=depth_t, readout_s=cam.readout_s,
        depth_scale=cam.depth_scale, depth_time_offset_s=cam.depth_time_offset_s,
        T_color_depth=cam.T_color_depth)
    _check_decoded(seq, cam, from_name)
    return seq


def _check_folder(root: Path, depth_factor: float) -> None:
    """FileNotFoundError unless ``root`` is a folder holding rgb.txt and depth.txt;
    ValueError unless ``depth_factor`` (raw depth units per metre) is positive and finite."""
    if not root.is_dir():
        raise FileNotFoundError(f"TUM sequence folder not found: {root}")
    for fname in ("rgb.txt", "depth.txt"):
        if not (root / fname).is_file():
            raise FileNotFoundError(
                f"file list not found: {root / fname} (a TUM sequence folder holds rgb.txt, "
                "depth.txt, rgb/ and depth/)"
            )
    if not (math.isfinite(depth_factor) and depth_factor > 0):
        raise ValueError(f"depth_factor must be positive and finite, got {depth_factor}")


def _folder_camera(root: Path, name: str, camera: Camera | str | None,
                   intrinsics: Intrinsics | None, readout_s: float | None
                   ) -> tuple[Camera, bool]:
    """The sequence's camera (``load_sequence``'s order: ``camera``, ``intrinsics``, the
    folder's calibration.txt, the folder ``name``), its readout (s) replaced by
    ``readout_s`` when given, and whether it came from the name."""
    cam = source_camera(camera=camera, intrinsics=intrinsics)
    from_name = cam is None and not (root / CALIBRATION).is_file()
    if from_name:
        cam = camera_from_name(name)
    elif cam is None:
        cam = read_calibration(root / CALIBRATION)
    if readout_s is not None:
        cam = cam._replace(readout_s=readout_s).validate()
    return cam, from_name


def _associated(root: Path, cam: Camera, frame_step: int, max_diff: float
                ) -> tuple[np.ndarray, np.ndarray, tuple[Path, ...], tuple[Path, ...]]:
    """The associated rgb/depth pairs of ``root``'s lists (every ``frame_step``-th line of
    each, depth times shifted by ``cam.depth_time_offset_s``, pairs within ``max_diff`` s):
    their rgb timestamps (N,) s, depth timestamps (N,) s, rgb and depth files. ValueError
    when no pair associates."""
    rgb_t, rgb_rel = read_file_list(root / "rgb.txt")
    depth_t, depth_rel = read_file_list(root / "depth.txt")
    if cam.depth_time_offset_s != 0.0:
        depth_t = depth_t + cam.depth_time_offset_s
    if frame_step > 1:
        rgb_t, rgb_rel = rgb_t[::frame_step], rgb_rel[::frame_step]
        depth_t, depth_rel = depth_t[::frame_step], depth_rel[::frame_step]
    pairs = associate_timestamps(rgb_t, depth_t, max_diff)
    if pairs.shape[0] == 0:
        raise ValueError(
            f"no rgb/depth pair of {root} associates within {max_diff} s "
            f"({rgb_t.size} rgb, {depth_t.size} depth timestamps)"
        )
    rgb_files = tuple(root / rgb_rel[i] for i in pairs[:, 0])
    depth_files = tuple(root / depth_rel[j] for j in pairs[:, 1])
    return rgb_t[pairs[:, 0]], depth_t[pairs[:, 1]], rgb_files, depth_files


def _groundtruth(root: Path) -> tuple[np.ndarray, np.ndarray] | None:
    """``root``'s groundtruth.txt as (timestamps (M,) s, poses7 (M, 7) T_world_cam), None
    when there is none; ValueError naming the bad line otherwise."""
    gt_path = root / "groundtruth.txt"
    if not gt_path.is_file():
        return None
    try:
        return read_trajectory(gt_path)
    except ValueError as err:
        raise ValueError(
            f"ground truth {err} (fix it, or remove {gt_path.name} to run without ATE)"
        ) from None


def _check_decoded(seq: TumSequence, cam: Camera, from_name: bool) -> None:
    """The checks that need the image size and the first frame: ``cam``'s intrinsics against
    the image's width and height (pixels) unless the camera came from the folder's name, and
    frame 0 decoded in full (ValueError / FileNotFoundError as ``decode_frame``)."""
    if not from_name:  # (a name's Freiburg camera fits the benchmark's 640x480)
        cam.intrinsics.validate(width=seq.width, height=seq.height)
    with warnings.catch_warnings():  # an empty first depth warns when the run decodes it
        warnings.simplefilter("ignore", EmptyDepthWarning)
        seq.decode_frame(0)  # decoded in full once: what the headers cannot tell
