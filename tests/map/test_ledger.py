"""The frames the keyframe map may still move (``pipeline.ledger``): LOST frames between two
settled ones are filled in along the motion between them, by time; a guessed chain takes
the correction of the frame that tied it; nothing else moves."""

from __future__ import annotations

import numpy as np

from edgevo_jax.geometry import exp_np
from edgevo_jax.map.ledger import Ledger
from edgevo_jax.tracking.records import Tie
from edgevo_jax.tracking.results import LOST, OK, WEAK, FrameResult


def at(x: float, yaw_deg: float = 0.0) -> np.ndarray:
    return exp_np(np.array([x, 0.0, 0.0, 0.0, np.radians(yaw_deg), 0.0]))


def result(t: float, pose: np.ndarray, state: str = OK) -> FrameResult:
    return FrameResult(t, pose, state, None if state == OK else "why", 0, None, None, 0, None,
                       None, 0.0, 0.0, 0.0)


def test_lost_frames_are_filled_in_by_time_between_the_settled_frames():
    ledger = Ledger()
    assert ledger.record(0, result(0.0, at(0.0)), settled=True) is None
    times = [0.1, 0.3, 0.4]  # uneven: a gap in the stream
    for i, t in enumerate(times, start=1):
        assert ledger.record(i, result(t, at(0.0), LOST), settled=False) is None
    moved = ledger.record(4, result(0.5, at(1.0, 10.0)), settled=True)
    assert (moved.first, moved.last) == (1, 3) and moved.poses.shape == (3, 4, 4)
    for pose, t in zip(moved.poses, times, strict=True):
        np.testing.assert_allclose(pose, at(2.0 * t, 20.0 * t), atol=1e-12)


def test_a_guessed_chain_takes_the_correction_and_the_loss_before_it_is_filled():
    ledger = Ledger()
    ledger.record(0, result(0.0, at(0.0)), settled=True)
    ledger.record(1, result(0.1, at(0.0), LOST), settled=False)
    guess = at(5.0)  # the chain began 5 m off, at a guess
    ledger.record(2, result(0.2, guess @ at(0.2), WEAK), settled=False)
    ledger.record(3, result(0.3, guess @ at(0.3), WEAK), settled=False)
    correction = np.linalg.inv(guess)
    moved = ledger.record(4, result(0.4, at(0.4)), settled=True,
                          tie=Tie(7, correction, since=2, guessed=5, restart=True))
    assert (moved.first, moved.last) == (1, 3)
    np.testing.assert_allclose(moved.poses[1:], [at(0.2), at(0.3)], atol=1e-12)
    np.testing.assert_allclose(moved.poses[0], at(0.1), atol=1e-12)  # filled, between 0 and 2


def test_nothing_moves_without_a_loss_or_a_correction():
    ledger = Ledger()
    assert ledger.record(0, result(0.0, at(0.0)), settled=True) is None
    ledger.record(1, result(0.1, at(0.1), WEAK), settled=False)
    assert ledger.record(2, result(0.2, at(0.2)), settled=True) is None
    fresh = Ledger()  # a loss with no settled frame before it keeps its poses
    fresh.record(0, result(0.0, at(0.0), LOST), settled=False)
    assert fresh.record(1, result(0.1, at(1.0)), settled=True) is None
