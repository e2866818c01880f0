"""A copy of a TUM sequence folder with some frames covered, as a hand over the lens or a
dropped camera would leave them: black colour images and empty depth images (0: missing).

For the map's "found again" tests and benchmarks: the tracker must call the covered frames
LOST and find its place again after them. Host side: numpy + OpenCV.
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Iterable
from pathlib import Path

import cv2
import numpy as np

from .images import read_image
from .tum import load_sequence

__all__ = ["covered_copy"]


def covered_copy(src_dir: str | os.PathLike[str], dst_dir: str | os.PathLike[str],
                 frames: Iterable[int], *, link: bool = True) -> list[float]:
    """Write a copy of the TUM folder ``src_dir`` to ``dst_dir`` (which must not exist) whose
    associated frames ``frames`` (indices into ``load_sequence(src_dir)``, 0-based) are
    covered: their colour image black, their depth image all 0 (missing), each written as a
    PNG of the source's size and type. Every other file (images, rgb.txt, depth.txt,
    groundtruth.txt, calibration.txt) is a symbolic link to the source's (``link``; False:
    a copy), so the copy keeps the source's timestamps and ground truth. The copy's camera
    comes from its own name as any folder's does: keep the source's camera name in it
    (``..._freiburg3_teddy_covered``) or pass ``camera=`` to ``load_sequence``.

    Returns the covered frames' timestamps (s). ValueError for an index outside the sequence
    (naming it) or no frame to cover; FileExistsError for an existing ``dst_dir``."""
    src, dst = Path(src_dir), Path(dst_dir)
    if dst.exists():
        raise FileExistsError(f"covered copy: {dst} exists already (give a new folder)")
    seq = load_sequence(src, check_images=False)
    picked = sorted({int(i) for i in frames})
    if not picked:
        raise ValueError("covered copy: no frame to cover")
    bad = [i for i in picked if not 0 <= i < len(seq)]
    if bad:
        raise ValueError(f"covered copy: frame {bad[0]} is outside the sequence's "
                         f"{len(seq)} associated frames (0 to {len(seq) - 1})")
    covered = {Path(f).resolve() for i in picked for f in (seq.rgb_files[i], seq.depth_files[i])}
    dst.mkdir(parents=True)
    for path in sorted(src.rglob("*")):
        if path.is_dir():
            continue
        rel = path.relative_to(src)
        out = dst / rel
        out.parent.mkdir(parents=True, exist_ok=True)
        if path.resolve() in covered:
            image = read_image(path, cv2.IMREAD_UNCHANGED, "rgb or depth")
            if not cv2.imwrite(str(out), np.zeros_like(image)):
                raise OSError(f"cannot write {out}")
        elif link:
            os.symlink(path.resolve(), out)
        else:
            shutil.copy2(path, out)
    return [float(seq.timestamps[i]) for i in picked]
