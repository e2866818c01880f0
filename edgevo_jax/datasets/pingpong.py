"""Long sequences from short clips: a clip played forward, then backward, again and again,
with fresh, evenly spaced timestamps (``pingpong``); or once there and once back on frames
the two passes do not share (``there_and_back``: a loop whose revisit sees no image seen
before). The motion stays continuous (it reverses at each end) and the ground truth
follows, so memory, drift and loops can be measured over any length."""

from __future__ import annotations

import dataclasses

import numpy as np

from .tum import TumSequence

#: a frame of ``there_and_back`` has ground truth where the clip's nearest sample is this close
#: in time (s): the association of the ATE (``runs.measure.GT_MAX_DIFF_S``)
GT_NEAREST_S = 0.02


def pingpong_indices(n: int, length: int) -> np.ndarray:
    """Frame indices 0, 1, .., n-1, n-2, .., 0, 1, .. (``length`` of them); (length,) int."""
    if n < 2:
        raise ValueError(f"a clip of {n} frame(s) cannot be played back and forth")
    period = 2 * (n - 1)
    k = np.arange(length) % period
    return np.where(k < n, k, period - k)


def _interpolate(gt_t: np.ndarray, gt_p: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Ground-truth poses7 (tx ty tz qx qy qz qw) at times t: positions linearly, rotations
    by normalised linear interpolation of the quaternions (on the same hemisphere)."""
    order = np.argsort(gt_t)
    gt_t, gt_p = gt_t[order], gt_p[order]
    k = np.clip(np.searchsorted(gt_t, t), 1, len(gt_t) - 1)
    t0, t1 = gt_t[k - 1], gt_t[k]
    a = np.clip((t - t0) / np.maximum(t1 - t0, 1e-12), 0.0, 1.0)[:, None]
    p0, p1 = gt_p[k - 1], gt_p[k]
    q1 = np.where(np.sum(p0[:, 3:] * p1[:, 3:], axis=1, keepdims=True) < 0, -p1[:, 3:],
                  p1[:, 3:])
    q = (1 - a) * p0[:, 3:] + a * q1
    return np.concatenate([(1 - a) * p0[:, :3] + a * p1[:, :3],
                           q / np.linalg.norm(q, axis=1, keepdims=True)], axis=1)


def pingpong(seq: TumSequence, length: int) -> TumSequence:
    """``seq`` played forward and backward to ``length`` frames. Frame k is the clip's frame
    ``pingpong_indices(len(seq), length)[k]`` at time t_0 + k * dt (dt: the clip's median
    frame interval), its depth image's time as far from it as in the clip; its ground truth
    (when the clip has one) is the clip's, interpolated at that frame's original timestamp.
    Nothing is copied: the frames are read from the clip's files."""
    if length < 1:
        raise ValueError(f"length must be positive, got {length}")
    idx = pingpong_indices(len(seq), length)
    dt = float(np.median(np.diff(seq.timestamps)))
    ts = float(seq.timestamps[0]) + dt * np.arange(length)
    gt = None
    if seq.groundtruth is not None:
        gt = (ts, _interpolate(*seq.groundtruth, np.asarray(seq.timestamps)[idx]))
    depth_t = None  # each depth image keeps its time relative to its colour image
    if seq.depth_timestamps is not None:
        lag = np.asarray(seq.depth_timestamps, np.float64) - np.asarray(seq.timestamps)
        depth_t = ts + lag[idx]
    return dataclasses.replace(
        seq, name=f"{seq.name}_pingpong{length}", timestamps=ts,
        rgb_files=tuple(seq.rgb_files[i] for i in idx),
        depth_files=tuple(seq.depth_files[i] for i in idx), groundtruth=gt,
        depth_timestamps=depth_t)


def there_and_back(seq: TumSequence, back: TumSequence | None = None) -> TumSequence:
    """Two passes over ``seq`` that share no image: its even frames forward, then its odd
    frames backward, ending near where it began (the revisit of a loop). The backward
    frames are read from ``back`` (another copy of the same clip, e.g. one with a biased
    depth: ``perturb.perturbed_copy(depth_scale=...)``; None: ``seq``). Frame k is at time
    t_0 + k * 2 dt (dt: the clip's median frame interval), its depth image as far from it
    as in the clip; its ground truth (when the clip has one) is the clip's, interpolated at
    that frame's original timestamp, where the clip's truth has a sample within
    ``GT_NEAREST_S`` of it (none is made up for frames before or after it). Nothing is
    copied. ValueError for a ``back`` of another length, or a clip of fewer than 4
    frames."""
    back = seq if back is None else back
    n = len(seq)
    if n < 4 or len(back) != n:
        raise ValueError(f"there and back needs a clip of 4 frames or more and a back copy "
                         f"of the same length, got {n} and {len(back)}")
    forward, backward = np.arange(0, n, 2), np.arange(n - 1 if n % 2 == 0 else n - 2, 0, -2)
    idx = np.concatenate([forward, backward])
    files = [(seq, i) for i in forward] + [(back, i) for i in backward]
    dt = 2.0 * float(np.median(np.diff(seq.timestamps)))
    ts = float(seq.timestamps[0]) + dt * np.arange(len(idx))
    gt = None
    if seq.groundtruth is not None:  # frames the truth does not reach have none
        original = np.asarray(seq.timestamps)[idx]
        gt_t = np.sort(np.asarray(seq.groundtruth[0], np.float64))
        k = np.clip(np.searchsorted(gt_t, original), 1, len(gt_t) - 1)
        near = np.minimum(np.abs(gt_t[k] - original), np.abs(gt_t[k - 1] - original))
        has = near <= GT_NEAREST_S
        gt = (ts[has], _interpolate(*seq.groundtruth, original[has]))
    depth_t = None
    if seq.depth_timestamps is not None:
        lag = np.asarray(seq.depth_timestamps, np.float64) - np.asarray(seq.timestamps)
        depth_t = ts + lag[idx]
    return dataclasses.replace(
        seq, name=f"{seq.name}_there_and_back", timestamps=ts,
        rgb_files=tuple(s.rgb_files[i] for s, i in files),
        depth_files=tuple(s.depth_files[i] for s, i in files), groundtruth=gt,
        depth_timestamps=depth_t)
