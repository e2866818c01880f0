"""A saved keyframe map drawn from two sides (``edgevo plot map``)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ..map.export import Cloud
from ._canvas import figure, save

_AXES = {"x": 0, "y": 1, "z": 2}


def plot_map(cloud: Cloud, path: str | os.PathLike[str], *, planes: tuple[str, str] = ("xy",
             "xz"), title: str | None = None, max_points: int = 200_000,
             dpi: float | None = None) -> Path:
    """The edges of a keyframe map (``map.export.map_cloud``) seen along two axes of the
    map's frame, one panel per ``planes`` entry (two of x, y, z; metres, equal scale), each
    point in its keyframe's time colour and the keyframes' centres joined in order; at most
    ``max_points`` points (an even subsample). Writes a PNG to ``path``; its path."""
    for plane in planes:
        if len(plane) != 2 or plane[0] == plane[1] or any(c not in _AXES for c in plane):
            raise ValueError(f"planes must be two different axes of x, y, z, got {plane!r}")
    keep = np.arange(len(cloud.xyz))
    if len(keep) > max_points:
        keep = np.linspace(0, len(keep) - 1, max_points).astype(int)
    xyz, rgb = cloud.xyz[keep], cloud.rgb[keep] / 255.0
    fig = figure((6.0 * len(planes), 6.0), layout="constrained")
    for n, plane in enumerate(planes):
        ax = fig.add_subplot(1, len(planes), n + 1)
        i, j = _AXES[plane[0]], _AXES[plane[1]]
        ax.scatter(xyz[:, i], xyz[:, j], c=rgb, s=0.3, linewidths=0, rasterized=True)
        ax.plot(cloud.centres[:, i], cloud.centres[:, j], color="k", linewidth=1.0,
                marker="o", markersize=2.5, label="keyframes, in order")
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_xlabel(f"{plane[0]} (m)")
        ax.set_ylabel(f"{plane[1]} (m)")
        ax.set_title(f"{plane[0]}-{plane[1]} plane of the map's frame", fontsize=11)
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=9, loc="best")
    fig.suptitle(title or f"{len(cloud.centres)} keyframes, {len(cloud.xyz):,} edge points "
                 "(colour: keyframe time, first dark blue, last yellow)", fontsize=12)
    return save(fig, path, dpi)
