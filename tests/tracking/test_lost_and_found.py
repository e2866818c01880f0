"""The keyframe map in a run (``Config.map``): a covered lens is LOST, the first frame after
it is found again in the map and placed near the truth, the frames covered are filled in
between, and the trajectory file holds the moved poses; ``locate`` finds a frame of the
scene and refuses a frame of another scene."""

from __future__ import annotations

import warnings

import cv2
import numpy as np
import pytest

from edgevo_jax import Config, Odometry, load_sequence, run
from edgevo_jax.datasets import BUNDLED_CLIP, subsequence
from edgevo_jax.datasets.cover import covered_copy
from edgevo_jax.datasets.tum import EmptyDepthWarning
from edgevo_jax.io import read_trajectory
from edgevo_jax.runs.measure import groundtruth_at, pose_errors

TEDDY = "rgbd_dataset_freiburg3_teddy_first200"


def test_a_covered_copy_is_black_and_empty_where_asked(tmp_path):
    dst = tmp_path / "rgbd_dataset_freiburg1_xyz_covered"
    times = covered_copy(BUNDLED_CLIP, dst, [2, 3])
    seq, src = load_sequence(dst), load_sequence(BUNDLED_CLIP)
    assert times == [float(src.timestamps[2]), float(src.timestamps[3])]
    np.testing.assert_array_equal(seq.timestamps, src.timestamps)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", EmptyDepthWarning)
        rgb, depth = seq.decode_frame(2)
    assert not rgb.any() and not np.any(depth > 0)
    rgb, depth = seq.decode_frame(4)
    assert np.array_equal(rgb, src.decode_frame(4)[0])
    with pytest.raises(ValueError, match="frame 9 is outside"):
        covered_copy(BUNDLED_CLIP, tmp_path / "other", [9])
    with pytest.raises(FileExistsError):
        covered_copy(BUNDLED_CLIP, dst, [1])


@pytest.mark.slow
def test_a_hand_over_the_lens_is_lost_then_found_again(shared_clip, tmp_path):
    covered = tmp_path / f"{TEDDY}_covered"
    covered_copy(shared_clip(TEDDY), covered, range(100, 130))
    seq = subsequence(load_sequence(covered), 0, 150)
    out = tmp_path / "traj.txt"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", EmptyDepthWarning)
        r = run(seq, Config(), out=out, progress=False)
    states = [x.state for x in r.results]
    assert set(states[100:130]) == {"LOST"}
    gt = groundtruth_at(seq, seq.timestamps)
    trans, rot = pose_errors(r.poses, gt, range(100))
    after = range(130, 145)  # within 0.5 s: the first frame called OK is right
    first = next(i for i in after if states[i] == "OK")
    assert trans[first] < 0.02 and rot[first] < 2.0
    assert any(x.placed and x.placed.startswith("found again") for x in r.results[130:145])
    ok_after = [i for i in range(first, 150) if states[i] == "OK"]
    assert ok_after and max(trans[ok_after]) < 0.02 and max(rot[ok_after]) < 2.0
    # the frames covered were filled in between: better than the pose held through them
    assert r.corrections and max(trans[100:130]) < 0.1
    t, poses7 = read_trajectory(out)
    np.testing.assert_allclose(poses7[:, :3], r.poses[:, :3, 3], atol=1e-6)


def test_locate_finds_the_scene_and_refuses_another(shared_clip):
    seq = load_sequence(BUNDLED_CLIP)
    frames = [seq.rectify_frame(*seq.decode_frame(i)) for i in range(len(seq))]
    odo = Odometry(Config(), seq.intrinsics)
    assert odo.locate(*frames[0]) is None  # an empty map finds nothing
    poses = [odo.track(rgb, d, float(t)).pose
             for (rgb, d), t in zip(frames, seq.timestamps, strict=True)]
    odo.close()
    assert len(odo.keyframe_map) == odo.num_keyframes
    found = odo.locate(*frames[4])
    assert found is not None and found.note.startswith("found again")
    pose = found.keyframe.pose @ np.linalg.inv(np.asarray(found.result.T_c_k, np.float64))
    assert np.linalg.norm(pose[:3, 3] - poses[4][:3, 3]) < 0.01
    other = load_sequence(shared_clip(TEDDY))  # another room, another desk
    rgb, depth = other.rectify_frame(*other.decode_frame(0))
    assert odo.locate(rgb, depth) is None
    noise = cv2.GaussianBlur(np.random.default_rng(0).integers(0, 256, rgb.shape, np.uint8),
                             (5, 5), 2.0)
    assert odo.locate(noise, depth) is None
    with pytest.raises(ValueError, match="earlier frames were"):
        odo.locate(rgb[:-2], depth[:-2])
