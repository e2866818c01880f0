"""Tracking state per frame (OK / WEAK / LOST with a reason), recovery after a loss, and the
streaming API under garbage input: never an exception from inside JAX, never a NaN pose."""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from edgevo_jax import Config, Intrinsics
from edgevo_jax.cli import BUNDLED_CLIP
from edgevo_jax.datasets import load_sequence
from edgevo_jax.tracking.odometry import LOST, OK, WEAK, Odometry


@pytest.fixture(scope="module")
def clip():
    seq = load_sequence(BUNDLED_CLIP)
    return seq, [seq.load_frame(i) for i in range(4)]


def _odometry(seq) -> Odometry:
    return Odometry(Config(), seq.intrinsics)


def test_black_frame_is_lost_with_a_predicted_pose_and_tracking_goes_on(clip):
    seq, frames = clip
    odo = _odometry(seq)
    r0 = odo.track(*frames[0], seq.timestamps[0])
    r1 = odo.track(*frames[1], seq.timestamps[1])
    black = odo.track(np.zeros_like(frames[2][0]), frames[2][1], seq.timestamps[2])
    assert (r0.state, r1.state) == (OK, OK)
    assert black.state == LOST and black.reason == "no edges in the frame"
    assert black.keyframe is None
    assert np.all(np.isfinite(black.pose)) and black.covariance is None
    # constant velocity: the lost frame continues the last motion (no jump)
    expected = r1.pose @ (np.linalg.inv(r0.pose) @ r1.pose)
    np.testing.assert_allclose(black.pose, expected, atol=1e-9)
    after = odo.track(*frames[3], seq.timestamps[3])
    assert after.state == OK and np.all(np.isfinite(after.pose))


def test_frame_without_depth_is_weak(clip):
    seq, frames = clip
    odo = _odometry(seq)
    odo.track(*frames[0], seq.timestamps[0])
    r = odo.track(frames[1][0], np.zeros_like(frames[1][1]), seq.timestamps[1])
    assert r.state == WEAK and r.reason.startswith("no depth")
    assert r.keyframe is None and np.all(np.isfinite(r.pose))


def test_a_wild_prediction_is_recovered_from_other_starts(clip):
    """A prediction 25 cm and 20 degrees off makes the first alignment fail; one of the
    recovery starts (the keyframe's own pose, the last frame's) finds the frame again."""
    seq, frames = clip
    ref = _odometry(seq)
    for i in range(3):
        good = ref.track(*frames[i], seq.timestamps[i])
    odo = _odometry(seq)
    odo.track(*frames[0], seq.timestamps[0])
    odo.track(*frames[1], seq.timestamps[1])
    wild = np.eye(4)
    c, s = np.cos(np.radians(20)), np.sin(np.radians(20))
    wild[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    wild[:3, 3] = [0.25, 0.0, 0.0]
    last = odo.state.motion.poses[-1]  # velocity = wild
    odo.state = dataclasses.replace(odo.state, motion=dataclasses.replace(
        odo.state.motion, poses=(last @ np.linalg.inv(wild), last)))
    r = odo.track(*frames[2], seq.timestamps[2])
    assert r.state in (OK, WEAK), r.reason
    assert np.linalg.norm(r.pose[:3, 3] - good.pose[:3, 3]) < 0.005


SMALL = Intrinsics(60.0, 60.0, 31.5, 23.5)


@st.composite
def garbage_frames(draw):
    seed = draw(st.integers(0, 2**31 - 1))
    kind = draw(st.sampled_from(["noise", "black", "white", "stripes"]))
    depth_kind = draw(st.sampled_from(["ok", "zero", "nan", "inf", "negative"]))
    rng = np.random.default_rng(seed)
    rgb = {"noise": rng.integers(0, 256, (48, 64, 3)), "black": np.zeros((48, 64, 3)),
           "white": np.full((48, 64, 3), 255),
           "stripes": np.repeat((np.arange(64) // 8 % 2 * 255)[None, :, None], 48, 0)
           .repeat(3, 2)}[kind].astype(np.uint8)
    depth = rng.uniform(0.5, 3.0, (48, 64)).astype(np.float32)
    if depth_kind == "zero":
        depth[:] = 0
    elif depth_kind != "ok":
        value = {"nan": np.nan, "inf": np.inf, "negative": -1.0}[depth_kind]
        depth[rng.random((48, 64)) < 0.5] = value
    return rgb, depth


@given(st.lists(garbage_frames(), min_size=2, max_size=5))
@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.too_slow])
def test_streaming_api_never_raises_and_never_writes_a_nan_pose(frames):
    odo = Odometry(Config(num_edges=64, min_inliers=5), SMALL)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for t, (rgb, depth) in enumerate(frames):
            r = odo.track(rgb, depth, float(t) * 0.03)
            assert r.state in (OK, WEAK, LOST)
            assert np.all(np.isfinite(r.pose))
            assert r.state == OK or r.reason


def test_timestamps_that_go_back_are_rejected(clip):
    seq, frames = clip
    odo = _odometry(seq)
    odo.track(*frames[0], 10.0)
    with pytest.raises(ValueError, match="does not increase"):
        odo.track(*frames[1], 9.5)


@pytest.mark.parametrize(("rgb", "depth", "message"), [
    (np.zeros((48, 64, 3), np.float32), np.ones((48, 64), np.float32), "rgb must be uint8"),
    (np.zeros((48, 64, 4), np.uint8), np.ones((48, 64), np.float32), "rgb must be uint8"),
    (np.zeros((48, 64, 3), np.uint8), np.ones((24, 32), np.float32), "but depth is 32x24"),
    (np.zeros((48, 64, 3), np.uint8), np.ones((48, 64), np.uint16), "divide by 5000"),
    (np.zeros((48, 64, 3), np.uint8), np.ones((48, 64, 1), np.float32), "depth must be float"),
])
def test_streaming_api_names_bad_arrays(rgb, depth, message):
    odo = Odometry(Config(), SMALL)
    with pytest.raises(ValueError, match=message):
        odo.track(rgb, depth, 0.0)


def test_streaming_api_rejects_a_change_of_image_size():
    odo = Odometry(Config(num_edges=64, min_inliers=5), SMALL)
    odo.track(np.zeros((48, 64, 3), np.uint8), np.ones((48, 64), np.float32), 0.0)
    with pytest.raises(ValueError, match="earlier frames were 64x48"):
        odo.track(np.zeros((24, 32, 3), np.uint8), np.ones((24, 32), np.float32), 0.1)
