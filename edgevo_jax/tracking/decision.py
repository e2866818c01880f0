"""The per-frame decision of the streaming tracker: a pure function of the tracker's state,
the frame's solve and facts, with the host effects it needs asked for as actions.

State (``TrackerState``, ``records``): a few small frozen records: the keyframe
(``Keyframe``) and the earlier ones kept for recovery, the motion history (``Motion``: the
last two poses and their times, and the device's prediction inputs), the inlier-share history
(``shares``) and the lost clock (``tracked_t``: when a frame was last tracked). Keyframe poses
are the tracker's copies of the map's record (``map.poses``): ``begin_frame`` and ``follow``
take the keyframes that moved there (the window's refinements, a loop's correction).

``decide(state, evidence, config)`` reads the frame's solve and facts (``Evidence``) and
returns ``Decision(state, result, actions)``, in phases, one short function per rule. Where
it needs something only a host effect can give, it returns the unchanged state, no result
and that one action: ``Search`` (the recovery search from other starts and keyframes),
``Confirm`` (an alignment from a feature start), ``Check`` (the second opinion, from two
depth images), ``Relocalise`` and ``Revisit`` (the keyframe map: ``places``, through
``backend``), ``Handover`` (all refinements the window has made, waited for) or
``MakeKeyframe`` (edge selection; the back end takes the keyframe). The driver
(``odometry.Odometry``) carries it out, adds the answer to the evidence
(``Evidence.answered``) and calls again; each action is asked for at most once per frame.
With every answer in, the result is the frame's ``FrameResult`` and the state is the one the
next frame starts from. The rules (docs/decisions.md), in order:

1. the solve is unusable (``lost_reason``), its inlier share is under ``doubt_share_ratio``
   of the recent frames' highest, or no share has been seen yet: ``Search``;
2. still under ``lost_share_ratio`` of that reference from every start: LOST;
3. tracked: the pose from the keyframe (an earlier one found by the search takes over),
   the keyframe reason (``frontend.keyframes``), WEAK when the residuals are high, the frame
   has no depth, or the solve is doubtful (share under the doubt ratio, it moved past the
   alignment's basin, or it comes more than ``lost_extrapolate_s`` after the last tracked
   frame) and no feature start confirms it (``Confirm``), or its keyframe was made at a
   guess (``Guess``: the chain is not tied to the map);
4. with the map (``Config.map``), a LOST or doubted frame and one tracked from a guessed
   keyframe ask the map where it is (``Relocalise``); a verified place makes it OK against
   that keyframe, and a guessed chain it was tracked in moves into the map's frame with it
   (``Tie``);
   then the second opinion: a frame tracked and not WEAK whose motion is large, whose
   solve was searched for, confirmed from features or placed by the map, or that follows a
   LOST frame, is WEAK when the depth points of the last frame not LOST do not lie on its
   surfaces at its motion from that frame (``Check``, ``Config.depth_check_share``);
5. LOST: the pose is the prediction (finite, a rotation) within ``lost_extrapolate_s`` of
   the last tracked frame or with a motion prior, else the last pose, held; the keyframe stays,
   unless the loss outlasts ``kf_max_interval_s`` (a new keyframe at the guess, guessed);
6. a new keyframe is built on refined poses only (``Handover`` first); with the map, an older
   keyframe that sees the frame takes over instead where one aligns (``Revisit``); when the
   selection finds too few edges the old keyframe stays.
This module runs no JAX: each rule is tested with plain numbers (tests/tracking/test_decision.py).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..config import Config
from ..derive import basin_px
from ..frontend.keyframes import keyframe_reason
from ..geometry import inverse_np, orthonormalise_np
from .following import begin_frame, follow, relative_from_world, with_keyframe
from .records import (
    Check,
    Confirm,
    Decision,
    Evidence,
    FrameFacts,
    Guess,
    Handover,
    Keyframe,
    MakeKeyframe,
    Motion,
    NewKeyframe,
    Placed,
    Relocalise,
    Revisit,
    Search,
    Tie,
    Timing,
    TrackerState,
)
from .results import LOST, OK, WEAK, FrameResult
from .verify import (
    SHARE_HISTORY,
    far_reason,
    inlier_share,
    lost_reason,
    reference_share,
    share_doubt,
    under,
    weak_reason,
)

__all__ = ["DEPTH_DISAGREES", "SHARE_HISTORY", "Check", "Confirm", "Decision", "Evidence",
           "FrameFacts", "Guess", "Handover", "Keyframe", "MakeKeyframe", "Motion",
           "NewKeyframe", "Placed", "Relocalise", "Revisit", "Search", "Tie", "Timing",
           "TrackerState", "begin_frame", "decide", "follow", "inlier_share", "lost_reason",
           "reference_share", "relative_from_world", "under", "weak_reason"]

#: how the reason of a frame the second opinion made WEAK begins (``_checked``)
DEPTH_DISAGREES = "depth disagrees with the previous frame's"

#: a chain made at a guess asks the map at every frame for this long after it began (s): its
#: place is most likely in view then; after it, at most every ``Config.map_chain_query_s``
CHAIN_EAGER_S = 1.0


# -- the decision: a recipe of phases -----------------------------------------------------------
@dataclass(frozen=True)
class _Step:
    """What the phases of ``decide`` have found so far about one frame: the keyframe and the
    solve it is tracked by (the search or the map may replace the first), the reference
    share, why it is LOST or WEAK, whether it is doubted (its solve unverified, or its chain
    made at a guess), where the map placed it (``placed``: its pose in its own chain,
    ``chain``, and that chain's guess), the state it leads to (``new``), its keyframe reason,
    the time since the last tracked frame (``since``, s: a LOST frame's), its pose and the
    ``Tie`` it asks of the driver."""

    kf: Keyframe
    res: Any
    reference: float | None
    lost: str | None = None
    confirmed: bool = False
    weak: str | None = None
    doubted: bool = False
    own_doubt: bool = False
    asked: bool = False
    placed: Placed | None = None
    chain: np.ndarray | None = None
    chain_guess: Guess | None = None
    new: TrackerState | None = None
    reason: str | None = None
    since: float = 0.0
    T_c_k: np.ndarray | None = None
    handed: bool = False
    pose: np.ndarray | None = None
    tie: Tie | None = None
    used: int = 0
    made: NewKeyframe | None = None
    agreement: float | None = None


def decide(state: TrackerState, ev: Evidence, config: Config) -> Decision:
    """The frame's decision (module doc): the next state, the frame's result and no action;
    or the unchanged state, no result and the one action the decision needs answered first.
    The rules, one phase each, in order."""
    if ev.solve is None:
        return _first(state, ev, config)
    step = _Step(state.keyframe, ev.solve, reference_share(state, config))
    for phase in (_searched, _judged, _found_again, _checked, _moved_on, _handed_over, _posed,
                  _revisited, _tied, _keyframed):
        step = phase(state, ev, config, step)
        if not isinstance(step, _Step):  # an action to answer first
            return Decision(state, None, (step,))
    return _concluded(state, ev, config, step)


def _searched(state: TrackerState, ev: Evidence, config: Config, s: _Step) -> _Step | Search:
    """Rules 1-2: an unusable or doubted solve (a wrong basin, as after a prediction far off)
    asks for other starts and keyframes (with no reference yet, the first frames, every start
    is tried); under the lost ratio from every start: LOST."""
    facts, res, reference = ev.facts, s.res, s.reference
    kf, confirmed = s.kf, s.confirmed
    lost = lost_reason(facts.num_edges, res, config)
    doubt, lost_ratio = config.doubt_share_ratio, config.lost_share_ratio
    if facts.num_edges > 0 and (lost is not None or under(res, reference, doubt)
                                or (reference is None and doubt > 0)):
        if not ev.asked(Search):
            return Search(None if lost else res, reference)
        if ev.answer(Search) is not None:
            kf, res, confirmed = ev.answer(Search)
            lost = None
    if lost is None and under(res, reference, lost_ratio):
        lost = (f"inlier share {inlier_share(res):.2f} under {lost_ratio:g} x the recent "
                f"{reference:.2f} from every start")
    return dataclasses.replace(s, kf=kf, res=res, lost=lost, confirmed=confirmed)


def _judged(state: TrackerState, ev: Evidence, config: Config, s: _Step) -> _Step | Confirm:
    """Rule 3's WEAK: high residuals, no depth, a doubted solve no feature start confirms
    (``Confirm``), or a keyframe made at a guess."""
    kf, res = s.kf, s.res
    weak, own = None, False
    if s.lost is None:
        weak = weak_reason(ev.facts.has_depth, res, config)
        if weak is None and not s.confirmed:
            weak = share_doubt(res, s.reference, config)
            gap = None if state.tracked_t is None else ev.facts.timestamp - state.tracked_t
            far = None if weak is not None else far_reason(res, config, gap)
            if far is not None:
                if not ev.asked(Confirm):
                    return Confirm(kf, res)
                weak = None if ev.answer(Confirm) else far + ", not confirmed by features"
            own = weak is not None
        weak = weak or (kf.guess.reason if kf.guess is not None else None)
    return dataclasses.replace(s, weak=weak, doubted=own or kf.guess is not None,
                               own_doubt=own)


def _found_again(state: TrackerState, ev: Evidence, config: Config, s: _Step
                 ) -> _Step | Relocalise:
    """Rule 4: with the map, a lost or doubted frame asks the map where it is, and so does a
    frame tracked from a keyframe made at a guess, at every frame in the chain's first
    ``CHAIN_EAGER_S`` and at most every ``map_chain_query_s`` after (the chain a loaded
    map's run begins with: its first frame on the tracker's thread, the later ones beside
    tracking); a verified place makes
    it OK against that keyframe (its pose in its own chain kept, ``chain``, to move the
    chain with it)."""
    if not (config.map and ev.facts.num_edges > 0 and (s.lost is not None or s.doubted)):
        return s
    t, guess = ev.facts.timestamp, s.kf.guess
    chain = s.lost is None and not s.own_doubt and guess is not None
    if chain and t - guess.t >= CHAIN_EAGER_S and state.asked_t is not None and \
            t - state.asked_t < config.map_chain_query_s:
        return s  # a chain made at a guess a while ago, asked a moment ago
    # a loaded map's chain: its first frame asks on the tracker's thread, the next beside
    # tracking (the back end runs one query at a time)
    beside = chain and guess.loaded and state.asked_t is not None
    s = dataclasses.replace(s, asked=True)
    if not ev.asked(Relocalise):
        if s.lost is not None:
            return Relocalise(state.motion.poses[-1])
        guess = s.kf.pose @ inverse_np(np.asarray(s.res.T_c_k, np.float64))
        return Relocalise(guess, inverse_np(state.motion.poses[-1]) @ guess, beside=beside)
    placed = ev.answer(Relocalise)
    if placed is None:
        return s
    chain = None if s.lost is not None else s.kf.pose @ inverse_np(
        orthonormalise_np(np.asarray(s.res.T_c_k, np.float64)))
    return dataclasses.replace(s, placed=placed, chain=chain, chain_guess=s.kf.guess,
                               kf=_current(placed.keyframe, ev.facts), res=placed.result,
                               lost=None, weak=None)


def _checked(state: TrackerState, ev: Evidence, config: Config, s: _Step) -> _Step | Check:
    """Rule 4b, the second opinion: a tracked frame not WEAK whose motion is large (its
    edges' RMS optical flow past the alignment's basin, ``derive.basin_px``), whose solve
    was searched for, confirmed from features or placed by the map, or that follows a LOST
    frame, is WEAK when too few of the depth points of the last frame not LOST lie on its
    surfaces at its motion from that frame (``Check``; ``Config.depth_check_share``): the
    distance field agrees with a wrong pose where edges snap to their neighbours, two depth
    images do not. (A LOST frame's pose is a guess: no measure of the motion. A frame placed
    with the chain it was tracked in: its motion in that chain, as the last frame's pose is
    the chain's.)"""
    share, tracked = config.depth_check_share, state.motion.tracked
    if not (share > 0 and s.lost is None and s.weak is None and tracked is not None):
        return s
    after_loss = state.tracked_t is not None and state.motion.times[-1] > state.tracked_t
    large = float(s.res.flow) > basin_px(config)  # the edges moved past the basin
    if not (large or after_loss or s.placed is not None or ev.asked(Search)
            or ev.asked(Confirm)):
        return s
    if not ev.asked(Check):
        if s.chain is not None:  # placed with its chain: the last frame is in the chain's
            return Check(inverse_np(s.chain) @ tracked)
        T_c_k = orthonormalise_np(np.asarray(s.res.T_c_k, np.float64))
        return Check(T_c_k @ inverse_np(s.kf.pose) @ tracked)
    agreement = ev.answer(Check)
    if agreement is None or agreement >= share:
        return dataclasses.replace(s, agreement=agreement)
    return dataclasses.replace(
        s, agreement=agreement, weak=f"{DEPTH_DISAGREES}: {100 * agreement:.0f} % of its "
        f"points on the frame's surfaces, under {100 * share:.0f} %")


def _moved_on(state: TrackerState, ev: Evidence, config: Config, s: _Step) -> _Step:
    """The state after a tracked frame (its keyframe's inliers counted) and its keyframe
    reason; for a LOST one, the state as it was, and a new keyframe only when the loss
    outlasts the keyframe interval (rule 5: the old view may be gone for good)."""
    facts, kf, res = ev.facts, s.kf, s.res
    if s.lost is None:
        reason = keyframe_reason(
            flow=float(res.flow), flow_t=float(res.flow_t), inliers=int(res.inliers),
            inlier_mean=float(np.mean(kf.inlier_counts)) if kf.inlier_counts else None,
            dt=facts.timestamp - kf.current_since, config=config)
        return dataclasses.replace(
            s, T_c_k=orthonormalise_np(np.asarray(res.T_c_k, np.float64)), reason=reason,
            new=_tracked(state, kf, res, facts, config, over=s.placed is not None))
    since = facts.timestamp - (state.tracked_t if state.tracked_t is not None
                               else kf.timestamp)
    return dataclasses.replace(s, new=state, since=since,
                               reason="lost" if since >= config.kf_max_interval_s else None)


def _handed_over(state: TrackerState, ev: Evidence, config: Config, s: _Step
                 ) -> _Step | Handover:
    """Rule 6: a new keyframe is built on refined poses only; a lost frame takes them as
    well (``Handover``: every refinement handed to the window)."""
    if not (s.reason or s.lost is not None):
        return s
    if not ev.asked(Handover):
        return Handover()
    refined = ev.answer(Handover)
    return dataclasses.replace(s, new=follow(s.new, refined), handed=bool(refined))


def _posed(state: TrackerState, ev: Evidence, config: Config, s: _Step) -> _Step:
    """The frame's pose: from its keyframe when tracked; when LOST, the prediction (finite, a
    rotation) within ``lost_extrapolate_s`` of the last tracked frame or with a motion prior
    (evidence: an IMU, wheels), else the last pose, held (rule 5)."""
    new = s.new
    if s.lost is None:
        pose = new.keyframe.pose @ inverse_np(s.T_c_k)
    elif ev.prior is None and s.since > config.lost_extrapolate_s:
        pose = new.motion.poses[-1]
    else:
        pose = new.motion.predict(ev.prior) if s.handed else ev.predicted
        # lost frames in a row extrapolate again and again: keep R a rotation, stay finite
        pose = orthonormalise_np(pose) if np.all(np.isfinite(pose)) else pose
        if not np.all(np.isfinite(pose)):
            pose = new.motion.poses[-1]
    return dataclasses.replace(s, pose=pose)


def _revisited(state: TrackerState, ev: Evidence, config: Config, s: _Step
               ) -> _Step | Revisit:
    """Rule 6, with the map: an older keyframe of the map that sees the frame takes over
    from the new keyframe it asked for, where one aligns (``Revisit``)."""
    if not (config.map and s.reason and s.lost is None and s.placed is None
            and not s.doubted):
        return s
    if not ev.asked(Revisit):
        return Revisit(s.pose, _recent(s.new, config))
    placed = ev.answer(Revisit)
    if placed is None:
        return s
    kf, res = _current(placed.keyframe, ev.facts), placed.result
    T_c_k = orthonormalise_np(np.asarray(res.T_c_k, np.float64))
    new = _tracked(follow(state, ev.answer(Handover)), kf, res, ev.facts, config, over=True)
    return dataclasses.replace(s, placed=placed, chain=s.pose, reason=None, kf=kf, res=res,
                               T_c_k=T_c_k, new=new, pose=kf.pose @ inverse_np(T_c_k))


def _tied(state: TrackerState, ev: Evidence, config: Config, s: _Step) -> _Step:
    """A frame the map placed: its motion moves into the map's frame with it, before a
    keyframe made from it reads its velocity (rolling shutter, depth timing), and the
    driver is asked to tie its chain (``Tie``)."""
    new, tie = s.new, None
    if s.placed is not None:
        # a LOST frame found on a keyframe the window no longer holds: the window's views are
        # not the frame's place (below: ``_tie``)
        far = s.chain is None and s.kf.id < state.num_keyframes - config.window_size
        tie = _tie(s.chain_guess or state.keyframe.guess, s.kf.id, s.pose, s.chain, far=far)
        new = dataclasses.replace(new, motion=Motion() if s.chain is None else
                                  new.motion.moved(s.pose @ inverse_np(s.chain)))
    return dataclasses.replace(s, new=new, tie=tie, used=new.keyframe.num_edges)


def _keyframed(state: TrackerState, ev: Evidence, config: Config, s: _Step
               ) -> _Step | MakeKeyframe:
    """A keyframe reason makes the frame a keyframe (``MakeKeyframe``; too few edges: the old
    one stays). With the map, one made at a loss's guess, from a doubted frame or in a
    guessed chain is guessed: nothing verified its pose."""
    if not s.reason:
        return s
    if not ev.asked(MakeKeyframe):
        return MakeKeyframe(s.new.num_keyframes, s.pose, ev.facts.timestamp, s.new.motion)
    made = ev.answer(MakeKeyframe)
    if made is None:
        return s
    guess = s.kf.guess
    if config.map and s.lost is not None:
        guess = Guess(state.index - 1, made.keyframe.id,
                      f"made at a guess after {s.since:.1f} s lost", ev.facts.timestamp)
    elif config.map and guess is None and s.doubted and s.placed is None and s.weak:
        guess = Guess(state.index - 1, made.keyframe.id, "made from a frame not verified",
                      ev.facts.timestamp)
    kf = made.keyframe
    if guess is not None:
        kf = dataclasses.replace(kf, guess=guess)
    if s.lost is None:  # tracked against s.kf: the pose graph's edge from it
        kf = dataclasses.replace(kf, parent=s.kf.id)
    made = made._replace(keyframe=kf)
    return dataclasses.replace(s, made=made, pose=kf.pose, new=_install(s.new, kf, config))


def _concluded(state: TrackerState, ev: Evidence, config: Config, s: _Step) -> Decision:
    """The state the next frame starts from (the motion pushed; the device's prediction
    inputs: the solve's own float32 pose when nothing changed, as the scan carries it, else
    from the world poses) and the frame's result."""
    # a frame tracked in a chain made at a guess that asked the map: the chain's clock
    asked_t = None if s.placed is not None or s.new.keyframe.guess is None else (
        ev.facts.timestamp if s.asked and s.lost is None else state.asked_t)
    new = dataclasses.replace(s.new, motion=s.new.motion.push(s.pose, ev.facts.timestamp,
                                                              tracked=s.lost is None),
                              asked_t=asked_t)
    plain = (s.lost is None and s.kf.id == state.keyframe.id and s.made is None
             and s.res is ev.solve and not ev.intrinsics_moved)
    rel = ((np.asarray(s.res.T_c_k, np.float32), state.motion.rel[0]) if plain
           else relative_from_world(new.motion, new.keyframe.pose))
    new = dataclasses.replace(new, motion=dataclasses.replace(new.motion, rel=rel))
    lost, res = s.lost, s.res
    result = _result(ev, s.pose, LOST if lost else (WEAK if s.weak else OK), lost or s.weak,
                     int(res.inliers), None if lost else np.asarray(res.covariance, np.float64),
                     s.reason if s.made else None, s.used, s.made,
                     None if lost else inlier_share(res), s.placed, s.agreement)
    return Decision(new, result, (), plain, s.tie)


def _current(kf: Keyframe, facts: FrameFacts) -> Keyframe:
    """A keyframe of the map made current by a frame at ``facts.timestamp``: its interval
    and its running inlier average start anew."""
    return dataclasses.replace(kf, since=facts.timestamp, inlier_counts=())


def _tracked(state: TrackerState, kf: Keyframe, res, facts: FrameFacts, config: Config, *,
             over: bool) -> TrackerState:
    """The state after a frame tracked against ``kf`` (its inliers counted): a keyframe the
    search found (an earlier one) takes over; one of the map (``over``) takes over with the
    old current joining the earlier ones recovery tries."""
    kf = dataclasses.replace(kf, inlier_counts=(*kf.inlier_counts, int(res.inliers)))
    shares = (*state.shares, inlier_share(res))[-SHARE_HISTORY:]
    if over:
        previous = tuple(k for k in (*state.previous, state.keyframe) if k.id != kf.id)
        return dataclasses.replace(state, keyframe=kf, tracked_t=facts.timestamp, shares=shares,
                                   previous=previous[-config.recovery_keyframes:])
    return dataclasses.replace(with_keyframe(state, kf), keyframe=kf, tracked_t=facts.timestamp,
                               shares=shares)


def _recent(state: TrackerState, config: Config) -> tuple[int, ...]:
    """Ids of the keyframes a revisit leaves out: the current one, the earlier ones recovery
    tries and the window's (the last ``window_size`` made)."""
    recent = {k.id for k in (state.keyframe, *state.previous)}
    recent.update(range(max(state.num_keyframes - config.window_size, 0), state.num_keyframes))
    return tuple(sorted(recent))


def _tie(guess: Guess | None, key: int, pose: np.ndarray, chain: np.ndarray | None, *,
         far: bool = False) -> Tie:
    """What the driver does for a frame placed at ``pose`` against the map's keyframe ``key``
    (``Tie``): where the frame came from a chain made at a guess (``guess``), the window
    starts again, and with its pose in that chain (``chain``) the chain moves into the
    map's frame. A LOST frame found again on a keyframe the window no longer holds
    (``far``) starts the window again as well: the window's keyframes are from before the
    loss and see another place, and refined jointly with the ones made after it they
    moved those by up to 10 cm (docs/decisions.md, "A second opinion from depth")."""
    if guess is None:
        return Tie(key, restart=far)
    if chain is None:
        return Tie(key, restart=True)
    return Tie(key, pose @ inverse_np(chain), guess.frame, guess.keyframe, restart=True)


def _install(state: TrackerState, kf: Keyframe, config: Config) -> TrackerState:
    """``kf`` made the current keyframe; the current one joins the earlier ones recovery
    tries (``recovery_keyframes`` of them)."""
    previous = state.previous
    if state.keyframe is not None:
        previous = (*previous, state.keyframe)[-(config.recovery_keyframes):]
    return dataclasses.replace(state, keyframe=kf, previous=previous,
                               num_keyframes=state.num_keyframes + 1)


def _first(state: TrackerState, ev: Evidence, config: Config) -> Decision:
    """A frame with no keyframe to solve against (the first, or none usable yet): it becomes
    the keyframe when it has enough edges with depth, else it is LOST at its prediction. In
    a map loaded from a file, the first keyframe is made at a guess: its chain asks the map
    where it is and moves into the map's frame when a frame is found (``Tie``)."""
    if not ev.asked(MakeKeyframe):
        return Decision(state, None, (MakeKeyframe(state.num_keyframes, ev.predicted,
                                                   ev.facts.timestamp, state.motion),))
    new, pose, made = state, ev.predicted, ev.answer(MakeKeyframe)
    if made is not None:
        kf = made.keyframe
        if state.loaded and state.keyframe is None and config.map:
            kf = dataclasses.replace(kf, guess=Guess(
                state.index - 1, kf.id, "made before the run was found in the loaded map",
                ev.facts.timestamp, loaded=True))
            made = made._replace(keyframe=kf)
        pose, new = kf.pose, _install(state, kf, config)
    new = dataclasses.replace(new, motion=new.motion.push(pose, ev.facts.timestamp,
                                                          tracked=made is not None))
    if new.keyframe is not None:
        new = dataclasses.replace(new, motion=dataclasses.replace(
            new.motion, rel=relative_from_world(new.motion, new.keyframe.pose)))
    state_, reason = (OK, None) if made else (LOST, "no edges with depth")
    if made is not None and made.keyframe.guess is not None:  # not tied to the loaded map
        state_, reason = WEAK, made.keyframe.guess.reason
    result = _result(ev, pose, state_, reason, 0, None, "first" if made else None, 0,
                     made, None)
    return Decision(new, result, ())


def _result(ev: Evidence, pose, state: str, reason, inliers: int, cov, kf_reason, used: int,
            made: NewKeyframe | None, share: float | None, placed: Placed | None = None,
            agreement: float | None = None) -> FrameResult:
    t = ev.timing
    return FrameResult(
        timestamp=ev.facts.timestamp, pose=pose, state=state, reason=reason, inliers=inliers,
        covariance=cov, keyframe=kf_reason, edges_used=used,
        select_ms=made.select_ms if made else None,
        mapping_ms=t.map_ms if t.map_ms is not None and (made or t.map_ms > 0.0) else None,
        preprocess_ms=t.preprocess_ms, solve_ms=t.solve_ms,
        total_ms=t.preprocess_ms + t.elapsed_ms, inlier_share=share,
        placed=None if placed is None else placed.note, depth_agreement=agreement)
