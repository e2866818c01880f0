"""Long sequences played back and forth from a clip (indices, timestamps, ground truth), and
once there and back on frames the passes do not share."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from edgevo_jax.cli import BUNDLED_CLIP
from edgevo_jax.datasets import (
    groundtruth_pose_at,
    load_sequence,
    pingpong,
    pingpong_indices,
    there_and_back,
)


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


def test_there_and_back_shares_no_image_and_reads_the_way_back_from_its_copy(tmp_path):
    seq = load_sequence(BUNDLED_CLIP)  # 9 associated frames
    loop = there_and_back(seq)
    n = len(seq)
    forward, backward = list(range(0, n, 2)), list(range(n - 2, 0, -2))
    assert [seq.rgb_files.index(f) for f in loop.rgb_files] == forward + backward
    assert not set(loop.rgb_files[:len(forward)]) & set(loop.rgb_files[len(forward):])
    assert np.all(np.diff(loop.timestamps) > 0)
    np.testing.assert_array_equal(loop.groundtruth[0], loop.timestamps)
    other = dataclasses.replace(seq, depth_files=tuple(tmp_path / f"d{i}.png"
                                                        for i in range(n)))
    mixed = there_and_back(seq, other)
    assert mixed.depth_files[:len(forward)] == loop.depth_files[:len(forward)]
    assert mixed.depth_files[len(forward):] == tuple(tmp_path / f"d{i}.png" for i in backward)
    with pytest.raises(ValueError, match="of the same length"):
        there_and_back(seq, dataclasses.replace(seq, rgb_files=seq.rgb_files[:4],
                                                depth_files=seq.depth_files[:4],
                                                timestamps=seq.timestamps[:4]))
