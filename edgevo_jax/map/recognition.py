"""Place recognition by randomised ferns: each keyframe's appearance as a short binary code,
compared with a frame's in well under a millisecond over a thousand keyframes.

The method is Glocker, Shotton, Criminisi and Izadi's ("Real-time RGB-D camera relocalization
via randomized ferns for keyframe encoding", IEEE TVCG 2015; the relocaliser of ElasticFusion
and InfiniTAM). The image is cut down to a blurred 80 x 60 thumbnail of intensity and depth;
each of ``NUM_FERNS`` ferns reads ``TESTS`` fixed pixels of it, each against a fixed
threshold on one channel (intensity or depth), and its code is the bits of those tests. Two
images are alike by the share of ferns whose codes agree (``similarity``).

Why ferns and not a bag of binary words: ferns need no vocabulary learnt offline (a
vocabulary is trained on images like the user's, and the shared clips are the only images
here, which the held-out evaluation forbids tuning to); they were made for RGB-D keyframes;
a code is ``NUM_FERNS`` bytes. What they lack is invariance to large changes of viewpoint:
they find keyframes taken from near the frame's view, and the geometry check after them
(features matched with PnP, then the edge alignment: ``tracking.places``) is what
accepts or refuses a place.

Host side, numpy + OpenCV; deterministic: the ferns are drawn once from a fixed seed.
"""

from __future__ import annotations

from typing import NamedTuple

import cv2
import numpy as np

__all__ = ["NUM_FERNS", "TESTS", "THUMBNAIL", "Ferns", "encode", "make_ferns", "similarity",
           "thumbnail"]

#: the thumbnail (width, height): Glocker et al.'s 1/8 of VGA; a frame of another size is
#: resized to it (its aspect ratio is not kept: both frames and keyframes come from one camera)
THUMBNAIL = (80, 60)
#: Gaussian blur of the thumbnail (its pixels): Glocker et al.'s sigma, so that a view a few
#: thumbnail pixels away (a few degrees of rotation) still gives most of the same bits
BLUR_SIGMA = 2.5
#: ferns per code and binary tests per fern: Glocker et al. found 500 ferns of 4 tests (RGB-D)
#: enough for keyframe retrieval; a code is 500 bytes
NUM_FERNS = 500
TESTS = 4
#: the depth thresholds are drawn in this range (m): the span of a Kinect-type sensor indoors
#: (Glocker et al.: 0.8-4 m)
DEPTH_RANGE = (0.8, 4.0)
#: the seed the ferns are drawn from: one fixed set for every map (codes of two runs compare)
SEED = 2015


class Ferns(NamedTuple):
    """The ferns' tests: for fern f and test j, the thumbnail pixel (row[f, j], col[f, j]),
    the channel (0: intensity 0-255, 1: depth in metres) and the threshold; the test's bit is
    1 when the pixel's value on that channel exceeds the threshold (a missing depth never
    does)."""

    row: np.ndarray
    col: np.ndarray
    channel: np.ndarray
    threshold: np.ndarray


def make_ferns(*, num_ferns: int = NUM_FERNS, tests: int = TESTS, seed: int = SEED) -> Ferns:
    """``num_ferns`` ferns of ``tests`` tests each, at uniformly drawn thumbnail pixels and
    channels, with thresholds drawn uniformly over intensity 0-255 or ``DEPTH_RANGE``."""
    if num_ferns < 1 or not 1 <= tests <= 8:
        raise ValueError(f"need num_ferns >= 1 and 1 <= tests <= 8 (one byte per code), got "
                         f"{num_ferns} and {tests}")
    rng = np.random.default_rng(seed)
    w, h = THUMBNAIL
    shape = (num_ferns, tests)
    channel = rng.integers(0, 2, shape)
    lo, hi = DEPTH_RANGE
    threshold = np.where(channel == 0, rng.uniform(0.0, 255.0, shape),
                         rng.uniform(lo, hi, shape)).astype(np.float32)
    return Ferns(rng.integers(0, h, shape), rng.integers(0, w, shape), channel, threshold)


def thumbnail(gray: np.ndarray, depth: np.ndarray | None) -> np.ndarray:
    """(2, 60, 80) float32: the blurred thumbnail of the uint8 gray image (H, W) and of the
    depth image (H, W, metres; 0 or NaN missing: 0 in the thumbnail, where a pixel's area
    holds no depth). ValueError for images of other kinds or sizes."""
    if gray.dtype != np.uint8 or gray.ndim != 2:
        raise ValueError(f"gray must be uint8 (H, W), got {gray.dtype} {gray.shape}")
    if depth is not None and depth.shape != gray.shape:
        raise ValueError(f"depth {depth.shape} and gray {gray.shape} differ in size")
    size = THUMBNAIL
    g = cv2.GaussianBlur(cv2.resize(gray.astype(np.float32), size, interpolation=cv2.INTER_AREA),
                         (0, 0), BLUR_SIGMA)
    if depth is None:
        return np.stack([g, np.zeros_like(g)])
    d = np.nan_to_num(np.asarray(depth, np.float32), nan=0.0, posinf=0.0, neginf=0.0)
    seen = (d > 0).astype(np.float32)
    # the mean of the measured depths under each thumbnail pixel (a missing depth is no 0 m)
    d_sum = cv2.GaussianBlur(cv2.resize(d, size, interpolation=cv2.INTER_AREA), (0, 0),
                             BLUR_SIGMA)
    n_sum = cv2.GaussianBlur(cv2.resize(seen, size, interpolation=cv2.INTER_AREA), (0, 0),
                             BLUR_SIGMA)
    d = np.where(n_sum > 0.5, d_sum / np.maximum(n_sum, 1e-6), 0.0).astype(np.float32)
    return np.stack([g, d])


def encode(ferns: Ferns, gray: np.ndarray, depth: np.ndarray | None) -> np.ndarray:
    """The image's code: (num_ferns,) uint8, fern f's tests as bits 0 .. tests - 1."""
    thumb = thumbnail(gray, depth)
    values = thumb[ferns.channel, ferns.row, ferns.col]
    bits = (values > ferns.threshold).astype(np.uint8)
    return (bits << np.arange(bits.shape[1], dtype=np.uint8)).sum(axis=1, dtype=np.uint8)


def similarity(codes: np.ndarray, code: np.ndarray) -> np.ndarray:
    """The share of ferns whose codes agree (0-1), of each row of ``codes`` (N, F) with
    ``code`` (F,): (N,) float64 (Glocker et al.'s block-wise Hamming distance, as 1 minus
    it)."""
    codes = np.asarray(codes)
    if codes.ndim != 2 or codes.shape[1:] != np.shape(code):
        raise ValueError(f"codes {codes.shape} and code {np.shape(code)} do not match")
    return np.count_nonzero(codes == code, axis=1) / codes.shape[1]
