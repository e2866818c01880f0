"""Figures of one run: the trajectory against the ground truth, and one pre-processed
frame (edges, gradient directions, the distance-field pyramid)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..metrics import align_trajectory

if TYPE_CHECKING:  # only for annotations: viz sits beside preprocess, not above it
    from ..image.preprocess import Frame

from ._canvas import figure, save

# ---------------------------------------------------------------------------- trajectory

_AXES = {"x": 0, "y": 1, "z": 2}


def plot_trajectory(
    gt_t: np.ndarray,
    gt_poses7: np.ndarray,
    est_t: np.ndarray,
    est_poses7: np.ndarray,
    path: str | os.PathLike[str],
    *,
    plane: str = "xy",
    max_diff: float = 0.02,
    title: str | None = None,
    dpi: float | None = None,
) -> Path:
    """Estimated trajectory vs ground truth; writes a PNG to ``path`` and returns the path.

    Inputs as :func:`align_trajectory` (seconds; poses7 of T_world_cam in metres). The
    estimate is aligned onto the ground truth as the ATE does; left: top view, the ``plane``
    axes (two of x, y, z of the ground truth's world frame, metres, equal scale); right:
    x, y and z (m) over time (s from the first estimated pose). The ground truth is drawn
    over the estimate's time span (plus 5 %); the estimate is a line with one dot per
    associated pose, coloured by its position error after alignment (m, colour bar). The
    title gives the ATE RMSE, equal to :func:`edgevo_jax.metrics.ate`'s. ``dpi``: pixels per
    inch (default 120; the figure is 12 x 6 inches).
    """
    if len(plane) != 2 or plane[0] == plane[1] or any(c not in _AXES for c in plane):
        raise ValueError(f"plane must be two different axes of x, y, z (e.g. 'xy'), got {plane!r}")
    al = align_trajectory(gt_t, gt_poses7, est_t, est_poses7, max_diff=max_diff)
    from matplotlib.colors import Normalize

    t0 = float(al.est_t.min())
    span = float(al.est_t.max()) - t0
    pad = max(0.05 * span, max_diff)
    in_span = (al.gt_t >= t0 - pad) & (al.gt_t <= t0 + span + pad)
    gt_tt, gt_xyz = al.gt_t[in_span] - t0, al.gt_xyz[:, in_span]
    order = np.argsort(al.est_t, kind="stable")
    est_tt, est_xyz = al.est_t[order] - t0, al.est_xyz[:, order]
    dots_t = al.est_t[al.pairs[:, 1]] - t0
    dots = al.est_xyz[:, al.pairs[:, 1]]
    norm = Normalize(vmin=0.0, vmax=max(float(al.error.max()), 1e-9))
    cmap = "plasma"

    fig = figure((12.0, 6.0), layout="constrained")
    grid = fig.add_gridspec(3, 2, width_ratios=(1.0, 1.15))
    ax_top = fig.add_subplot(grid[:, 0])
    i, j = _AXES[plane[0]], _AXES[plane[1]]
    ax_top.plot(gt_xyz[i], gt_xyz[j], color="0.35", linewidth=2.0, label="ground truth")
    ax_top.plot(est_xyz[i], est_xyz[j], color="tab:blue", linewidth=1.0, alpha=0.7,
                label="estimate (aligned)")
    sc = ax_top.scatter(dots[i], dots[j], c=al.error, cmap=cmap, norm=norm, s=22, zorder=3,
                        edgecolors="k", linewidths=0.3)
    ax_top.scatter(gt_xyz[i, :1], gt_xyz[j, :1], marker="*", s=120, color="0.35", zorder=4,
                   label="ground-truth start")
    ax_top.set_aspect("equal", adjustable="datalim")
    ax_top.set_xlabel(f"{plane[0]} (m)")
    ax_top.set_ylabel(f"{plane[1]} (m)")
    ax_top.set_title(f"top view ({plane[0]}-{plane[1]} plane of the ground-truth frame)",
                     fontsize=11)
    ax_top.grid(True, alpha=0.3)
    ax_top.legend(fontsize=9, loc="best")
    fig.colorbar(sc, ax=ax_top, label="position error after alignment (m)", shrink=0.8)
    first = None
    for row, name in enumerate("xyz"):
        ax = fig.add_subplot(grid[row, 1], sharex=first)
        first = first or ax
        k = _AXES[name]
        ax.plot(gt_tt, gt_xyz[k], color="0.35", linewidth=2.0)
        ax.plot(est_tt, est_xyz[k], color="tab:blue", linewidth=1.0, alpha=0.7)
        ax.scatter(dots_t, dots[k], c=al.error, cmap=cmap, norm=norm, s=14, zorder=3,
                   edgecolors="k", linewidths=0.3)
        ax.set_ylabel(f"{name} (m)")
        ax.grid(True, alpha=0.3)
        if row < 2:
            ax.tick_params(labelbottom=False)
    ax.set_xlabel("time since the first estimated pose (s)")
    head = title or "estimate vs ground truth"
    fig.suptitle(f"{head}: ATE RMSE {al.rmse:.4f} m over {al.pairs.shape[0]} poses "
                 "(rigid alignment, no scale)", fontsize=12)
    return save(fig, path, dpi)


# ---------------------------------------------------------------------------- one frame


def plot_frame(
    gray: np.ndarray,
    frame: Frame,
    path: str | os.PathLike[str],
    *,
    title: str | None = None,
    dpi: float | None = None,
) -> Path:
    """One pre-processed frame (EdgeVO Fig. 3); writes a PNG to ``path`` and returns it.

    gray: (H, W) image the frame was computed from; frame: a
    :class:`edgevo_jax.preprocess.Frame` (edge_uv (N, 2) pixels (u, v) = (column, row),
    edge_mag (N,) Sobel L2 gradient magnitude in 8-bit intensity units, dist: one distance
    field per level, (H / 2**l, W / 2**l) in that level's pixels, edge_map).
    Top row: the gray image, the Canny edge pixels coloured by gradient magnitude, and the
    gradient direction of the nearest edge at every pixel (degrees, cyclic colours); bottom
    row: the distance-field pyramid, one panel per level, each in its own pixels and colour
    scale (square root, clipped at its 99th percentile). ``dpi``: pixels per inch (default
    120; a panel is 4.6 inches wide).
    """
    img, uv, mag = _checked_frame(gray, frame)
    h, w = img.shape
    levels = len(frame.dist)
    cols = max(3, levels)
    panel = 4.6
    fig = figure((panel * cols, 2 * panel * h / w + 1.2), layout="constrained")
    axes = fig.subplots(2, cols, squeeze=False)
    for ax in axes.ravel():
        ax.set_xticks([])
        ax.set_yticks([])

    ax = axes[0, 0]
    ax.imshow(img, cmap="gray", interpolation="antialiased")
    ax.set_title(f"(a) gray image, {w}x{h} px", fontsize=11)
    _edge_panel(fig, axes[0, 1], uv, mag, h, w)
    _direction_panel(fig, axes[0, 2], frame, h, w)
    for level, field in enumerate(frame.dist):
        _distance_panel(fig, axes[1, level], field, level)
    for ax in axes[1, levels:]:
        ax.set_axis_off()
    if title:
        fig.suptitle(title, fontsize=12)
    return save(fig, path, dpi)


def _checked_frame(gray: np.ndarray, frame: Frame) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The gray image (H, W), the frame's edge pixels (N, 2) (u, v) and magnitudes (N,)
    float64, checked: ValueError unless gray is 2-D of the size of the frame's level 0 and
    edge_uv, edge_mag have those shapes."""
    img = np.asarray(gray)
    if img.ndim != 2:
        raise ValueError(f"gray must be a 2-D (H, W) image, got shape {img.shape}")
    h, w = img.shape
    if tuple(frame.dist[0].shape) != (h, w):
        raise ValueError(f"gray is {w}x{h} but the frame's level 0 is "
                         f"{frame.dist[0].shape[1]}x{frame.dist[0].shape[0]} (width x height)")
    uv = np.asarray(frame.edge_uv)
    mag = np.asarray(frame.edge_mag, np.float64)
    if uv.ndim != 2 or uv.shape[1] != 2 or mag.shape != (uv.shape[0],):
        raise ValueError(f"frame.edge_uv must be (N, 2) and edge_mag (N,), got {uv.shape} and "
                         f"{mag.shape}")
    return img, uv, mag


def _edge_panel(fig, ax, uv: np.ndarray, mag: np.ndarray, h: int, w: int) -> None:
    """Panel (b): the edge pixels uv (N, 2) (u, v) of an (h, w) image coloured by their
    gradient magnitude mag (N,) (8-bit units, scale clipped at the 99th percentile), the rest
    black; with its colour bar."""
    import matplotlib as mpl

    edge_img = np.full((h, w), np.nan)
    cols_u = np.clip(np.round(uv[:, 0]).astype(int), 0, w - 1)
    rows_v = np.clip(np.round(uv[:, 1]).astype(int), 0, h - 1)
    edge_img[rows_v, cols_u] = mag
    cmap = mpl.colormaps["viridis"].with_extremes(bad="black")
    vmax = float(np.percentile(mag, 99)) if mag.size else 1.0
    im = ax.imshow(edge_img, cmap=cmap, vmin=0.0, vmax=max(vmax, 1e-9), interpolation="nearest")
    ax.set_title(f"(b) Canny edges: {uv.shape[0]} pixels", fontsize=11)
    fig.colorbar(im, ax=ax, shrink=0.85, label="gradient magnitude (Sobel, 8-bit units)")


def _direction_panel(fig, ax, frame: Frame, h: int, w: int) -> None:
    """Panel (c): at every pixel of the (h, w) level 0, the gradient direction (degrees,
    atan2(g_v, g_u), cyclic colours) of the nearest edge of ``frame.edge_map`` (black where
    none is found); with its colour bar."""
    import jax.numpy as jnp
    import matplotlib as mpl

    from ..image.interp import nearest_edge_gradient

    vv, uu = np.mgrid[0:h, 0:w]
    g, found = nearest_edge_gradient(frame.edge_map, jnp.asarray(
        np.stack([uu.ravel(), vv.ravel()]).astype(np.float32)))
    g, found = np.asarray(g, np.float64), np.asarray(found)
    angle = np.where(found, np.degrees(np.arctan2(g[1], g[0])), np.nan).reshape(h, w)
    im = ax.imshow(angle, cmap=mpl.colormaps["twilight"].with_extremes(bad="black"),
                   vmin=-180.0, vmax=180.0, interpolation="nearest")
    ax.set_title("(c) gradient direction of the nearest edge", fontsize=11)
    fig.colorbar(im, ax=ax, shrink=0.85, ticks=[-180, -90, 0, 90, 180],
                 label="atan2(g_v, g_u) (degrees)")


def _distance_panel(fig, ax, field, level: int) -> None:
    """Panel (d), (e), ...: the distance field of ``level`` (H / 2**l, W / 2**l), distances
    in that level's pixels, on a square-root colour scale clipped at its 99th percentile;
    with its colour bar."""
    from matplotlib.colors import PowerNorm

    d = np.asarray(field, np.float64)
    top = float(np.percentile(d, 99)) if d.size else 1.0
    # square-root colour scale: the few pixels near edges, which the residuals read,
    # get as much of the colour range as the wide empty regions
    im = ax.imshow(d, cmap="magma", norm=PowerNorm(0.5, vmin=0.0, vmax=max(top, 1e-9)),
                   interpolation="antialiased")
    ax.set_title(f"({chr(ord('d') + level)}) distance field, level {level}: "
                 f"{d.shape[1]}x{d.shape[0]}", fontsize=11)
    fig.colorbar(im, ax=ax, shrink=0.85, extend="max",
                 label=f"distance to nearest edge (level-{level} px)")
