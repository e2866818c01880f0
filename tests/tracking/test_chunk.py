"""The scan tracker: the device-side prediction, and chunks of frames tracked in one call
giving the frame-by-frame driver's trajectory (to 1e-6 m; it is in fact bit-identical), with
the clips' rolling shutter (each frame's rate from its own time step)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from edgevo_jax import Config, Odometry
from edgevo_jax.cli import BUNDLED_CLIP
from edgevo_jax.datasets import load_sequence
from edgevo_jax.frontend.chunk import predict_matrix
from edgevo_jax.geometry import Pose
from edgevo_jax.image.preprocess import preprocess
from edgevo_jax.runs.run import dispatch_chunk, initial_pose, track_in_chunks

twists = st.lists(st.floats(-0.5, 0.5), min_size=6, max_size=6)


def _se3(twist) -> np.ndarray:
    return np.asarray(jaxlie.SE3.exp(jnp.asarray(twist, jnp.float64)).as_matrix(), np.float64)


@settings(max_examples=25, deadline=None)
@given(twists, twists, twists)
def test_prediction_in_keyframe_poses_is_world_constant_velocity(kf, prev, last):
    """A B^-1 A with A = T_(i-1)_kf, B = T_(i-2)_kf equals inv(T_w_pred) T_w_kf with
    T_w_pred = T_w_(i-1) T_w_(i-2)^-1 T_w_(i-1)."""
    with jax.enable_x64(True):
        T_w_kf, T_w_prev, T_w_last = _se3(kf), _se3(prev), _se3(last)
        inv = np.linalg.inv
        A, B = inv(T_w_last) @ T_w_kf, inv(T_w_prev) @ T_w_kf
        T_w_pred = T_w_last @ inv(T_w_prev) @ T_w_last
        np.testing.assert_allclose(np.asarray(predict_matrix(jnp.asarray(A), jnp.asarray(B))),
                                   inv(T_w_pred) @ T_w_kf, atol=1e-9)
        np.testing.assert_allclose(
            np.asarray(Pose.from_matrix(jnp.asarray(A), orthonormalise=None).inverse()
                       .as_matrix()), inv(A), atol=1e-12)


@pytest.fixture(scope="module")
def bundled_frames():
    seq = load_sequence(BUNDLED_CLIP)
    config = Config()
    frames = [preprocess(*seq.load_frame(i), config) for i in range(len(seq))]
    return seq, config, frames, [float(t) for t in seq.timestamps]


def _frame_by_frame(seq, config, frames, ts):
    odo = Odometry(config, seq.intrinsics, initial_pose=initial_pose(seq),
                   readout_s=seq.readout_s)
    return [odo.track_frame(f, t) for f, t in zip(frames, ts, strict=True)], odo


@pytest.mark.parametrize("size", [3, 8])
def test_scan_tracker_gives_the_frame_by_frame_trajectory(bundled_frames, size):
    """Chunks cut at keyframes and re-tracked: same poses, states and keyframes."""
    seq, config, frames, ts = bundled_frames
    ref, odo_ref = _frame_by_frame(seq, config, frames, ts)
    odo = Odometry(config, seq.intrinsics, initial_pose=initial_pose(seq),
                   readout_s=seq.readout_s)
    got = track_in_chunks(odo, frames, ts, size=size)
    assert odo_ref.num_keyframes >= 2  # the clip makes a keyframe part-way: chunks are cut
    assert [r.keyframe for r in got] == [r.keyframe for r in ref]
    assert [r.state for r in got] == [r.state for r in ref]
    err = np.abs(np.array([r.pose for r in got]) - np.array([r.pose for r in ref]))
    assert err[:, :3, 3].max() <= 1e-6 and err[:, :3, :3].max() <= 1e-6


def test_scan_tracker_on_a_longer_shared_clip(shared_clip):
    """60 frames of fr3_teddy (a keyframe every few frames, so many cut chunks)."""
    seq = load_sequence(shared_clip("rgbd_dataset_freiburg3_teddy_first200"))
    config = Config()
    frames = [preprocess(*seq.load_frame(i), config) for i in range(60)]
    ts = [float(t) for t in seq.timestamps[:60]]
    ref, odo_ref = _frame_by_frame(seq, config, frames, ts)
    odo = Odometry(config, seq.intrinsics, initial_pose=initial_pose(seq),
                   readout_s=seq.readout_s)
    got = track_in_chunks(odo, frames, ts, size=4)
    assert odo_ref.num_keyframes > 5
    err = np.abs(np.array([r.pose for r in got]) - np.array([r.pose for r in ref]))
    assert err[:, :3, 3].max() <= 1e-6


def test_chunk_errors(bundled_frames):
    seq, config, frames, ts = bundled_frames
    odo = Odometry(config, seq.intrinsics)
    with pytest.raises(RuntimeError, match="no keyframe yet"):
        odo.solve_inputs()
    with pytest.raises(ValueError, match="2 frames but 1 timestamps"):
        track_in_chunks(odo, frames[:2], ts[:1], size=2)
    odo.track_frame(frames[0], ts[0])
    with pytest.raises(ValueError, match="a chunk takes 1 to 2 frames"):
        dispatch_chunk(odo, frames[:3], 2, ts[:3])
