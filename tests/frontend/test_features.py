"""Feature poses for the keyframe map (``frontend.features``): landmarks are keypoints with
depth, back-projected; the landmark pose of a real pair is near its ground truth, guided
matching brings it nearer with more matches, and a pose from another scene is refused."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from edgevo_jax.datasets import BUNDLED_CLIP, load_sequence
from edgevo_jax.frontend.features import (
    MIN_INLIERS,
    Keypoints,
    detect,
    landmark_pose,
    landmarks,
    refine_pose,
    relative_pose,
)
from edgevo_jax.geometry import inverse_np, rotation_angle_np
from edgevo_jax.runs.measure import groundtruth_at


@pytest.fixture(scope="module")
def clip():
    seq = load_sequence(BUNDLED_CLIP)
    frames = [seq.rectify_frame(*seq.decode_frame(i)) for i in (0, 8)]
    gray = [cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY) for rgb, _ in frames]
    return seq, gray, [d for _, d in frames], groundtruth_at(seq, seq.timestamps[[0, 8]])


def error(T: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    E = inverse_np(T_true) @ T
    return float(np.linalg.norm(E[:3, 3])), float(np.degrees(rotation_angle_np(E)))


def test_landmarks_are_the_keypoints_with_depth_back_projected(clip):
    seq, gray, depth, _ = clip
    kps = detect(gray[0], kind="orb")
    lm = landmarks(kps, depth[0], seq.intrinsics, min_depth=0.1, max_depth=8.0)
    assert 0 < len(lm.xyz) <= len(kps.uv) and lm.descriptors.shape == (len(lm.xyz), 32)
    fx, fy, cx, cy = seq.intrinsics
    np.testing.assert_allclose(fx * lm.xyz[:, 0] / lm.xyz[:, 2] + cx, lm.uv[:, 0], atol=1e-4)
    col, row = np.rint(lm.uv).astype(int).T
    np.testing.assert_allclose(lm.xyz[:, 2], depth[0][row, col], rtol=1e-6)
    assert lm.nbytes == lm.xyz.nbytes + lm.descriptors.nbytes + lm.uv.nbytes


def test_the_landmark_pose_finds_the_true_motion_and_guided_matching_refines_it(clip):
    seq, gray, depth, gt = clip
    T_true = inverse_np(gt[1]) @ gt[0]  # T_8_0
    lm = landmarks(detect(gray[0], kind="orb"), depth[0], seq.intrinsics, min_depth=0.1,
                   max_depth=8.0)
    cur = detect(gray[1], kind="orb", max_features=2000)
    start = landmark_pose(lm, cur, seq.intrinsics)
    assert start is not None and start.inliers >= MIN_INLIERS
    t0, r0 = error(start.T_c_k, T_true)
    assert t0 < 0.03 and r0 < 1.5
    refined = refine_pose(lm, cur, start, seq.intrinsics)
    t1, r1 = error(refined.T_c_k, T_true)
    assert refined.inliers > start.inliers
    assert t1 < 0.02 and r1 < 1.0
    # the same matches as the recovery's pose, which lifts its matches after the ratio test
    again = relative_pose(detect(gray[0], kind="orb"), depth[0], cur, seq.intrinsics,
                          min_depth=0.1, max_depth=8.0)
    assert again is not None and error(again, T_true)[0] < 0.05


def test_no_pose_from_another_scene(clip):
    seq, gray, depth, _ = clip
    lm = landmarks(detect(gray[0], kind="orb"), depth[0], seq.intrinsics, min_depth=0.1,
                   max_depth=8.0)
    rng = np.random.default_rng(0)
    noise = rng.integers(0, 256, gray[1].shape, dtype=np.uint8)
    assert landmark_pose(lm, detect(cv2.GaussianBlur(noise, (3, 3), 1.0), kind="orb"),
                         seq.intrinsics) is None
    empty = Keypoints(np.zeros((0, 2), np.float32), np.zeros((0, 32), np.uint8))
    assert landmark_pose(lm, empty, seq.intrinsics) is None
