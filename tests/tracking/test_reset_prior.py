"""``Odometry.reset`` (a new start, bit for bit, nothing compiled again) and the per-frame
motion prior T_prev_cur (the start of the solve in place of constant velocity), on frames
of the bundled clip."""

from __future__ import annotations

import chex
import numpy as np
import pytest

from edgevo_jax import Config, Odometry
from edgevo_jax.cli import BUNDLED_CLIP
from edgevo_jax.datasets import load_sequence
from edgevo_jax.datasets.groundtruth import groundtruth_pose_at
from edgevo_jax.frontend.chunk import batch_of_one, track_next
from edgevo_jax.geometry import exp_np, inverse_np, predict_np, rotation_angle_np
from edgevo_jax.io import poses7_to_matrices
from edgevo_jax.tracking import effects as tracker_module


@pytest.fixture(scope="module")
def bundled():
    return load_sequence(BUNDLED_CLIP)


def gt_pose(seq, i: int) -> np.ndarray:
    """T_world_cam at frame i's own time (the ground truth interpolated)."""
    pose7 = groundtruth_pose_at(seq, float(seq.timestamps[i]), interpolate=True)
    return poses7_to_matrices(np.asarray(pose7)[None])[0]


def track_all(odo, frames, times, priors=None):
    priors = priors or [None] * len(frames)
    return [odo.track(rgb, d, t, prior=p) for (rgb, d), t, p in zip(frames, times, priors,
                                                                     strict=True)]


def test_reset_tracks_as_a_new_tracker_bit_for_bit(bundled, monkeypatch):
    """Six frames (keyframes, the window's refinements at its 4-frame lag), reset at
    another pose, the same frames again: the results of a new Odometry started there, bit
    for bit; the per-frame solve was traced once over all of it."""
    guarded = batch_of_one(chex.assert_max_traces(track_next, n=1))
    monkeypatch.setattr(tracker_module, "track_next_jit", guarded)
    config = Config(kf_max_interval_s=0.1)  # a keyframe every ~3 frames
    frames = [bundled.load_frame(i) for i in range(6)]
    times = list(bundled.timestamps[:6])
    start = gt_pose(bundled, 0)
    odo = Odometry(config, bundled.intrinsics)
    first = track_all(odo, frames, times)
    odo.reset(pose=start)
    again = track_all(odo, frames, times)  # timestamps start over: the old ones are gone
    fresh_odo = Odometry(config, bundled.intrinsics, initial_pose=start)
    fresh = track_all(fresh_odo, frames, times)
    assert odo.num_keyframes == fresh_odo.num_keyframes >= 2
    assert len(odo.refinements) == len(fresh_odo.refinements) >= 1
    for a, b in zip(again, fresh, strict=True):
        np.testing.assert_array_equal(a.pose, b.pose)
        assert (a.state, a.reason, a.inliers, a.keyframe, a.inlier_share) == (
            b.state, b.reason, b.inliers, b.keyframe, b.inlier_share)
        if b.covariance is not None:
            np.testing.assert_array_equal(a.covariance, b.covariance)
    # started elsewhere: the first run's trajectory is the same one, moved by ``start``
    np.testing.assert_allclose(again[-1].pose, start @ first[-1].pose, atol=1e-5)
    # reset() without a pose: the constructor's initial pose (identity here)
    odo.reset()
    np.testing.assert_array_equal(odo.track(*frames[0], times[0]).pose, np.eye(4))
    odo.close()
    fresh_odo.close()


def test_reset_refuses_a_pose_that_is_not_rigid(bundled):
    odo = Odometry(Config(), bundled.intrinsics)
    with pytest.raises(ValueError, match="pose has non-finite"):
        odo.reset(pose=np.full((4, 4), np.nan))
    with pytest.raises(ValueError, match="pose is not rigid"):
        odo.reset(pose=np.diag([1.0, 1.0, 3.0, 1.0]))


def test_a_lost_frame_takes_the_prior_in_place_of_constant_velocity(bundled):
    """A frame without edges is LOST at its prediction: T_w_prev @ prior with a prior, the
    constant-velocity pose without."""
    frames = [bundled.load_frame(i) for i in range(2)]
    blank = (np.zeros_like(frames[0][0]), frames[0][1])
    prior = exp_np(np.array([0.03, -0.02, 0.01, 0.02, 0.0, -0.01]))
    results = {}
    for key, p in (("prior", prior), ("none", None)):
        odo = Odometry(Config(mapping=False), bundled.intrinsics)
        done = track_all(odo, frames, bundled.timestamps[:2])
        results[key] = (done, odo.track(*blank, bundled.timestamps[2], prior=p))
    done, lost = results["prior"]
    assert lost.state == "LOST" and lost.reason == "no edges in the frame"
    np.testing.assert_allclose(lost.pose, done[-1].pose @ prior, atol=1e-12)
    done, lost = results["none"]
    np.testing.assert_allclose(lost.pose, predict_np(done[-1].pose, done[0].pose), atol=1e-12)


def test_a_ground_truth_prior_is_as_good_and_a_wrong_one_converges(bundled):
    """Frames 0, 4, 8, 4 at a 30 Hz clock: the motion reverses, which constant velocity
    predicts worst. With the ground-truth motion as the prior every frame is OK and the
    motions between frames are as close to the ground truth as without (0.5 mm slack: the
    minimum is that flat, solves from starts a few mm apart end ~0.5 mm apart); a
    prior 1.9 cm and 0.8 deg off the ground truth converges: each motion's error within
    1 mm of the ground-truth prior's."""
    idx = [0, 4, 8, 4]
    frames = [bundled.load_frame(i) for i in idx]
    times = [100.0 + k / 30 for k in range(len(idx))]
    gt = [gt_pose(bundled, i) for i in idx]
    truth = [None] + [inverse_np(a) @ b for a, b in zip(gt, gt[1:], strict=False)]
    off = exp_np(np.array([0.012, -0.01, 0.01, 0.01, 0.0, -0.01]))
    wrong = [None] + [t @ off for t in truth[1:]]

    def run(priors):
        with Odometry(Config(), bundled.intrinsics, initial_pose=gt[0]) as odo:
            return track_all(odo, frames, times, priors)

    def step_errors(results):
        poses = [r.pose for r in results]
        errs = [inverse_np(t) @ inverse_np(a) @ b
                for t, a, b in zip(truth[1:], poses[:-1], poses[1:], strict=True)]
        return np.array([np.linalg.norm(e[:3, 3]) for e in errs])

    plain, good, bad = run(None), run(truth), run(wrong)
    assert all(r.state == "OK" for r in good + bad)
    assert np.mean(step_errors(good)) <= np.mean(step_errors(plain)) + 5e-4
    # from 18.5 mm off to within 1 mm of where the ground-truth prior led
    assert np.linalg.norm(off[:3, 3]) > 0.018 and np.degrees(rotation_angle_np(off)) > 0.8
    assert np.max(np.abs(step_errors(bad) - step_errors(good))) < 1e-3


@pytest.mark.parametrize(("prior", "match"), [
    (np.full((4, 4), np.nan), "prior has non-finite"),
    (np.eye(4)[:3], "prior must be a 4x4"),
    (np.diag([1.0, 2.0, 1.0, 1.0]), "prior is not rigid"),
])
def test_a_bad_prior_is_named(bundled, prior, match):
    odo = Odometry(Config(), bundled.intrinsics)
    rgb = np.zeros((48, 64, 3), np.uint8)
    with pytest.raises(ValueError, match=match):
        odo.track(rgb, np.ones((48, 64), np.float32), 1.0, prior=prior)
