"""The frames the keyframe map may still move (``map.ledger``) over the record of poses
(``map.poses``): LOST frames between two settled ones are filled in along the motion between
them, by time; a guessed chain moves with its keyframes (each frame hangs from its
keyframe); nothing else moves; a correction after a fill moves the filled frame too."""

from __future__ import annotations

import numpy as np

from edgevo_jax.geometry import exp_np
from edgevo_jax.map import Poses
from edgevo_jax.map.ledger import Ledger


def at(x: float, yaw_deg: float = 0.0) -> np.ndarray:
    return exp_np(np.array([x, 0.0, 0.0, 0.0, np.radians(yaw_deg), 0.0]))


def record(poses: Poses, ledger: Ledger, t: float, pose: np.ndarray, *, kf: int = 0,
           lost: bool = False, settled: bool = False, moved=frozenset()):
    index = poses.add_frame(kf, t, pose, lost=lost)
    return ledger.record(index, settled=settled, moved=frozenset(moved))


def test_lost_frames_are_filled_in_by_time_between_the_settled_frames():
    poses = Poses()
    poses.add_keyframe(0, np.eye(4), 0.0)
    ledger = Ledger(poses)
    assert record(poses, ledger, 0.0, at(0.0), settled=True) is None
    times = [0.1, 0.3, 0.4]  # uneven: a gap in the stream
    for t in times:
        assert record(poses, ledger, t, at(0.0), lost=True) is None
    moved = record(poses, ledger, 0.5, at(1.0, 10.0), settled=True)
    assert (moved.first, moved.last) == (1, 3) and moved.poses.shape == (3, 4, 4)
    for i, (pose, t) in enumerate(zip(moved.poses, times, strict=True), start=1):
        np.testing.assert_allclose(pose, at(2.0 * t, 20.0 * t), atol=1e-12)
        np.testing.assert_array_equal(poses.pose(i), pose)  # the record holds them


def test_a_guessed_chain_moves_with_its_keyframes_and_the_loss_before_it_is_filled():
    poses = Poses()
    poses.add_keyframe(0, np.eye(4), 0.0)
    ledger = Ledger(poses)
    record(poses, ledger, 0.0, at(0.0), settled=True)
    record(poses, ledger, 0.1, at(0.0), lost=True)
    guess = at(5.0)  # the chain began 5 m off, at a guess: keyframe 5
    poses.add_keyframe(5, guess, 0.2)
    record(poses, ledger, 0.2, guess @ at(0.2), kf=5)
    record(poses, ledger, 0.3, guess @ at(0.3), kf=5)
    poses.add_keyframe(7, at(0.4), 0.4)  # the map's keyframe that places the next frame
    poses.move({5: np.linalg.inv(guess)})  # the tie
    moved = record(poses, ledger, 0.4, at(0.4), kf=7, settled=True, moved={5})
    assert (moved.first, moved.last) == (1, 3)
    np.testing.assert_allclose(moved.poses[1:], [at(0.2), at(0.3)], atol=1e-12)
    np.testing.assert_allclose(moved.poses[0], at(0.1), atol=1e-12)  # filled, between 0 and 2
    np.testing.assert_allclose(poses.keyframe(5), np.eye(4), atol=1e-12)


def test_nothing_moves_without_a_loss_or_a_correction():
    poses = Poses()
    poses.add_keyframe(0, np.eye(4), 0.0)
    ledger = Ledger(poses)
    assert record(poses, ledger, 0.0, at(0.0), settled=True) is None
    record(poses, ledger, 0.1, at(0.1))  # WEAK: open
    assert record(poses, ledger, 0.2, at(0.2), settled=True) is None
    fresh = Poses()  # a loss with no settled frame before it keeps its poses
    fresh.add_keyframe(0, np.eye(4), 0.0)
    fresh_ledger = Ledger(fresh)
    record(fresh, fresh_ledger, 0.0, at(0.0), lost=True)
    assert record(fresh, fresh_ledger, 0.1, at(1.0), settled=True) is None


def test_a_correction_after_a_fill_moves_the_filled_frame_with_its_keyframe():
    poses = Poses()
    poses.add_keyframe(0, np.eye(4), 0.0)
    ledger = Ledger(poses)
    record(poses, ledger, 0.0, at(0.0), settled=True)
    record(poses, ledger, 0.1, at(9.0), lost=True)  # a wild guess
    record(poses, ledger, 0.2, at(0.2), settled=True)
    np.testing.assert_allclose(poses.pose(1), at(0.1), atol=1e-12)
    C = at(0.0, 5.0)  # a loop moves keyframe 0: every frame hanging from it follows
    poses.move({0: C})
    for i, x in enumerate((0.0, 0.1, 0.2)):
        np.testing.assert_allclose(poses.pose(i), C @ at(x), atol=1e-12)
    assert poses.first_hanging_from({0}) == 0 and poses.first_hanging_from({3}) is None
