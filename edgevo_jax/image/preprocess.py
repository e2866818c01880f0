"""Host-side preprocessing of one RGB-D frame (numpy + OpenCV) into fixed-shape arrays.

gray -> Gaussian blur -> Canny; Sobel gradients (their L2 magnitude is the one Canny
thresholds); level-0 Euclidean distance field to the nearest edge (OpenCV's 5x5 chamfer
approximation); levels 1..L-1 by halving level 0 (means of 2x2 blocks) with distances
rescaled to the level's pixels. The nearest edge's gradient (the consistency test) is found
on the device from the distance field and a map of edge directions (``preprocess.EdgeMap``):
a labelled distance transform would give it for every pixel, at three times the cost of the
plain one.
"""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from functools import cache
from typing import Any, NamedTuple

import cv2
import jax.numpy as jnp
import numpy as np

from ..config import Config
from ..hostmem import aligned_array, aligned_empty


class EdgeMap(NamedTuple):
    """Where the nearest edge p' of a level-0 pixel is, and its gradient: the level-0
    distance field dist0 (H, W) (px) and code (H, W) uint8, the direction of the edge at
    each edge pixel (1 + its gradient angle in 254 steps; see ``preprocess.direction_codes``),
    copied to the empty neighbours of edge pixels; 0 elsewhere. depth (H, W) float32 metres
    (0 = missing): the frame's depth map for the optional depth residual, None without it."""

    dist0: jnp.ndarray
    code: jnp.ndarray
    depth: jnp.ndarray | None = None


@dataclass(frozen=True)
class Frame:
    """One pre-processed frame. Pixels are (u, v) = (column, row).

    edge_uv (N, 2) float32 pixels of the Canny edges; edge_grad (N, 2) their normalised
    image gradient; edge_mag (N,) Sobel L2 magnitude; edge_depth (N,) metres (0 = missing);
    dist: one float32 distance field per level, (H / 2**l, W / 2**l), in that level's pixels;
    edge_map: ``preprocess.EdgeMap`` (level-0 field and (H, W) uint8 direction codes), from
    which the device finds the nearest edge's gradient; depth: the (H, W) depth image in
    metres it was made from (a reference, not a copy; the local map reads it at keyframes);
    gray: the (H, W) uint8 image the edges were found in (a reference; recovery's feature
    hypotheses read it), None when the frame was made from edges alone; depth_lag_s: how
    long after the colour image the depth image was taken (s; a keyframe made from the
    frame moves its edges' depths to the colour image's time, ``shutter.depths_at_colour_time``).
    """

    edge_uv: np.ndarray
    edge_grad: np.ndarray
    edge_mag: np.ndarray
    edge_depth: np.ndarray
    dist: tuple[np.ndarray, ...]
    edge_map: EdgeMap
    depth: np.ndarray | None = None
    gray: np.ndarray | None = None
    depth_lag_s: float = 0.0

    @property
    def num_edges(self) -> int:
        """Number of Canny edge pixels."""
        return int(self.edge_uv.shape[0])

    @property
    def shape(self) -> tuple[int, int]:
        """(H, W) of level 0."""
        return self.dist[0].shape


@cache
def _worker() -> ThreadPoolExecutor:
    """One background thread for the distance transform (created on first use)."""
    return ThreadPoolExecutor(max_workers=1, thread_name_prefix="edgevo-dt")


def beside(fn: Callable[..., Any], /, *args: Any, **kwargs: Any) -> Future:
    """``fn(*args, **kwargs)`` on the preprocessing's worker thread, which is idle between a
    frame's preprocessing and the next's: host work the caller's thread overlaps."""
    return _worker().submit(fn, *args, **kwargs)


def to_gray(rgb: np.ndarray) -> np.ndarray:
    """uint8 gray image from an RGB (H, W, 3) or gray (H, W) uint8 image."""
    if rgb.ndim == 2:
        return rgb
    return cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)


def detect_edges(gray: np.ndarray, config: Config) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Canny edge mask (uint8, 255 on edges) and 3x3 Sobel gradients gx, gy (int16); Canny
    runs on those same gradients (one Sobel pass for both)."""
    k = config.blur_ksize
    blurred = cv2.GaussianBlur(gray, (k, k), config.blur_sigma) if k > 1 else gray
    gx, gy = cv2.spatialGradient(blurred)
    edges = cv2.Canny(gx, gy, config.canny_low, config.canny_high, L2gradient=True)
    return edges, gx, gy


def distance_pyramid(level0: np.ndarray, num_levels: int) -> tuple[np.ndarray, ...]:
    """Levels 1.. of a float32 distance field (H, W): level l + 1's pixel (x, y) is the mean
    of level l's 2x2 block at (2x, 2y), ((top left + top right) + (bottom left + bottom
    right)) / 4 in float32, and its distance divided by 2 (the level's pixels); an odd last
    row or column is left out, so that every level is an exact halving, as
    ``Intrinsics.at_level`` has it. Shapes (H // 2**l, W // 2**l), 64-byte aligned
    (``aligned_empty``). The sums are numpy's, not ``cv2.resize``'s, so that the fields do
    not depend on the OpenCV release (docs/decisions.md, "The distance pyramid's halving")."""
    levels = [level0]
    for _ in range(1, num_levels):
        prev = levels[-1]
        h, w = prev.shape[0] // 2, prev.shape[1] // 2
        pairs = np.add(prev[:2 * h, 0:2 * w:2], prev[:2 * h, 1:2 * w:2])  # each row's
        out = np.add(pairs[0::2], pairs[1::2], out=aligned_empty((h, w), np.float32))
        levels.append(np.multiply(out, np.float32(0.125), out=out))  # / 4, then / 2
    return tuple(levels)


def direction_code_values(grad: np.ndarray) -> np.ndarray:
    """(N,) uint8 codes of normalised gradients grad (N, 2): 1 + the angle in 254 steps (1.4
    degrees, far below the consistency gate)."""
    angle = np.arctan2(grad[:, 1], grad[:, 0])
    q = np.round((angle + np.pi) * (254.0 / (2.0 * np.pi))).astype(np.int32) % 254
    return (1 + q).astype(np.uint8)


#: Largest |Sobel| of ``cv2.spatialGradient`` on uint8 images (3x3: 4 x 255).
SOBEL_MAX = 1020


def normalised_gradients(gx: np.ndarray, gy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Gradient magnitudes (N,) and normalised gradients (N, 2), float32, of Sobel values
    gx, gy (N,) (the same arithmetic wherever it is used: ``_code_table`` relies on it)."""
    egx, egy = gx.astype(np.float32), gy.astype(np.float32)
    mag = np.hypot(egx, egy)
    grad = np.stack([egx, egy], axis=-1) / np.maximum(mag, 1e-6)[:, None]
    return mag.astype(np.float32), grad.astype(np.float32)


@cache
def _code_table() -> np.ndarray:
    """The direction code of every Sobel pair (gx, gy) in [-SOBEL_MAX, SOBEL_MAX]^2, flat
    (row gy + SOBEL_MAX, column gx + SOBEL_MAX): ``direction_code_values`` of
    ``normalised_gradients``, computed once (~0.1 s, 4 MB) so that a frame looks its ~10^4
    edges' codes up instead of taking their arctangents (a fifth of a millisecond)."""
    r = np.arange(-SOBEL_MAX, SOBEL_MAX + 1, dtype=np.int16)
    gy, gx = (a.ravel() for a in np.meshgrid(r, r, indexing="ij"))
    return direction_code_values(normalised_gradients(gx, gy)[1])


def direction_codes(pts: np.ndarray, grad: np.ndarray, shape: tuple[int, int],
                    values: np.ndarray | None = None) -> np.ndarray:
    """(H, W) uint8 map of edge directions: at each edge pixel pts (N, 2) (u, v), the code
    of its normalised gradient grad (N, 2) (``direction_code_values``; ``values``: those
    codes when known); each empty pixel next to an edge takes a neighbour's code (a 3x3
    dilation), so that a lookup one pixel off the edge still finds it; 0 elsewhere."""
    h, w = shape
    code = aligned_empty((h, w), np.uint8)
    code.fill(0)
    if not pts.shape[0]:
        return code
    values = direction_code_values(grad) if values is None else values
    flat = pts[:, 1] * w + pts[:, 0]
    code.reshape(-1)[flat] = values
    grown = cv2.dilate(code, np.ones((3, 3), np.uint8), dst=aligned_empty((h, w), np.uint8))
    grown.reshape(-1)[flat] = values  # edge pixels keep their own direction
    return grown


def preprocess(rgb: np.ndarray, depth: np.ndarray, config: Config) -> Frame:
    """Turn an RGB (H, W, 3) uint8 image and a depth map (H, W) in metres into a Frame."""
    return start_preprocess(rgb, depth, config).finish()


def start_preprocess(rgb: np.ndarray, depth: np.ndarray, config: Config) -> PreprocessJob:
    """The first half of ``preprocess``: edges found, the distance fields launched on the
    worker thread, the edges' gradients and depths gathered. Do other work, then call
    ``.finish()`` for the Frame."""
    gray = to_gray(rgb)
    edges, gx, gy = detect_edges(gray, config)
    return PreprocessJob.start(edges, gx, gy, depth, config, gray=gray)


def frame_from_edges(
    edges: np.ndarray, gx: np.ndarray, gy: np.ndarray, depth: np.ndarray, config: Config
) -> Frame:
    """A Frame from an edge mask (H, W) uint8 (non-zero on edges), image gradients gx, gy
    (H, W) (read at edge pixels only) and depth (H, W) in metres."""
    return PreprocessJob.start(edges, gx, gy, depth, config).finish()


def distance_fields(edges: np.ndarray, num_levels: int) -> tuple[np.ndarray, ...]:
    """The distance-field pyramid of an edge mask (H, W) (non-zero on edges): the largest
    part of the preprocessing, in OpenCV calls that release the GIL (it runs on the worker
    thread while the caller's thread works)."""
    h, w = edges.shape
    if cv2.countNonZero(edges):
        # a 5x5 chamfer L2 distance (within 0.08 px of the exact one inside the 5 px
        # residual gate on TUM frames)
        dist0 = cv2.distanceTransform(cv2.bitwise_not(edges), cv2.DIST_L2, cv2.DIST_MASK_5,
                                      dst=aligned_empty((h, w), np.float32))
    else:  # no edge at all: every distance is "far"; the tracker reports the frame lost
        dist0 = aligned_empty((h, w), np.float32)
        dist0.fill(float(h + w))
    return distance_pyramid(dist0, num_levels)


@dataclass(frozen=True)
class PreprocessJob:
    """A frame whose edge pixels, gradients and depths are known and whose distance fields
    (``distance_fields``) are being made on the worker thread."""

    pts: np.ndarray  # (N, 2) int32 edge pixels in raster order
    grad: np.ndarray  # (N, 2) normalised image gradients
    mag: np.ndarray  # (N,) gradient magnitudes
    depth: np.ndarray  # (N,) depth at the edge pixels (m, 0 = missing)
    shape: tuple[int, int]
    fields: Future
    depth_image: np.ndarray | None = None  # (H, W) metres, a reference (Frame.depth)
    codes: np.ndarray | None = None  # (N,) the edges' direction codes, when looked up
    gray: np.ndarray | None = None  # (H, W) uint8, a reference (Frame.gray)
    map_depth: np.ndarray | None = None  # (H, W) float32, cleaned (EdgeMap.depth)

    @classmethod
    def start(cls, edges, gx, gy, depth, config: Config, *, gray: np.ndarray | None = None
              ) -> PreprocessJob:
        """Launch ``distance_fields`` on the worker thread, then find the edge pixels and
        gather their gradients and depths."""
        fields = _worker().submit(distance_fields, edges, config.num_levels)
        h, w = edges.shape
        found = cv2.findNonZero(edges)  # raster order
        pts = np.zeros((0, 2), np.int32) if found is None else found.reshape(-1, 2)
        flat = pts[:, 1] * w + pts[:, 0]
        sgx, sgy = np.take(gx.ravel(), flat), np.take(gy.ravel(), flat)
        mag, grad = normalised_gradients(sgx, sgy)
        codes = None
        # Sobel of a uint8 image (as ``detect_edges`` makes it): look the codes up; other
        # gradients (``frame_from_edges``'s callers) get them computed in ``finish``
        if sgx.dtype == np.int16 and sgx.size and max(
                int(np.abs(sgx).max()), int(np.abs(sgy).max())) <= SOBEL_MAX:
            codes = np.take(_code_table(), (sgy.astype(np.int32) + SOBEL_MAX) * (
                2 * SOBEL_MAX + 1) + (sgx.astype(np.int32) + SOBEL_MAX))
        d = np.take(depth.ravel(), flat).astype(np.float32)
        d = np.where(np.isfinite(d) & (d >= config.min_depth) & (d <= config.max_depth), d, 0.0)
        map_depth = None
        if config.depth_residual:
            map_depth = aligned_array(np.where(
                np.isfinite(depth) & (depth >= config.min_depth) & (depth <= config.max_depth),
                depth, 0.0), np.float32)  # 64-byte aligned: JAX takes it without a copy
        return cls(pts, grad, mag, d.astype(np.float32), (h, w), fields, depth, codes, gray,
                   map_depth)

    def finish(self) -> Frame:
        """Make the direction codes (while the worker may still run), wait for the distance
        fields and build the Frame."""
        code = direction_codes(self.pts, self.grad, self.shape, self.codes)
        dist = self.fields.result()
        return Frame(
            edge_uv=self.pts.astype(np.float32),
            edge_grad=self.grad,
            edge_mag=self.mag,
            edge_depth=self.depth,
            dist=dist,
            edge_map=EdgeMap(dist[0], code, self.map_depth),
            depth=self.depth_image,
            gray=self.gray,
        )
