"""Wide-baseline motion hypotheses from image features, for recovery.

The edge alignment converges from a few pixels of its coarsest level; after a gap in the
stream or a fast turn the motion is far beyond that and no start made from the previous
motions is in its basin. Here SIFT keypoints of a keyframe and of a frame are matched
(Lowe's ratio test), the keyframe's keypoints back-projected with its depth, and the frame's
pose found by PnP inside RANSAC: a start for the edge alignment, which then refines it (the
result is judged like any other alignment). Host-side, OpenCV, deterministic (OpenCV's RANSAC
seeds its generator per call); only recovery calls it.
"""

from __future__ import annotations

from typing import NamedTuple

import cv2
import numpy as np

from ..camera import Intrinsics

#: SIFT keypoints kept per image (the strongest): enough for PnP on TUM's 640x480 frames in
#: ~40 ms per image, which only recovering frames pay
MAX_FEATURES = 1000
#: Lowe's ratio test (his paper's 0.8: it keeps most correct matches, few wrong ones)
RATIO = 0.8
#: RANSAC's inlier threshold (px) and the fewest inliers a pose is trusted on
REPROJECTION_PX = 3.0
MIN_INLIERS = 15


class Keypoints(NamedTuple):
    """SIFT keypoints of one image: uv (N, 2) float32 pixels (column, row) and their
    descriptors (N, 128) float32."""

    uv: np.ndarray
    descriptors: np.ndarray


def detect(gray: np.ndarray, *, max_features: int = MAX_FEATURES,
           kind: str = "sift") -> Keypoints:
    """Keypoints of a uint8 gray image (H, W); empty arrays when it has none. ``kind``:
    "sift" (descriptors (N, 128) float32; ~40 ms per 640x480 image) or "orb" (binary,
    (N, 32) uint8, matched by Hamming distance; ~8 ms, but too few matches across the
    widest motions, where SIFT still finds a pose)."""
    if gray.dtype != np.uint8 or gray.ndim != 2:
        raise ValueError(f"gray must be uint8 (H, W), got {gray.dtype} {gray.shape}")
    if kind not in ("sift", "orb"):
        raise ValueError(f"kind must be 'sift' or 'orb', got {kind!r}")
    make = cv2.SIFT_create if kind == "sift" else cv2.ORB_create
    kps, desc = make(max_features).detectAndCompute(gray, None)
    width, dtype = (128, np.float32) if kind == "sift" else (32, np.uint8)
    if desc is None or not kps:
        return Keypoints(np.zeros((0, 2), np.float32), np.zeros((0, width), dtype))
    return Keypoints(np.array([k.pt for k in kps], np.float32), desc.astype(dtype))


def relative_pose(
    kf: Keypoints, kf_depth: np.ndarray, cur: Keypoints, intr: Intrinsics, *,
    min_depth: float, max_depth: float, ratio: float = RATIO,
    reprojection_px: float = REPROJECTION_PX, min_inliers: int = MIN_INLIERS,
) -> np.ndarray | None:
    """T_cur_kf (4, 4, float64) from keypoints matched between a keyframe (with its depth
    (H, W) in metres; outside [min_depth, max_depth] or NaN = missing) and a frame, or None
    when fewer than ``min_inliers`` matches agree on one pose."""
    if len(kf.uv) < 2 or len(cur.uv) < 2:
        return None
    norm = cv2.NORM_HAMMING if kf.descriptors.dtype == np.uint8 else cv2.NORM_L2
    pairs = cv2.BFMatcher(norm).knnMatch(kf.descriptors, cur.descriptors, k=2)
    good = [p[0] for p in pairs if len(p) == 2 and p[0].distance < ratio * p[1].distance]
    if len(good) < min_inliers:
        return None
    q = np.array([m.queryIdx for m in good])
    t = np.array([m.trainIdx for m in good])
    uv = kf.uv[q]
    h, w = kf_depth.shape
    col = np.clip(np.rint(uv[:, 0]).astype(int), 0, w - 1)
    row = np.clip(np.rint(uv[:, 1]).astype(int), 0, h - 1)
    z = kf_depth[row, col].astype(np.float64)
    ok = np.isfinite(z) & (z >= min_depth) & (z <= max_depth)
    if ok.sum() < min_inliers:
        return None
    fx, fy, cx, cy = (float(v) for v in intr)
    z = z[ok]
    pts = np.stack([(uv[ok, 0] - cx) / fx * z, (uv[ok, 1] - cy) / fy * z, z], axis=1)
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    found, rvec, tvec, inliers = cv2.solvePnPRansac(
        pts, cur.uv[t[ok]].astype(np.float64), K, None, reprojectionError=reprojection_px,
        iterationsCount=300, confidence=0.999, flags=cv2.SOLVEPNP_EPNP)
    if not found or inliers is None or len(inliers) < min_inliers:
        return None
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(rvec)[0]
    T[:3, 3] = tvec[:, 0]
    return T if np.all(np.isfinite(T)) else None
