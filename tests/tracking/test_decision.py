"""The per-frame decision (``tracking.decision``), rule by rule, with plain numbers: no frame
is solved and nothing is compiled. Each case is an input (the state, the frame's solve and
facts, the answers of the actions the decision asks for), the actions it asks for, the
state it leads to and the reason it gives (the rules: docs/decisions.md, "Divergence checks
and recovery", "LOST frames keep the keyframe", "Never silently wrong", "The window beside
tracking")."""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import numpy as np
import pytest

from edgevo_jax import Config
from edgevo_jax.tracking.decision import (
    SHARE_HISTORY,
    Check,
    Confirm,
    Evidence,
    FrameFacts,
    Handover,
    Keyframe,
    MakeKeyframe,
    Motion,
    NewKeyframe,
    Placed,
    Relocalise,
    Revisit,
    Search,
    TrackerState,
    begin_frame,
    decide,
    follow,
)

CFG = Config(map=False)  # the odometry's rules; the map's: MAP below
MAP = Config()


class Solve(NamedTuple):
    """What the decision reads of a ``TrackResult``."""

    T_c_k: np.ndarray
    covariance: np.ndarray
    inliers: int
    visible: float
    moved: float
    flow: float
    flow_t: float
    mean_residual: float


class Mapped(NamedTuple):
    key: int
    pose: np.ndarray


def shift(x: float = 0.0, y: float = 0.0, z: float = 0.0) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = x, y, z
    return T


def solve(share: float = 0.9, *, visible: int = 200, moved: float = 2.0, flow: float = 0.0,
          T: np.ndarray | None = None, mean_residual: float = 0.5, cov: float = 1e-6) -> Solve:
    return Solve(shift(0.01) if T is None else T, np.eye(6) * cov, int(round(share * visible)),
                 float(visible), moved, flow, 0.0, mean_residual)


def state(*, shares=(0.9,), tracked_t: float | None = 0.95, kf_t: float = 0.5,
          previous=(), counts=(180,)) -> TrackerState:
    kf = Keyframe(3, kf_t, np.eye(4), 200, tuple(counts))
    poses = (shift(-0.02), shift(-0.03))
    # the last frame not LOST: the one at 0.95 s where it was tracked, else the one before
    tracked = poses[-1] if tracked_t is not None and tracked_t >= 0.95 else poses[0]
    motion = Motion(poses, (0.9, 0.95), (np.eye(4, dtype=np.float32),) * 2, tracked)
    return TrackerState(kf, tuple(previous), motion, tuple(shares), tracked_t, index=10,
                        num_keyframes=4)


def facts(t: float = 1.0, *, edges: int = 800, depth: bool = True) -> FrameFacts:
    return FrameFacts(t, edges, depth)


def made(ask: MakeKeyframe, *, pose: np.ndarray | None = None) -> NewKeyframe:
    return NewKeyframe(Keyframe(ask.id, ask.timestamp, ask.pose if pose is None else pose, 150),
                       2.0)


def conclude(st: TrackerState, res, fa: FrameFacts, *, found="unused", confirmed=None,
             handover=(), make=made, predicted=None, moved_intrinsics=False, prior=None,
             config=CFG, placed="unused", revisited="unused", checked=None):
    """Run the decision as the driver does, answering its actions; the actions asked (by
    type), the final decision."""
    ev = Evidence(fa, res, st.motion.predict(prior) if predicted is None else predicted,
                  prior=prior, intrinsics_moved=moved_intrinsics)
    asked = []
    for _ in range(7):
        d = decide(st, ev, config)
        assert d.state is st or not d.actions
        if not d.actions:
            return asked, d
        (action,) = d.actions
        asked.append(type(action))
        if isinstance(action, Search):
            assert found != "unused", "a search nobody expected"
            answer = found(st, action) if callable(found) else found
        elif isinstance(action, Confirm):
            assert confirmed is not None, "a confirmation nobody expected"
            answer = confirmed
        elif isinstance(action, Handover):
            answer = tuple(handover)
        elif isinstance(action, Check):
            answer = checked(st, action) if callable(checked) else checked
        elif isinstance(action, Relocalise):
            assert placed != "unused", "a map query nobody expected"
            answer = placed(st, action) if callable(placed) else placed
        elif isinstance(action, Revisit):
            assert revisited != "unused", "a revisit nobody expected"
            answer = revisited
        else:
            assert isinstance(action, MakeKeyframe)
            answer = make(action) if make else None
        ev = ev.answered(action, answer)
    raise AssertionError(f"the decision asked for more than six actions: {asked}")


def test_the_second_opinion_compares_with_the_last_frame_not_lost():
    """After a LOST frame (held at a guess) the check measures the motion from the frame
    before it, the last one tracked: T_cur_prev = T_cur_kf T_world_kf^-1 T_world_tracked."""
    asks = []

    def check(st, action):
        asks.append(action)
        return 0.9

    s0 = state(tracked_t=0.9)  # the frame at 0.95 s was LOST
    asked, d = conclude(s0, solve(T=shift(0.01)), facts(), checked=check)
    assert asked == [Check] and d.result.state == "OK" and d.result.depth_agreement == 0.9
    expected = shift(0.01) @ np.linalg.inv(s0.keyframe.pose) @ s0.motion.poses[0]
    np.testing.assert_allclose(asks[0].T_cur_prev, expected, atol=1e-12)
    assert d.state.motion.tracked is d.state.motion.poses[-1]  # this frame, tracked


def keep_first(st, action):  # the search found nothing better than the first solve
    return (st.keyframe, action.first, False) if action.first is not None else None


# (name, state, solve, facts, conclude options, actions asked, state, reason, keyframe reason)
CASES = [
    ("tracked: OK, no keyframe", {}, {}, {}, {}, [], "OK", None, None),
    ("unusable (too few inliers), nothing found: LOST", {}, {"share": 0.05}, {},
     {"found": None}, [Search, Handover], "LOST", "too few inliers", None),
    ("non-finite pose, nothing found: LOST", {},
     {"T": np.full((4, 4), np.nan)}, {}, {"found": None}, [Search, Handover], "LOST",
     "non-finite pose", None),
    ("ill-conditioned covariance, nothing found: LOST", {}, {"cov": 0.0}, {}, {"found": None},
     [Search, Handover], "LOST", "covariance ill-conditioned", None),
    ("no edges in the frame: LOST without a search", {}, {}, {"edges": 0}, {}, [Handover],
     "LOST", "no edges in the frame", None),
    ("share under the doubt ratio, the first kept: WEAK", {"shares": (0.95,)}, {"share": 0.6},
     {}, {"found": keep_first}, [Search], "WEAK", "under 0.8 x the recent 0.95", None),
    ("share under the lost ratio from every start: LOST", {"shares": (0.95,)},
     {"share": 0.4}, {}, {"found": keep_first}, [Search, Handover], "LOST", "from every start",
     None),
    ("no share seen yet: every start is tried", {"shares": ()}, {}, {},
     {"found": keep_first}, [Search, Check], "OK", None, None),
    ("mean residual over half the gate: WEAK", {}, {"mean_residual": 3.0}, {}, {}, [],
     "WEAK", "mean residual 3.00 px over half the gate", None),
    ("no depth: WEAK", {}, {}, {"depth": False}, {}, [], "WEAK", "no depth", None),
    ("moved past the basin, confirmed by features: OK", {}, {"moved": 45.0}, {},
     {"confirmed": True}, [Confirm, Check], "OK", None, None),
    ("moved past the basin, not confirmed: WEAK", {}, {"moved": 45.0}, {},
     {"confirmed": False}, [Confirm], "WEAK", "moved 45 px from its start, past the 20 px basin",
     None),
    ("0.33 s after the last tracked frame, confirmed by features: OK", {"tracked_t": 0.67},
     {}, {}, {"confirmed": True}, [Confirm, Check], "OK", None, None),
    ("0.33 s after the last tracked frame, not confirmed: WEAK", {"tracked_t": 0.67}, {}, {},
     {"confirmed": False}, [Confirm], "WEAK",
     "0.33 s after the last tracked frame, not confirmed by features", None),
    ("0.05 s after the last tracked frame: OK without asking", {}, {}, {}, {},
     [], "OK", None, None),
    ("0.1 s after the last tracked frame, the one before LOST: the second opinion asked",
     {"tracked_t": 0.9}, {}, {}, {}, [Check], "OK", None, None),
    ("moved past the basin, the search confirmed it: OK without asking", {"shares": ()},
     {"moved": 45.0}, {}, {"found": lambda st, a: (st.keyframe, a.first, True)},
     [Search, Check], "OK", None, None),
    ("searched, the depth images agree: OK", {"shares": ()}, {}, {},
     {"found": keep_first, "checked": 0.95}, [Search, Check], "OK", None, None),
    ("searched, the depth images disagree: WEAK", {"shares": ()}, {}, {},
     {"found": keep_first, "checked": 0.3}, [Search, Check], "WEAK",
     "depth disagrees with the previous frame's: 30 % of its points", None),
    ("confirmed by features, the depth images disagree: WEAK", {}, {"moved": 45.0}, {},
     {"confirmed": True, "checked": 0.5}, [Confirm, Check], "WEAK", "depth disagrees", None),
    ("after a LOST frame, the depth images disagree: WEAK", {"tracked_t": 0.9}, {}, {},
     {"checked": 0.5}, [Check], "WEAK", "depth disagrees", None),
    ("tracked plainly after a tracked frame: no second opinion asked", {}, {}, {},
     {"checked": 0.0}, [], "OK", None, None),
    ("flow: a new keyframe on refined poses (large motion: the second opinion asked)", {},
     {"flow": 60.0}, {}, {}, [Check, Handover, MakeKeyframe], "OK", None, "flow"),
    ("large motion, the depth images disagree: WEAK", {}, {"flow": 60.0}, {},
     {"checked": 0.2}, [Check, Handover, MakeKeyframe], "WEAK", "depth disagrees", "flow"),
    ("interval: a new keyframe", {"kf_t": 0.0}, {}, {"t": 1.0}, {}, [Handover, MakeKeyframe],
     "OK", None, "interval"),
    ("the keyframe's selection finds too few edges: the old one stays", {}, {"flow": 60.0}, {},
     {"make": None}, [Check, Handover, MakeKeyframe], "OK", None, None),
    ("LOST within the keyframe interval: the keyframe stays", {}, {"share": 0.05}, {},
     {"found": None}, [Search, Handover], "LOST", "too few inliers", None),
    ("LOST past the keyframe interval: a keyframe at the guess", {"tracked_t": 0.0},
     {"share": 0.05}, {}, {"found": None}, [Search, Handover, MakeKeyframe], "LOST",
     "too few inliers", "lost"),
]


@pytest.mark.parametrize(("name", "st", "res", "fa", "opts", "asks", "verdict", "reason",
                          "kf_reason"), CASES, ids=[c[0] for c in CASES])
def test_rule(name, st, res, fa, opts, asks, verdict, reason, kf_reason):
    s0 = state(**st)
    asked, d = conclude(s0, solve(**res), facts(**fa), **opts)
    assert asked == asks
    assert d.result.state == verdict
    assert (d.result.reason is None) if reason is None else reason in d.result.reason
    assert d.result.keyframe == kf_reason
    assert np.all(np.isfinite(d.result.pose))
    if kf_reason is not None:  # a new keyframe: the old one joins those recovery tries
        assert d.state.keyframe.id == s0.num_keyframes and d.state.num_keyframes == 5
        assert d.state.previous[-1].id == s0.keyframe.id
    else:
        assert d.state.keyframe.id == s0.keyframe.id and d.state.num_keyframes == 4
    assert d.state.index == s0.index  # counted by begin_frame, not here
    assert d.state.motion.times == (s0.motion.times[-1], 1.0)


def test_correspondences_reason():
    """Level-0 inliers under ``kf_min_inlier_ratio`` of the running mean: a keyframe."""
    s0 = state(counts=(700, 700), shares=(0.9,))
    _, d = conclude(s0, solve(0.9), facts())
    assert d.result.keyframe == "correspondences"
    assert d.state.previous[-1].inlier_counts == (700, 700, 180)  # counted before it left


def test_tracked_frame_state():
    """A tracked frame: pose from the keyframe and the solve, its inliers counted against
    the keyframe, its share in the history (the last ``SHARE_HISTORY``), the lost clock
    set, and the device's next inputs the solve's own pose (plain)."""
    s0 = state(shares=(0.5, 0.6, 0.7, 0.8, 0.85))
    _, d = conclude(s0, solve(0.9), facts(1.0))
    np.testing.assert_allclose(d.result.pose, shift(-0.01))
    assert d.plain and d.result.inliers == 180 and d.result.inlier_share == pytest.approx(0.9)
    assert d.state.keyframe.inlier_counts == (180, 180)
    assert d.state.shares == (0.6, 0.7, 0.8, 0.85, 0.9) and len(d.state.shares) == SHARE_HISTORY
    assert d.state.tracked_t == 1.0
    np.testing.assert_array_equal(d.state.motion.rel[0], shift(0.01).astype(np.float32))
    np.testing.assert_array_equal(d.state.motion.rel[1], s0.motion.rel[0])
    assert d.result.covariance.shape == (6, 6)


def test_lost_frame_state():
    """A LOST frame 0.1 s after the last tracked one: the prediction (a rotation,
    orthonormalised), no covariance, no share; the share history and the lost clock
    unchanged; the keyframe kept; not plain."""
    s0 = state()
    _, d = conclude(s0, solve(0.05), facts(), found=None)
    np.testing.assert_allclose(d.result.pose, s0.motion.predict())
    assert d.result.covariance is None and d.result.inlier_share is None
    assert d.state.shares == s0.shares and d.state.tracked_t == s0.tracked_t
    assert d.state.keyframe == s0.keyframe and not d.plain


def test_lost_frame_long_after_the_last_tracked_one_holds_the_last_pose():
    """Past ``lost_extrapolate_s`` since the last tracked frame the velocity says too
    little: the last pose, held; a motion prior still gives the pose."""
    s0 = state(tracked_t=0.9)
    t = 0.9 + CFG.lost_extrapolate_s + 0.05
    assert not np.allclose(s0.motion.predict(), s0.motion.poses[-1])  # a moving camera
    _, d = conclude(s0, solve(0.05), facts(t), found=None)
    np.testing.assert_array_equal(d.result.pose, s0.motion.poses[-1])
    prior = shift(0.02)
    _, d = conclude(s0, solve(0.05), facts(t), found=None, prior=prior)
    np.testing.assert_allclose(d.result.pose, s0.motion.poses[-1] @ prior, atol=1e-12)


def test_lost_frame_with_a_prior_takes_its_prediction_and_never_a_non_finite_pose():
    s0 = state()
    prior = shift(0.02)
    _, d = conclude(s0, solve(0.05), facts(), found=None, prior=prior,
                    predicted=s0.motion.predict(prior))
    np.testing.assert_allclose(d.result.pose, s0.motion.poses[-1] @ prior, atol=1e-12)
    _, d = conclude(s0, solve(0.05), facts(), found=None, prior=prior,
                    predicted=np.full((4, 4), np.inf))
    np.testing.assert_array_equal(d.result.pose, s0.motion.poses[-1])


def test_lost_frame_predicts_from_refined_poses():
    """The window's refinement of the current keyframe, handed over on a LOST frame, moves
    the last poses with it: the frame's pose is predicted from them."""
    s0 = state()
    _, d = conclude(s0, solve(0.05), facts(), found=None,
                    handover=[Mapped(s0.keyframe.id, shift(z=0.1))])
    expected = shift(z=0.1) @ s0.motion.predict()
    np.testing.assert_allclose(d.result.pose, expected, atol=1e-12)
    np.testing.assert_allclose(d.state.keyframe.pose, shift(z=0.1))


def test_new_keyframe_is_built_on_refined_poses():
    """A refinement handed over before a new keyframe moves the frame's pose with its
    keyframe, and the keyframe is asked for at that pose."""
    s0 = state()
    asks = []

    def make(ask):
        asks.append(ask)
        return made(ask)

    _, d = conclude(s0, solve(flow=60.0), facts(), make=make,
                    handover=[Mapped(s0.keyframe.id, shift(y=0.2))])
    np.testing.assert_allclose(asks[0].pose, shift(y=0.2) @ shift(-0.01))
    np.testing.assert_allclose(d.result.pose, asks[0].pose)
    assert d.state.previous[-1].pose[1, 3] == 0.2
    assert d.result.select_ms == 2.0 and not d.plain


def test_keyframe_pose_refined_inline_is_the_frame_pose():
    """With the window inline, the new keyframe comes back refined: the frame takes it."""
    refined = shift(x=0.3)
    _, d = conclude(state(), solve(flow=60.0), facts(), make=lambda a: made(a, pose=refined))
    np.testing.assert_array_equal(d.result.pose, refined)
    np.testing.assert_array_equal(d.state.motion.poses[-1], refined)


def test_recovered_against_an_earlier_keyframe_it_takes_over():
    """The search found the frame against an earlier keyframe: that one becomes current
    (pose from it), the old current one is left (as the tracker always did)."""
    earlier = Keyframe(1, 0.2, shift(z=1.0), 180, (150,))
    s0 = state(previous=(earlier,))
    better = solve(0.95)
    _, d = conclude(s0, solve(0.05), facts(), found=(earlier, better, False))
    assert d.result.state == "OK" and d.state.keyframe.id == 1
    assert d.state.previous == (dataclasses.replace(earlier, inlier_counts=(150, 190)),)
    np.testing.assert_allclose(d.result.pose, shift(z=1.0) @ shift(-0.01))
    assert not d.plain


@pytest.mark.parametrize("change", ["search kept another solve", "intrinsics moved"])
def test_not_plain(change):
    """The device's next inputs come from the world poses when the solve is not the one
    it predicted from: another solve, or intrinsics the window moved."""
    s0 = state()
    if change == "intrinsics moved":
        _, d = conclude(s0, solve(), facts(), moved_intrinsics=True)
    else:
        _, d = conclude(s0, solve(0.5), facts(), found=lambda st, a: (st.keyframe, solve(), False))
    assert not d.plain


def test_first_frame():
    """The first frame becomes the keyframe at its prediction; without edges with depth it
    is LOST there and no keyframe is made."""
    s0 = TrackerState()
    _, d = conclude(s0, None, facts(0.0), predicted=np.eye(4))
    assert (d.result.state, d.result.keyframe, d.state.keyframe.id) == ("OK", "first", 0)
    np.testing.assert_array_equal(d.state.motion.rel[0], np.eye(4, dtype=np.float32))
    _, d = conclude(s0, None, facts(0.0), predicted=np.eye(4), make=None)
    assert (d.result.state, d.result.reason, d.state.keyframe) == ("LOST", "no edges with depth",
                                                                    None)


def test_begin_frame_takes_the_window_refinements():
    """Refinements due at a frame: the keyframe takes its refined pose, the current one moves
    the last two poses with it (relative motion kept), a keyframe no longer held is skipped,
    the frame is counted."""
    earlier = Keyframe(1, 0.2, shift(z=1.0), 180)
    s0 = state(previous=(earlier,))
    s1 = begin_frame(s0, [Mapped(1, shift(z=1.5)), Mapped(3, shift(x=0.1)), Mapped(9, np.eye(4))])
    assert s1.index == s0.index + 1
    np.testing.assert_array_equal(s1.previous[0].pose, shift(z=1.5))
    np.testing.assert_array_equal(s1.keyframe.pose, shift(x=0.1))
    for before, after in zip(s0.motion.poses, s1.motion.poses, strict=True):
        np.testing.assert_allclose(after, shift(x=0.1) @ before)
    assert follow(s0, []) == s0


# -- the keyframe map's rules (Config.map) ----------------------------------------------------
OLD = Keyframe(1, 0.1, shift(0.5), 300)  # a keyframe of the map, made long before


def on_old(share: float = 0.9, note: str = "found again: keyframe 1") -> Placed:
    """The map's answer: the frame aligned to OLD, 1 cm in front of it."""
    return Placed(OLD, solve(share, T=shift(z=-0.01)), note)


def test_a_lost_frame_asks_the_map_and_a_verified_place_makes_it_ok():
    s0 = state()
    asked, d = conclude(s0, solve(0.05), facts(), found=None, config=MAP, placed=on_old())
    assert asked == [Search, Relocalise, Check]  # placed: the second opinion asked too
    assert d.result.state == "OK" and d.result.placed == "found again: keyframe 1"
    np.testing.assert_allclose(d.result.pose, shift(0.5, z=0.01), atol=1e-12)
    assert d.state.keyframe.id == 1 and d.state.keyframe.since == 1.0
    assert d.state.previous[-1].id == s0.keyframe.id  # the old current joins recovery's
    assert d.tie is not None and d.tie.keyframe == 1 and d.tie.correction is None
    assert not d.tie.restart  # keyframe 1 is among the window's (the last window_size made)
    assert len(d.state.motion.poses) == 1  # no velocity across the jump
    assert not d.plain


def test_a_lost_frame_found_on_a_keyframe_the_window_left_starts_the_window_again():
    """The window's keyframes are from before the loss and see another place: refined
    jointly across the loss they moved the next keyframes (docs/decisions.md)."""
    s0 = dataclasses.replace(state(), num_keyframes=4 + MAP.window_size)
    asked, d = conclude(s0, solve(0.05), facts(), found=None, config=MAP, placed=on_old())
    assert d.result.state == "OK" and d.tie.keyframe == 1 and d.tie.restart
    assert d.tie.correction is None
    # a frame tracked in a tied chain that the map placed (a doubted one): no restart
    asked, d = conclude(s0, solve(0.9, moved=100.0), facts(), config=MAP, confirmed=False,
                        placed=on_old())
    assert asked[:2] == [Confirm, Relocalise] and d.tie is not None and not d.tie.restart


def test_a_keyframe_made_where_the_map_placed_a_frame_reads_no_velocity_across_the_jump():
    # the held pose of a loss and the place found are not a motion: a keyframe made there
    # must not unroll its edges for it (rolling shutter) nor move their depths by it
    asks = []

    def make(ask):
        asks.append(ask)
        return made(ask)

    placed = Placed(OLD, solve(0.9, T=shift(z=-0.01), flow=60.0), "found again: keyframe 1")
    asked, d = conclude(state(), solve(0.05), facts(), found=None, config=MAP, placed=placed,
                        make=make, handover=())
    assert asked == [Search, Relocalise, Check, Handover, MakeKeyframe]
    assert d.result.state == "OK" and asks[0].motion.poses == ()
    np.testing.assert_allclose(asks[0].pose, shift(0.5, z=0.01), atol=1e-12)


def test_a_query_that_finds_nothing_leaves_the_frame_lost():
    asked, d = conclude(state(), solve(0.05), facts(), found=None, config=MAP, placed=None,
                        handover=())
    assert asked == [Search, Relocalise, Handover]
    assert d.result.state == "LOST" and d.tie is None and d.result.placed is None


def test_a_frame_without_edges_does_not_ask_the_map():
    asked, d = conclude(state(), solve(), facts(edges=0), config=MAP)
    assert asked == [Handover] and d.result.state == "LOST"


def test_a_keyframe_made_at_a_loss_is_guessed_and_frames_tracked_from_it_are_weak():
    s0 = state(tracked_t=0.0)  # lost for 1 s: a keyframe at the guess
    asked, d = conclude(s0, solve(0.05), facts(), found=None, config=MAP, placed=None)
    assert asked == [Search, Relocalise, Handover, MakeKeyframe]
    kf = d.state.keyframe
    assert kf.guess is not None and kf.guess.keyframe == kf.id and kf.guess.frame == 9
    assert "made at a guess after 1.0 s lost" in kf.guess.why
    # the next frame, tracked well from it, asks the map; nothing found: WEAK, named
    s1 = dataclasses.replace(d.state, shares=(0.9,), tracked_t=1.0)
    asked, d1 = conclude(s1, solve(0.9), facts(1.03), config=MAP, placed=None)
    assert asked == [Relocalise]
    assert d1.result.state == "WEAK"
    assert d1.result.reason == (f"tracked from keyframe {kf.id}, made at a guess after 1.0 s "
                                "lost: not tied to the map")
    # found: the chain moves into the map's frame with the frame, the window starts again
    asked, d2 = conclude(s1, solve(0.9), facts(1.03), config=MAP, placed=on_old())
    assert d2.result.state == "OK"
    tie = d2.tie
    assert tie.restart and tie.since == 9 and tie.guessed == kf.id
    chain_pose = kf.pose @ np.linalg.inv(shift(0.01))
    np.testing.assert_allclose(tie.correction @ chain_pose, d2.result.pose, atol=1e-12)
    # in its first second the chain asks at every frame; after it, not again before
    # ``map_chain_query_s``
    assert d1.state.asked_t == 1.03 and kf.guess.t == 1.0
    asked, e2 = conclude(d1.state, solve(0.9), facts(1.06), config=MAP, placed=None)
    assert asked == [Relocalise]
    # a second on (frames tracked meanwhile): asked a moment ago, not again before
    # ``map_chain_query_s``
    on = dataclasses.replace(e2.state, tracked_t=2.05, asked_t=2.1, keyframe=dataclasses.replace(
        e2.state.keyframe, since=2.0))
    asked, d4 = conclude(on, solve(0.9), facts(2.2), config=MAP)
    assert asked == [] and d4.result.state == "WEAK" and d4.state.asked_t == 2.1
    asked, d5 = conclude(dataclasses.replace(on, tracked_t=2.3), solve(0.9),
                         facts(2.1 + MAP.map_chain_query_s), config=MAP, placed=None)
    assert asked == [Relocalise] and d5.state.asked_t == 2.1 + MAP.map_chain_query_s
    # a frame of the chain doubted by its own solve asks at once
    asked, _ = conclude(on, solve(0.9, moved=100.0), facts(2.2), config=MAP,
                        confirmed=False, placed=None)
    assert asked == [Confirm, Relocalise]
    np.testing.assert_allclose(d2.state.motion.poses[0], tie.correction @ s1.motion.poses[-1],
                               atol=1e-12)


def test_the_chain_a_loaded_map_run_begins_with_asks_beside_tracking_at_every_frame():
    """A run started in a loaded map: its first keyframe is guessed (``Guess.loaded``) and
    its first frame tracked asks the map on the tracker's thread, every later one beside
    tracking (``Relocalise.beside``), as often as any chain asks; a frame doubted by its own
    solve asks on the tracker's thread, as any; a place found ties the chain as any tie
    does."""
    first = TrackerState(num_keyframes=7, loaded=True)
    ev = Evidence(facts(0.0), None, np.eye(4))
    d0 = decide(first, ev, MAP)
    (ask,) = d0.actions
    d0 = decide(first, ev.answered(ask, made(ask)), MAP)
    kf = d0.state.keyframe
    assert kf.guess.loaded and kf.id == 7 and d0.result.state == "WEAK"
    asks = []

    def placed(st, action):
        asks.append(action)
        return None

    st = dataclasses.replace(d0.state, shares=(0.9,), tracked_t=0.0)
    asked, d = conclude(st, solve(0.9), facts(0.03), config=MAP, placed=placed)
    assert asked == [Relocalise] and not asks[-1].beside  # the first: on the thread
    st = d.state
    assert st.asked_t == 0.03
    for t in (0.06, 0.09, 1.5, 1.53):  # every frame in the chain's first second, then
        on = dataclasses.replace(st, tracked_t=t - 0.03, keyframe=dataclasses.replace(
            st.keyframe, since=t - 0.03))  # at most every map_chain_query_s, as any chain
        asked, d = conclude(on, solve(0.9), facts(t), config=MAP, placed=placed)
        assert asked == ([] if t == 1.53 else [Relocalise]) and d.result.state == "WEAK"
        st = d.state
    assert [a.beside for a in asks] == [False, True, True, True]
    asked, _ = conclude(st, solve(0.9, moved=100.0), facts(0.03), config=MAP,
                        confirmed=False, placed=placed)
    assert asked == [Confirm, Relocalise] and not asks[-1].beside
    checks = []
    asked, d = conclude(st, solve(0.9), facts(0.03), config=MAP, placed=on_old(),
                        checked=lambda s_, action: checks.append(action) or 0.9)
    assert d.result.state == "OK" and d.tie.guessed == kf.id and d.tie.restart
    # the second opinion measures its motion in its chain, where the last frame's pose is
    chain = kf.pose @ np.linalg.inv(shift(0.01))
    np.testing.assert_allclose(checks[0].T_cur_prev,
                               np.linalg.inv(chain) @ st.motion.tracked, atol=1e-12)


def test_a_keyframe_made_from_a_doubted_frame_is_guessed():
    s0 = state(shares=(0.95,))
    asked, d = conclude(s0, solve(0.6, flow=60.0), facts(), found=keep_first, config=MAP,
                        placed=None)
    assert asked == [Search, Relocalise, Handover, MakeKeyframe]
    assert d.result.state == "WEAK" and d.result.keyframe == "flow"
    assert d.state.keyframe.guess.why == "made from a frame not verified"


def test_a_revisit_hands_the_frame_to_an_older_keyframe_instead_of_a_new_one():
    s0 = state()
    asked, d = conclude(s0, solve(0.9, flow=60.0), facts(), config=MAP,
                        revisited=on_old(0.9, "revisit: keyframe 1 takes over"))
    assert asked == [Check, Handover, Revisit]  # a large motion: the second opinion too
    assert d.result.keyframe is None and d.state.num_keyframes == s0.num_keyframes
    assert d.state.keyframe.id == 1 and d.result.placed.startswith("revisit")
    np.testing.assert_allclose(d.result.pose, shift(0.5, z=0.01), atol=1e-12)
    assert d.tie is not None and not d.tie.restart and d.tie.correction is None
    # the motion moved with the frame: its velocity is kept
    v0 = np.linalg.inv(s0.motion.poses[-1]) @ (s0.keyframe.pose @ np.linalg.inv(shift(0.01)))
    v1 = np.linalg.inv(d.state.motion.poses[0]) @ d.state.motion.poses[1]
    np.testing.assert_allclose(v1, v0, atol=1e-12)
    # nothing takes over: the new keyframe as before; the ids a revisit leaves out
    asked, d = conclude(s0, solve(0.9, flow=60.0), facts(), config=MAP, revisited=None)
    assert asked == [Check, Handover, Revisit, MakeKeyframe] and d.result.keyframe == "flow"


def test_the_map_off_asks_nothing_of_it():
    asked, d = conclude(state(tracked_t=0.0), solve(0.05), facts(), found=None)
    assert asked == [Search, Handover, MakeKeyframe] and d.state.keyframe.guess is None
