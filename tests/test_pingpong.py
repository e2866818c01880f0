"""Long sequences played back and forth from a clip: indices, timestamps, ground truth."""

from __future__ import annotations

import numpy as np
import pytest

from edgevo_jax.cli import BUNDLED_CLIP
from edgevo_jax.datasets import groundtruth_pose_at, load_sequence, pingpong, pingpong_indices


def test_indices_go_back_and_forth():
    assert pingpong_indices(4, 11).tolist() == [0, 1, 2, 3, 2, 1, 0, 1, 2, 3, 2]
    with pytest.raises(ValueError, match="cannot be played back and forth"):
        pingpong_indices(1, 3)


def test_pingpong_sequence_follows_the_clip():
    seq = load_sequence(BUNDLED_CLIP)
    n = len(seq)
    long = pingpong(seq, 3 * n)
    assert len(long) == 3 * n and long.name.endswith(f"pingpong{3 * n}")
    assert np.all(np.diff(long.timestamps) > 0)
    idx = pingpong_indices(n, 3 * n)
    assert long.rgb_files[n] == seq.rgb_files[n - 2]  # the first step back
    gt_t, gt_p = long.groundtruth
    np.testing.assert_array_equal(gt_t, long.timestamps)
    # each frame's ground truth is the clip's at that frame's original time (TUM's ground
    # truth runs at 100 Hz: the nearest sample is within ~5 ms of motion, ~2 mm here)
    for k in range(0, 3 * n, 5):
        near = groundtruth_pose_at(seq, float(seq.timestamps[idx[k]]))
        assert np.linalg.norm(gt_p[k, :3] - near[:3]) < 3e-3
    # frames come from the clip's files: loading one gives the clip's frame
    np.testing.assert_array_equal(long.load_frame(n)[1], seq.load_frame(n - 2)[1])


def test_pingpong_keeps_each_depth_images_time_to_its_colour_image(shared_clip):
    seq = load_sequence(shared_clip("rgbd_dataset_freiburg1_rpy_first120"))
    played = pingpong(seq, 300)
    lag = np.asarray(seq.depth_timestamps) - np.asarray(seq.timestamps)
    idx = pingpong_indices(len(seq), 300)
    assert played.depth_timestamps.shape == (300,)
    np.testing.assert_allclose(played.depth_timestamps - played.timestamps, lag[idx],
                               atol=1e-6)
