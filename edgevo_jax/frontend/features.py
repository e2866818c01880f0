"""Wide-baseline motion hypotheses from image features, for recovery and the keyframe map.

The edge alignment converges from a few pixels of its coarsest level; after a gap in the
stream or a fast turn the motion is far beyond that and no start made from the previous
motions is in its basin. Here SIFT keypoints of a keyframe and of a frame are matched
(Lowe's ratio test), the keyframe's keypoints back-projected with its depth, and the frame's
pose found by PnP inside RANSAC: a start for the edge alignment, which then refines it (the
result is judged like any other alignment). A keyframe map keeps a keyframe's keypoints
lifted to 3D (``Landmarks``) and finds a frame's pose from them (``landmark_pose``) without
the keyframe's images. Host-side, OpenCV, deterministic (OpenCV's RANSAC seeds its generator
per call); only recovery and the map call it.
"""

from __future__ import annotations

import threading
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


class Detections:
    """The keypoints of one uint8 gray image (H, W), each kind and count detected once
    (``detect``): the first ``get`` detects, every later one, on any thread, takes the same
    (one in progress on another thread is waited for). A keyframe's are shared by the
    recovery's feature start and the map's description of it; a frame's by the recovery,
    its confirmation and the map's query."""

    def __init__(self, gray: np.ndarray) -> None:
        self.gray = gray
        self._lock = threading.Lock()
        self._found: dict[tuple[str, int], Keypoints] = {}

    def get(self, kind: str, max_features: int = MAX_FEATURES) -> Keypoints:
        """The image's keypoints of ``kind`` ("sift", "orb"), at most ``max_features``."""
        with self._lock:
            key = (kind, max_features)
            if key not in self._found:
                self._found[key] = detect(self.gray, kind=kind, max_features=max_features)
            return self._found[key]


def _matches(a: np.ndarray, b: np.ndarray, ratio: float, min_matches: int
             ) -> tuple[np.ndarray, np.ndarray] | None:
    """Indices (into ``a``, into ``b``) of the descriptors matched by Lowe's ratio test
    (Hamming for binary descriptors, else L2); None when fewer than ``min_matches``."""
    if len(a) < 2 or len(b) < 2:
        return None
    norm = cv2.NORM_HAMMING if a.dtype == np.uint8 else cv2.NORM_L2
    pairs = cv2.BFMatcher(norm).knnMatch(a, b, k=2)
    good = [p[0] for p in pairs if len(p) == 2 and p[0].distance < ratio * p[1].distance]
    if len(good) < min_matches:
        return None
    return (np.array([m.queryIdx for m in good]), np.array([m.trainIdx for m in good]))


def relative_pose(
    kf: Keypoints, kf_depth: np.ndarray, cur: Keypoints, intr: Intrinsics, *,
    min_depth: float, max_depth: float, ratio: float = RATIO,
    reprojection_px: float = REPROJECTION_PX, min_inliers: int = MIN_INLIERS,
) -> np.ndarray | None:
    """T_cur_kf (4, 4, float64) from keypoints matched between a keyframe (with its depth
    (H, W) in metres; outside [min_depth, max_depth] or NaN = missing) and a frame, or None
    when fewer than ``min_inliers`` matches agree on one pose."""
    matched = _matches(kf.descriptors, cur.descriptors, ratio, min_inliers)
    if matched is None:
        return None
    q, t = matched
    pts, ok = _lift(kf.uv[q], kf_depth, intr, min_depth, max_depth)
    if ok.sum() < min_inliers:
        return None
    return _pnp(pts, cur.uv[t[ok]], intr, reprojection_px, min_inliers)


def _lift(uv: np.ndarray, depth: np.ndarray, intr: Intrinsics, min_depth: float,
          max_depth: float) -> tuple[np.ndarray, np.ndarray]:
    """Pixels uv (N, 2) back-projected with the depth (H, W, metres) at their nearest pixel:
    the points (M, 3) float64 of those with a depth in [min_depth, max_depth] and which
    those are (N,) bool."""
    h, w = depth.shape
    col = np.clip(np.rint(uv[:, 0]).astype(int), 0, w - 1)
    row = np.clip(np.rint(uv[:, 1]).astype(int), 0, h - 1)
    z = depth[row, col].astype(np.float64)
    ok = np.isfinite(z) & (z >= min_depth) & (z <= max_depth)
    fx, fy, cx, cy = (float(v) for v in intr)
    z = z[ok]
    pts = np.stack([(uv[ok, 0] - cx) / fx * z, (uv[ok, 1] - cy) / fy * z, z], axis=1)
    return pts.reshape(-1, 3), ok


class Landmarks(NamedTuple):
    """Keypoints of a keyframe lifted with its depth: xyz (N, 3) float64 metres in the
    keyframe's camera, their descriptors (N, D) (``Keypoints.descriptors``) and pixels
    uv (N, 2) float32. What a keyframe map keeps to find a frame's pose from features
    without the keyframe's images."""

    xyz: np.ndarray
    descriptors: np.ndarray
    uv: np.ndarray

    @property
    def nbytes(self) -> int:
        """Bytes held."""
        return int(self.xyz.nbytes + self.descriptors.nbytes + self.uv.nbytes)


def landmarks(kps: Keypoints, depth: np.ndarray, intr: Intrinsics, *, min_depth: float,
              max_depth: float) -> Landmarks:
    """The keypoints ``kps`` with a depth in [min_depth, max_depth] at their nearest pixel of
    ``depth`` (H, W, metres; NaN = missing), back-projected through ``intr``."""
    xyz, ok = _lift(kps.uv, depth, intr, min_depth, max_depth)
    return Landmarks(xyz, kps.descriptors[ok], kps.uv[ok])


class FeaturePose(NamedTuple):
    """A pose from matched features: T_cur_kf (4, 4, float64) and the matches that agree
    with it (RANSAC inliers)."""

    T_c_k: np.ndarray
    inliers: int


def landmark_pose(lm: Landmarks, cur: Keypoints, intr: Intrinsics, *, ratio: float = RATIO,
                  reprojection_px: float = REPROJECTION_PX, min_inliers: int = MIN_INLIERS
                  ) -> FeaturePose | None:
    """T_cur_kf from a keyframe's landmarks matched to a frame's keypoints (Lowe's ratio
    test, then EPnP in RANSAC), with its inlier count; None when fewer than ``min_inliers``
    matches agree on one pose."""
    matched = _matches(lm.descriptors, cur.descriptors, ratio, min_inliers)
    if matched is None:
        return None
    q, t = matched
    return _pnp(lm.xyz[q], cur.uv[t], intr, reprojection_px, min_inliers, count=True)


#: guided matching (``refine_pose``): the search radii (px) of its rounds, each round's pose
#: predicting the next's matches (ORB-SLAM's relocalisation searches by projection alike),
#: and the most bits two ORB descriptors may differ by to match (of 256; ORB-SLAM's
#: TH_HIGH is 100, its TH_LOW 50)
GUIDED_RADII_PX = (30.0, 15.0, 8.0)
GUIDED_MAX_BITS = 70
_POPCOUNT = np.unpackbits(np.arange(256, dtype=np.uint8)[:, None], axis=1).sum(axis=1)


def refine_pose(lm: Landmarks, cur: Keypoints, start: FeaturePose, intr: Intrinsics, *,
                reprojection_px: float = REPROJECTION_PX, min_inliers: int = MIN_INLIERS
                ) -> FeaturePose:
    """A feature pose refined by guided matching: each landmark projected at the pose is
    matched to the nearest-in-descriptor keypoint within a radius (``GUIDED_RADII_PX``,
    narrowing; at most ``GUIDED_MAX_BITS`` bits apart; one landmark per keypoint), and the
    pose solved again from every such match (EPnP in RANSAC, then Levenberg-Marquardt on
    the inliers). Far more matches than the ratio test leaves across a wide baseline, so a
    more accurate start. ORB (binary) landmarks only; ``start`` as it is where a round finds
    fewer than ``min_inliers``."""
    if lm.descriptors.dtype != np.uint8 or not len(cur.uv):
        return start
    fx, fy, cx, cy = (float(v) for v in intr)
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    xyz = lm.xyz.astype(np.float64)
    best = start
    for radius in GUIDED_RADII_PX:
        T = best.T_c_k
        p = xyz @ T[:3, :3].T + T[:3, 3]
        front = p[:, 2] > 1e-3
        z = np.where(front, p[:, 2], 1.0)
        uv = np.stack([fx * p[:, 0] / z + cx, fy * p[:, 1] / z + cy], axis=1)
        d2 = np.sum((uv[:, None, :] - cur.uv[None, :, :].astype(np.float64)) ** 2, axis=2)
        li, ki = np.nonzero((d2 < radius * radius) & front[:, None])
        bits = _POPCOUNT[np.bitwise_xor(lm.descriptors[li], cur.descriptors[ki])].sum(axis=1)
        keep = bits <= GUIDED_MAX_BITS
        li, ki, bits = li[keep], ki[keep], bits[keep]
        # the closest descriptor per landmark, then per keypoint (stable: ties by index)
        order = np.lexsort((ki, bits, li))
        li, ki, bits = li[order], ki[order], bits[order]
        first = np.r_[True, li[1:] != li[:-1]]
        li, ki, bits = li[first], ki[first], bits[first]
        order = np.lexsort((li, bits, ki))
        li, ki = li[order], ki[order]
        first = np.r_[True, ki[1:] != ki[:-1]]
        li, ki = li[first], ki[first]
        if len(li) < min_inliers:
            break
        found = _pnp(xyz[li], cur.uv[ki], intr, reprojection_px, min_inliers, count=True,
                     inliers_out=True)
        if found is None:
            break
        (T, n), inl = found
        rvec, tvec = cv2.Rodrigues(T[:3, :3])[0], T[:3, 3:].copy()
        rvec, tvec = cv2.solvePnPRefineLM(xyz[li][inl], cur.uv[ki][inl].astype(np.float64),
                                          K, None, rvec, tvec)
        T = np.eye(4)
        T[:3, :3] = cv2.Rodrigues(rvec)[0]
        T[:3, 3] = tvec[:, 0]
        if not np.all(np.isfinite(T)):
            break
        best = FeaturePose(T, n)
    return best


def _pnp(pts: np.ndarray, uv: np.ndarray, intr: Intrinsics, reprojection_px: float,
         min_inliers: int, *, count: bool = False, inliers_out: bool = False):
    """EPnP in RANSAC of 3D points (N, 3) in the keyframe's camera seen at pixels uv (N, 2):
    T_cur_kf, or None when fewer than ``min_inliers`` agree or the pose is not finite;
    ``count``: a ``FeaturePose`` with the inlier count instead; ``inliers_out``: with the
    inliers' indices (a pair)."""
    fx, fy, cx, cy = (float(v) for v in intr)
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    found, rvec, tvec, inliers = cv2.solvePnPRansac(
        pts, uv.astype(np.float64), K, None, reprojectionError=reprojection_px,
        iterationsCount=300, confidence=0.999, flags=cv2.SOLVEPNP_EPNP)
    if not found or inliers is None or len(inliers) < min_inliers:
        return None
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(rvec)[0]
    T[:3, 3] = tvec[:, 0]
    if not np.all(np.isfinite(T)):
        return None
    out = FeaturePose(T, len(inliers)) if count else T
    return (out, inliers[:, 0]) if inliers_out else out
