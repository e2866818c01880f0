"""Image files of a sequence checked and read with errors that name the file: a PNG or JPEG
checked whole (signature and end marker) and its size and format read from its header without
decoding it, so that a bad file deep in a long sequence is reported before tracking starts;
any image decoded with OpenCV (a truncated JPEG refused). Host side: numpy + OpenCV."""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np

__all__ = ["check_files", "describe", "read_image"]


def read_image(path: Path, flags: int, what: str) -> np.ndarray:
    """The image at ``path`` decoded with OpenCV ``flags``; FileNotFoundError, or ValueError
    for a truncated JPEG or a file OpenCV cannot decode, naming the ``what`` image."""
    if not path.is_file():
        raise FileNotFoundError(f"{what} image not found: {path}")
    buf = np.fromfile(path, np.uint8)
    if path.suffix.lower() in _JPEG_SUFFIXES and _JPEG_END not in buf[-64:].tobytes():
        raise ValueError(f"cannot decode {what} image {path}: truncated JPEG (no end-of-image "
                         f"marker FF D9 at the end of its {buf.size} bytes)")
    img = cv2.imdecode(buf, flags) if buf.size else None
    if img is None:
        raise ValueError(f"cannot decode {what} image {path} (corrupt or truncated file?)")
    return img


_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_PNG_END = b"IEND\xaeB`\x82"  # the IEND chunk type and its CRC: the last bytes of a whole PNG
# PNG colour type -> (what cv2.IMREAD_UNCHANGED makes of it)
_PNG_COLOUR = {0: "1 channel", 2: "3 channels", 3: "palette colour", 4: "gray + alpha",
               6: "4 channels"}


def _png_header(path: Path, what: str) -> tuple[int, int, str] | None:
    """(width, height, description) from a PNG's header, checking that the file is a whole
    PNG (signature, IHDR, IEND at the end) without decoding it; None for a non-PNG name."""
    if path.suffix.lower() != ".png":
        return None
    size = path.stat().st_size
    with path.open("rb") as f:
        head = f.read(26)
        f.seek(max(size - 64, 0))
        tail = f.read()
    if len(head) < 26 or head[:8] != _PNG_SIGNATURE or head[12:16] != b"IHDR":
        raise ValueError(f"cannot decode {what} image {path}: not a PNG file ({size} bytes; "
                         "corrupt?)")
    if _PNG_END not in tail:
        raise ValueError(f"cannot decode {what} image {path}: truncated PNG (no IEND chunk at "
                         f"the end of its {size} bytes)")
    width, height = int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")
    bits = "16-bit" if head[24] == 16 else "8-bit"
    return width, height, f"{bits}, {_PNG_COLOUR.get(head[25], f'colour type {head[25]}')}"


_JPEG_SUFFIXES = (".jpg", ".jpeg")
_JPEG_END = b"\xff\xd9"  # EOI: the last marker of a whole JPEG
# start-of-frame markers (baseline, progressive, lossless, arithmetic): they hold the size
_JPEG_SOF = frozenset({0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE,
                       0xCF})


def _jpeg_header(path: Path, what: str) -> tuple[int, int, str] | None:
    """(width, height, description) from a JPEG's frame header, checking that the file is a
    whole JPEG (SOI at the start, EOI at the end) without decoding it; None for a non-JPEG
    name."""
    if path.suffix.lower() not in _JPEG_SUFFIXES:
        return None
    size = path.stat().st_size
    with path.open("rb") as f:
        if f.read(3) != b"\xff\xd8\xff":
            raise ValueError(f"cannot decode {what} image {path}: not a JPEG file ({size} "
                             "bytes; corrupt?)")
        f.seek(max(size - 64, 0))
        if _JPEG_END not in f.read():
            raise ValueError(f"cannot decode {what} image {path}: truncated JPEG (no "
                             f"end-of-image marker FF D9 at the end of its {size} bytes)")
        f.seek(2)
        while True:  # segments: FF, marker, 2-byte length (counting itself), body
            head = f.read(4)
            while len(head) == 4 and head[1] == 0xFF:  # fill bytes before a marker
                head = head[1:] + f.read(1)
            if len(head) < 4 or head[0] != 0xFF or head[1] in (0xD9, 0xDA):
                raise ValueError(f"cannot decode {what} image {path}: corrupt JPEG (no frame "
                                 "header before its image data)")
            if head[1] in _JPEG_SOF:
                body = f.read(6)  # precision, height, width, components
                if len(body) < 6:
                    break
                channels = body[5]
                return (int.from_bytes(body[3:5], "big"), int.from_bytes(body[1:3], "big"),
                        f"{body[0]}-bit, {channels} channel{'s' if channels != 1 else ''}")
            f.seek(int.from_bytes(head[2:4], "big") - 2, os.SEEK_CUR)
    raise ValueError(f"cannot decode {what} image {path}: corrupt JPEG (frame header cut "
                     "short)")


def check_files(rgb_files: tuple[Path, ...], depth_files: tuple[Path, ...]) -> None:
    """Every associated image present, a whole PNG or JPEG (other formats: present), the same
    size, depth 16-bit single channel: read from the files' headers and ends only (no
    decoding), so a bad file deep in a long sequence is reported before tracking starts."""
    for what, files in (("rgb", rgb_files), ("depth", depth_files)):
        missing = [f for f in files if not f.is_file()]
        if missing:
            more = f" (and {len(missing) - 1} more of its {len(files)} {what} images)"
            raise FileNotFoundError(
                f"{what} image not found: {missing[0]}" + (more if len(missing) > 1 else "")
            )
    size = None
    for rgb_path, depth_path in zip(rgb_files, depth_files, strict=True):
        rgb = _png_header(rgb_path, "rgb") or _jpeg_header(rgb_path, "rgb")
        depth = _png_header(depth_path, "depth") or _jpeg_header(depth_path, "depth")
        if depth is not None and depth[2] != "16-bit, 1 channel":
            raise ValueError(
                f"depth image {depth_path} must be single-channel 16-bit, got {depth[2]}"
            )
        if rgb is not None and depth is not None and rgb[:2] != depth[:2]:
            raise ValueError(
                f"rgb {rgb_path} is {rgb[0]}x{rgb[1]} but depth {depth_path} is "
                f"{depth[0]}x{depth[1]} (width x height)"
            )
        here = rgb or depth
        if here is not None:
            if size is None:
                size = (here[:2], rgb_path if rgb is not None else depth_path)
            elif here[:2] != size[0]:
                raise ValueError(
                    f"frame {rgb_path} is {here[0]}x{here[1]}, the sequence (from "
                    f"{size[1]}) is {size[0][0]}x{size[0][1]} (width x height)"
                )


def describe(img: np.ndarray) -> str:
    """An image's bit depth and channels, as ``16-bit, 1 channel``."""
    bits = {np.dtype(np.uint8): "8-bit", np.dtype(np.uint16): "16-bit"}.get(
        img.dtype, f"dtype {img.dtype}"
    )
    channels = 1 if img.ndim == 2 else img.shape[2]
    return f"{bits}, {channels} channel{'s' if channels != 1 else ''}"
