"""The one record of every pose (``map.poses``): a refinement moves a keyframe and no frame; a
correction moves a keyframe and every frame hanging from it, in the order corrections came,
and none of another keyframe; a frame filled in takes later corrections on top."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from edgevo_jax.geometry import exp_np
from edgevo_jax.map import Poses

twists = st.lists(st.floats(-0.5, 0.5), min_size=6, max_size=6).map(np.array)


def at(x: float, yaw_deg: float = 0.0) -> np.ndarray:
    return exp_np(np.array([x, 0.0, 0.0, 0.0, np.radians(yaw_deg), 0.0]))


def test_a_refinement_moves_the_keyframe_and_no_frame():
    poses = Poses()
    poses.add_keyframe(0, at(0.0), 0.0)
    poses.add_frame(0, 0.1, at(0.1), lost=False)
    poses.refine(0, at(0.05))
    np.testing.assert_array_equal(poses.keyframe(0), at(0.05))
    np.testing.assert_array_equal(poses.pose(0), at(0.1))


@settings(max_examples=30, deadline=None)
@given(st.lists(twists, min_size=1, max_size=4), twists)
def test_corrections_move_the_frames_of_their_keyframe_in_order(corrections, frame_twist):
    poses = Poses()
    poses.add_keyframe(0, np.eye(4), 0.0)
    poses.add_keyframe(1, at(1.0), 1.0)
    reported = exp_np(frame_twist)
    poses.add_frame(0, 0.5, reported, lost=False)
    poses.add_frame(1, 1.5, at(1.5), lost=False)
    expected, kf = reported, np.eye(4)
    for twist in corrections:
        C = exp_np(twist)
        poses.move({0: C})
        expected, kf = C @ expected, C @ kf
    np.testing.assert_allclose(poses.pose(0), expected, atol=1e-12)
    np.testing.assert_allclose(poses.keyframe(0), kf, atol=1e-12)
    np.testing.assert_array_equal(poses.pose(1), at(1.5))  # another keyframe's: unmoved
    np.testing.assert_allclose(poses.poses(), np.stack([expected, at(1.5)]), atol=1e-12)


def test_a_frame_recorded_after_a_correction_does_not_take_it_again():
    poses = Poses()
    poses.add_keyframe(0, np.eye(4), 0.0)
    C = at(0.3, 10.0)
    poses.move({0: C})
    poses.add_frame(0, 0.1, at(0.2), lost=False)  # tracked from the moved keyframe
    np.testing.assert_array_equal(poses.pose(0), at(0.2))
    poses.move({0: C})
    np.testing.assert_allclose(poses.pose(0), C @ at(0.2), atol=1e-12)


def test_a_filled_frame_takes_later_corrections_on_top():
    poses = Poses()
    poses.add_keyframe(0, np.eye(4), 0.0)
    poses.add_frame(0, 0.1, at(9.0), lost=True)
    poses.move({0: at(1.0)})
    poses.fill(0, at(0.1))  # the path between the frames on either side, as they are now
    np.testing.assert_array_equal(poses.pose(0), at(0.1))
    poses.move({0: at(0.0, 3.0)})
    np.testing.assert_allclose(poses.pose(0), at(0.0, 3.0) @ at(0.1), atol=1e-12)


def test_orthonormalised_moves_and_the_errors_named():
    poses = Poses()
    poses.add_keyframe(2, np.eye(4), 0.0)
    assert 2 in poses and 0 not in poses and poses.keyframe_time(2) == 0.0
    skew = np.eye(4)
    skew[0, 1] = 1e-3  # a correction that is not quite a rotation
    poses.move({2: skew}, orthonormalise=True)
    R = poses.keyframe(2)[:3, :3]
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    with pytest.raises(ValueError, match="has a pose already"):
        poses.add_keyframe(2, np.eye(4), 0.0)
    with pytest.raises(KeyError, match="keyframe 5"):
        poses.keyframe(5)
    poses.add_keyframe(200, np.eye(4), 1.0)  # ids far apart: the record grows
    assert poses.keyframes([2, 200]).shape == (2, 4, 4)
    frame = poses.add_frame(None, 0.0, np.eye(4), lost=True)  # no keyframe yet
    poses.move({2: at(1.0)})
    np.testing.assert_array_equal(poses.pose(frame), np.eye(4))
