"""A saved keyframe map as a point cloud (``edgevo map export``): every keyframe's selected
edges, lifted with their depth and placed at the keyframe's pose in the map's frame, written
as a binary PLY that any point-cloud viewer opens (MeshLab, CloudCompare, Open3D, Blender).

Each point is coloured by when its keyframe was made, from dark blue (the map's first
keyframe) through green to yellow (its last), so the sessions and the way the camera went
read from the colours: an edge image has no colour of its own to give.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import NamedTuple

import numpy as np

from .archive import read_cloud

#: the colour ramp of keyframe time: (position in [0, 1], RGB), linear between the knots
RAMP = ((0.0, (68, 1, 84)), (0.25, (59, 82, 139)), (0.5, (33, 145, 140)),
        (0.75, (94, 201, 98)), (1.0, (253, 231, 37)))


class Cloud(NamedTuple):
    """A map's edges as points: ``xyz`` (N, 3) float32 in the map's frame (m), ``rgb``
    (N, 3) uint8 (``RAMP`` by keyframe time), ``keyframe`` (N,) the index of each point's
    keyframe in the file, and the keyframes' centres ``centres`` (K, 3) in the map's frame."""

    xyz: np.ndarray
    rgb: np.ndarray
    keyframe: np.ndarray
    centres: np.ndarray


def ramp(t: np.ndarray) -> np.ndarray:
    """``RAMP``'s colours (N, 3) uint8 at ``t`` (N,) in [0, 1] (clipped)."""
    at, rgb = (np.array(v, np.float64) for v in zip(*RAMP, strict=True))
    t = np.clip(np.asarray(t, np.float64), 0.0, 1.0)
    return np.stack([np.interp(t, at, rgb[:, c]) for c in range(3)], axis=-1
                    ).round().astype(np.uint8)


def map_cloud(path: str | os.PathLike[str], *, max_depth: float | None = None) -> Cloud:
    """The edges of the map file at ``path`` as a ``Cloud``; ``max_depth`` (m): only the
    points nearer than this to their keyframe's camera (its z). MapFileError for a file that
    is no readable map."""
    if max_depth is not None and not max_depth > 0:
        raise ValueError(f"max_depth must be positive, got {max_depth}")
    poses, points = read_cloud(path)
    if max_depth is not None:
        points = [q[q[:, 2] < max_depth] for q in points]
    parts = [(p[:3, :3] @ q.T.astype(np.float64)).T + p[:3, 3] for p, q in zip(
        poses, points, strict=True)]
    keyframe = np.repeat(np.arange(len(poses)), [len(q) for q in points])
    when = keyframe / max(len(poses) - 1, 1)
    xyz = np.concatenate(parts).astype(np.float32) if parts else np.zeros((0, 3), np.float32)
    return Cloud(xyz, ramp(when), keyframe, poses[:, :3, 3].copy())


def write_ply(path: str | os.PathLike[str], xyz: np.ndarray, rgb: np.ndarray) -> Path:
    """Write points ``xyz`` (N, 3) with colours ``rgb`` (N, 3) uint8 as a binary
    little-endian PLY (x, y, z float32; red, green, blue uchar); its path."""
    xyz, rgb = np.asarray(xyz, np.float32), np.asarray(rgb, np.uint8)
    if xyz.ndim != 2 or xyz.shape[1] != 3 or rgb.shape != xyz.shape:
        raise ValueError(f"points (N, 3) and colours (N, 3) needed, got {xyz.shape} and "
                         f"{rgb.shape}")
    rows = np.empty(len(xyz), [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"),
                               ("green", "u1"), ("blue", "u1")])
    for n, name in enumerate("xyz"):
        rows[name] = xyz[:, n]
    for n, name in enumerate(("red", "green", "blue")):
        rows[name] = rgb[:, n]
    header = ("ply\nformat binary_little_endian 1.0\ncomment edgevo_jax keyframe map edges\n"
              f"element vertex {len(rows)}\nproperty float x\nproperty float y\n"
              "property float z\nproperty uchar red\nproperty uchar green\n"
              "property uchar blue\nend_header\n")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "wb") as f:
        f.write(header.encode("ascii"))
        f.write(rows.tobytes())
    return path


def export_ply(map_path: str | os.PathLike[str], out: str | os.PathLike[str], *,
               max_depth: float | None = None) -> int:
    """Write the edges of the map file at ``map_path`` (nearer than ``max_depth`` to their
    keyframe, m) to the PLY ``out`` (``map_cloud``, ``write_ply``); how many points."""
    cloud = map_cloud(map_path, max_depth=max_depth)
    write_ply(out, cloud.xyz, cloud.rgb)
    return len(cloud.xyz)
