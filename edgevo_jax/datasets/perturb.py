"""Copies of a TUM sequence folder with known camera errors injected: test and benchmark
tooling for camera calibration, whose estimate can then be compared with the truth.

Each injected value is the value of the ``Camera`` field (``camera.Camera``, the camera file
of docs/camera_file.md) that describes the copy: a calibration that recovers the truth from
the copy returns exactly the values passed here.

- ``depth_pose`` = ``T_color_depth``: the copy's depth images are what a depth camera at
  pose ``depth_pose`` in the colour camera's frame (p_color = T p_depth) sees, rendered from
  the source's registered depth with ``register_depth`` and T^-1 (pixels nothing lands on
  are 0).
- ``depth_scale`` = ``depth_scale``: the copy's depth values are the true depth divided by
  it (true depth = depth_scale * depth read).
- ``depth_time_offset_s`` = ``depth_time_offset_s``: depth.txt's timestamps are the true
  times minus it (t_depth_true = t_depth_file + offset), written to the microsecond.
- ``fx_factor``, ``fy_factor``: the copy's ``calibration.txt`` (which ``load_sequence``
  reads) states fx * fx_factor and fy * fy_factor; the true camera is returned and written
  to ``camera_true.toml``.

The source is taken as true: its depth registered to colour, scale 1, offset 0. Host side:
numpy + OpenCV.
"""

from __future__ import annotations

import math
import os
import shutil
from pathlib import Path

import cv2
import numpy as np

from ..camera import Camera, Intrinsics, checked_pose
from ..camera_file import write_camera_toml
from ..depth_registration import register_depth
from .calibration import CALIBRATION
from .images import read_image
from .tum import TumSequence, load_sequence, read_file_list

__all__ = ["TRUE_CAMERA", "perturbed_copy"]

#: The file of a perturbed copy holding its true camera (a camera file).
TRUE_CAMERA = "camera_true.toml"


def _place(src: Path, dst: Path, link: bool) -> None:
    dst.parent.mkdir(parents=True, exist_ok=True)
    if link:
        os.symlink(src.resolve(), dst)
    else:
        shutil.copy2(src, dst)


def _write_png(path: Path, image: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), image):
        raise OSError(f"cannot write {path}")


def perturbed_copy(
    src_dir: str | os.PathLike[str],
    dst_dir: str | os.PathLike[str],
    *,
    depth_pose: np.ndarray | None = None,
    depth_scale: float = 1.0,
    depth_time_offset_s: float = 0.0,
    fx_factor: float = 1.0,
    fy_factor: float = 1.0,
    camera: Camera | str | None = None,
    depth_factor: float = 5000.0,
    link: bool = True,
) -> Camera:
    """Write a TUM-style copy of the sequence folder ``src_dir`` to ``dst_dir`` (which must
    not exist) with the camera errors of the module's docstring injected, and return the
    copy's true camera (also written to ``dst_dir / TRUE_CAMERA``, with the injected values
    as its ``[source]``).

    The source's camera is ``camera`` or what ``load_sequence`` finds (calibration.txt, the
    folder name); it must have the default depth fields. Images that are not changed are
    symbolic links to the source's (``link``; False: copies); rgb.txt, groundtruth.txt and,
    without a time offset, depth.txt are copied as they are. Depth images are rewritten
    (16-bit PNG, ``depth_factor`` units) when ``depth_pose`` or ``depth_scale`` is given.
    With ``depth_pose`` and a lens distortion, the copy holds undistorted images (rgb
    rewritten too, as ``load_frame`` gives them) and its camera has no distortion. Raw
    depth values beyond 65535 after scaling are clipped. ValueError for a bad value (naming
    it), FileExistsError for an existing ``dst_dir``."""
    src, dst = Path(src_dir), Path(dst_dir)
    if dst.exists():
        raise FileExistsError(f"perturbed copy: {dst} exists already (give a new folder)")
    scale, offset = _checked_values(depth_scale, depth_time_offset_s, fx_factor, fy_factor)
    pose = None if depth_pose is None else checked_pose(depth_pose, "depth_pose")
    seq = load_sequence(src, camera=camera, depth_factor=depth_factor, check_images=False)
    if seq.depth_scale != 1.0 or seq.depth_time_offset_s != 0.0 or seq.T_color_depth is not None:
        raise ValueError("perturbed_copy: the source camera must have the default depth fields "
                         "(it is taken as the truth)")
    intr: Intrinsics = seq.intrinsics
    undistorted = pose is not None and seq.distortion is not None
    distortion = None if undistorted else seq.distortion
    truth = Camera(intr, distortion, seq.readout_s, scale, offset, pose).validate()

    dst.mkdir(parents=True)
    rgb_rel, depth_rel = _copy_lists(src, dst, offset)
    _write_rgb(seq, src, dst, rgb_rel, undistorted, link)
    _write_depth(seq, src, dst, depth_rel, pose, scale, depth_factor, link)
    _write_calibration(src, dst, intr, distortion, fx_factor, fy_factor)
    injected: dict[str, object] = {
        "perturbed_copy_of": str(src), "depth_scale": scale, "depth_time_offset_s": offset,
        "fx_factor": float(fx_factor), "fy_factor": float(fy_factor),
        "undistorted": undistorted}
    if pose is not None:
        injected["T_color_depth"] = [float(v) for v in pose.ravel()]
    write_camera_toml(dst / TRUE_CAMERA, truth, source=injected)
    return truth


def _checked_values(depth_scale: float, depth_time_offset_s: float, fx_factor: float,
                    fy_factor: float) -> tuple[float, float]:
    """The depth scale (> 0) and the depth time offset (s) as floats, the focal-length
    factors checked (> 0); ValueError naming the first bad value (all must be finite)."""
    scale, offset = float(depth_scale), float(depth_time_offset_s)
    if not (math.isfinite(scale) and scale > 0):
        raise ValueError(f"depth_scale must be finite and > 0, got {depth_scale}")
    if not math.isfinite(offset):
        raise ValueError(f"depth_time_offset_s must be finite, got {depth_time_offset_s}")
    for name, f in (("fx_factor", fx_factor), ("fy_factor", fy_factor)):
        if not (math.isfinite(f) and f > 0):
            raise ValueError(f"{name} must be finite and > 0, got {f}")
    return scale, offset


def _copy_lists(src: Path, dst: Path, offset: float) -> tuple[list[str], list[str]]:
    """Copy rgb.txt and groundtruth.txt (if any) from ``src`` to ``dst``, and depth.txt with
    its timestamps moved back by ``offset`` s (t_file = t_true - offset; as it is for 0).
    Returns the rgb and the depth images' paths relative to the folder, in list order."""
    shutil.copy2(src / "rgb.txt", dst / "rgb.txt")
    if (src / "groundtruth.txt").is_file():
        shutil.copy2(src / "groundtruth.txt", dst / "groundtruth.txt")
    _, rgb_rel = read_file_list(src / "rgb.txt")
    depth_t, depth_rel = read_file_list(src / "depth.txt")
    if offset == 0.0:
        shutil.copy2(src / "depth.txt", dst / "depth.txt")
    else:
        lines = ["# depth maps", f"# perturbed copy of {src.name}: true time = this + "
                 f"{offset!r} s", "# timestamp filename"]
        lines += [f"{t - offset:.6f} {rel}" for t, rel in zip(depth_t, depth_rel, strict=True)]
        (dst / "depth.txt").write_text("\n".join(lines) + "\n")
    return rgb_rel, depth_rel


def _write_rgb(seq: TumSequence, src: Path, dst: Path, rgb_rel: list[str],
               undistorted: bool, link: bool) -> None:
    """The copy's rgb images (paths ``rgb_rel`` relative to the folders): undistorted onto
    ``seq``'s pinhole intrinsics when ``undistorted``, else linked (``link``) or copied."""
    h, w = seq.height, seq.width
    for rel in rgb_rel:
        if undistorted:
            bgr = read_image(src / rel, cv2.IMREAD_COLOR, "rgb")
            bgr, _ = seq.rectify_frame(bgr, np.zeros((h, w), np.uint16))  # (channel-blind)
            _write_png(dst / rel, bgr)
        else:
            _place(src / rel, dst / rel, link)


def _write_depth(seq: TumSequence, src: Path, dst: Path, depth_rel: list[str],
                 pose: np.ndarray | None, scale: float, depth_factor: float,
                 link: bool) -> None:
    """The copy's depth images (paths ``depth_rel``): linked or copied when nothing changes
    them, else 16-bit PNGs of ``depth_factor`` units per metre holding the true depth (m)
    divided by ``scale``, seen by a depth camera at ``pose`` (4, 4) T_color_depth when given
    (rendered from the rectified source depth), clipped to 0 .. 65535."""
    h, w = seq.height, seq.width
    blank = np.zeros((h, w, 3), np.uint8)
    intr = seq.intrinsics
    for rel in depth_rel:
        if pose is None and scale == 1.0:
            _place(src / rel, dst / rel, link)
            continue
        raw = read_image(src / rel, cv2.IMREAD_UNCHANGED, "depth")
        if pose is None:  # per pixel: no resampling, distortion or not
            metres = raw.astype(np.float64) / depth_factor
        else:
            _, metres = seq.rectify_frame(blank, raw)
            metres = register_depth(metres, intr, intr, np.linalg.inv(pose)).astype(np.float64)
        out = np.clip(np.rint(metres / scale * depth_factor), 0, 65535).astype(np.uint16)
        _write_png(dst / rel, out)


def _write_calibration(src: Path, dst: Path, intr: Intrinsics, distortion,
                       fx_factor: float, fy_factor: float) -> None:
    """The copy's calibration.txt: fx * fx_factor, fy * fy_factor, cx, cy (pixels) and the
    distortion coefficients (none for an undistorted copy), under a comment naming the true
    camera's file."""
    fx, fy, cx, cy = intr
    numbers = [fx * fx_factor, fy * fy_factor, cx, cy, *(distortion or ())]
    (dst / CALIBRATION).write_text(
        f"# perturbed copy of {src.name}: fx x {fx_factor!r}, fy x {fy_factor!r}; the true "
        f"camera is {TRUE_CAMERA}\n" + " ".join(repr(float(v)) for v in numbers) + "\n")
