"""The local window beside tracking (pipeline/mapping.py): the refined keyframe pose is taken
at a fixed frame lag whatever the worker's speed, and every program is compiled or loaded
before the first tracked frame (Odometry._warm_up)."""

from __future__ import annotations

import logging
import time

import jax
import numpy as np
import pytest
from conftest import shared_tum_dir

from edgevo_jax import Config
from edgevo_jax.datasets import load_sequence
from edgevo_jax.frontend import features
from edgevo_jax.image.preprocess import preprocess, to_gray
from edgevo_jax.tracking.odometry import Odometry
from edgevo_jax.window import sliding as local_map

TEDDY = "rgbd_dataset_freiburg3_teddy_first200"
#: a small window that fills after three keyframes (refinement and marginalisation run)
SMALL = Config(window_size=3)
FRAMES = 30


@pytest.fixture(scope="module")
def teddy_frames():
    clip = shared_tum_dir() / TEDDY
    if not clip.is_dir():
        pytest.skip(f"../shared/data/tum not found: {clip}")
    seq = load_sequence(clip)
    return seq, [seq.load_frame(i) for i in range(FRAMES)]


def _track(seq, frames, config: Config) -> tuple[np.ndarray, int]:
    with Odometry(config, seq.intrinsics) as odo:
        poses = np.stack([odo.track(*f, seq.timestamps[i]).pose for i, f in enumerate(frames)])
        return poses, odo.num_keyframes


def test_a_slow_worker_changes_nothing(teddy_frames, monkeypatch):
    """The window's result is taken at a fixed frame lag: a worker made slower (a random
    sleep before each step) gives the same poses bit for bit; taken inline (lag 0) the
    poses differ (the lag is real) but stay within 1 cm."""
    seq, frames = teddy_frames
    config = SMALL.replace(mapping_lag=2)
    fast, keyframes = _track(seq, frames, config)
    assert keyframes > config.window_size  # the window filled, refined and marginalised
    step = local_map.SlidingWindow.add_keyframe
    rng = np.random.default_rng(0)

    def slow(self, *args, **kwargs):
        time.sleep(float(rng.uniform(0.0, 0.05)))
        return step(self, *args, **kwargs)

    monkeypatch.setattr(local_map.SlidingWindow, "add_keyframe", slow)
    slowed, _ = _track(seq, frames, config)
    monkeypatch.setattr(local_map.SlidingWindow, "add_keyframe", step)
    assert np.array_equal(fast, slowed)
    inline, _ = _track(seq, frames, config.replace(mapping_lag=0))
    gap = np.linalg.norm(inline[:, :3, 3] - fast[:, :3, 3], axis=1)
    assert gap.max() > 0 and gap.max() < 0.01


@pytest.mark.parametrize("kept", [False, True], ids=["jit", "kept"])
def test_nothing_compiles_after_the_first_frame(teddy_frames, caplog, kept, tmp_path,
                                                request):
    """With shapes no other test uses (fresh programs), the first frame compiles (the
    warm-up) and the later ones, keyframes, window refinement and marginalisation included,
    compile nothing."""
    seq, frames = teddy_frames
    config = SMALL.replace(num_edges=320 + 8 * kept, active_per_keyframe=96, mapping_lag=1)
    done = [preprocess(*f, config) for f in frames]
    if kept:  # programs exported and stored (edgevo_jax.programs), as in `edgevo run`
        request.getfixturevalue("kept_programs")
    with Odometry(config, seq.intrinsics) as odo:
        with jax.log_compiles(True), caplog.at_level(logging.WARNING):
            odo.track_frame(done[0], seq.timestamps[0])
            first = [r for r in caplog.records if "Compiling" in r.getMessage()]
            caplog.clear()
            for i in range(1, FRAMES):
                odo.track_frame(done[i], seq.timestamps[i])
        later = [r.getMessage()[:80] for r in caplog.records if "Compiling" in r.getMessage()]
        assert odo.num_keyframes > config.window_size
    assert first and not later
    assert any(tmp_path.glob("exported/*.bin")) == kept


def test_mapping_lag_must_not_be_negative():
    with pytest.raises(ValueError, match="mapping_lag"):
        Config(mapping_lag=-1)


def test_orb_start_between_nearby_frames(teddy_frames):
    """ORB keypoints (binary, matched by Hamming distance) give a pose within 3 cm of
    SIFT's between teddy frames 10 apart; unknown kinds are refused."""
    seq, frames = teddy_frames
    (rgb0, d0), (rgb1, _) = frames[0], frames[10]
    kp0 = features.detect(to_gray(rgb0), kind="orb")
    assert kp0.descriptors.dtype == np.uint8 and kp0.descriptors.shape[1] == 32
    T = features.relative_pose(kp0, d0, features.detect(to_gray(rgb1), kind="orb"),
                               seq.intrinsics, min_depth=0.1, max_depth=8.0)
    sift = features.relative_pose(
        features.detect(to_gray(rgb0)), d0, features.detect(to_gray(rgb1)), seq.intrinsics,
        min_depth=0.1, max_depth=8.0)
    assert T is not None and sift is not None
    assert np.linalg.norm(T[:3, 3] - sift[:3, 3]) < 0.03
    with pytest.raises(ValueError, match="kind"):
        features.detect(to_gray(rgb0), kind="akaze")
