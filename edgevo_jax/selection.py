"""Which keyframe edges the tracker uses.

EdgeVO "Edge Culling": an edge is a candidate only with valid depth and a gradient magnitude of
at least the Canny high threshold. The candidates are then packed into a fixed number of slots
(``Config.max_edges``) with a validity mask, so that the tracker compiles once; when there are
more candidates than slots, a seeded uniform subset is kept.
"""

from __future__ import annotations

import numpy as np

from .config import Config
from .preprocess import Frame
from .solve import KeyframeEdges


def cull(frame: Frame, config: Config) -> np.ndarray:
    """Indices of the frame's edges with valid depth and magnitude >= canny_high."""
    keep = (frame.edge_depth > 0) & (frame.edge_mag >= config.canny_high)
    return np.flatnonzero(keep)


def pack_edges(frame: Frame, idx: np.ndarray, size: int, seed: int) -> KeyframeEdges:
    """Edges ``idx`` of ``frame`` in ``size`` slots (numpy): a seeded subset when too many,
    padding with valid=False when too few. Kept in raster order for cache-friendly lookups."""
    if idx.size > size:
        idx = np.sort(np.random.default_rng(seed).choice(idx, size, replace=False))
    n = idx.size
    uv = np.zeros((2, size), np.float32)
    rho = np.ones(size, np.float32)
    grad = np.zeros((2, size), np.float32)
    valid = np.zeros(size, bool)
    uv[:, :n] = frame.edge_uv[idx].T
    rho[:n] = 1.0 / frame.edge_depth[idx]
    grad[:, :n] = frame.edge_grad[idx].T
    valid[:n] = True
    return KeyframeEdges(uv=uv, rho=rho, grad=grad, valid=valid)


def keyframe_edges(frame: Frame, config: Config, seed: int) -> KeyframeEdges:
    """The culled edges of a keyframe, packed into ``config.max_edges`` slots."""
    return pack_edges(frame, cull(frame, config), config.max_edges, seed)
