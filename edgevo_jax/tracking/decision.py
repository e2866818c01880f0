"""The per-frame decision of the streaming tracker: a pure function of the tracker's state,
the frame's solve and facts, with the host effects it needs asked for as actions.

State (``TrackerState``, ``records``): a few small frozen records: the keyframe
(``Keyframe``) and the earlier ones kept for recovery, the motion history (``Motion``: the
last two poses and their times, and the device's prediction inputs), the inlier-share history
(``shares``), the lost clock (``tracked_t``: when a frame was last tracked) and the window's
hand-over (``begin_frame``, ``refine``: keyframe poses the window refined, taken at fixed
frames).

``decide(state, evidence, config)`` reads the frame's solve and facts (``Evidence``) and
returns ``Decision(state, result, actions)``. Where it needs something only a host effect can
give, it returns the unchanged state, no result and that one action: ``Search`` (the
recovery search from other starts and keyframes), ``Confirm`` (an alignment from a feature
start), ``Relocalise`` and ``Revisit`` (the keyframe map: ``relocalise``), ``Handover`` (all
refinements the window has made, waited for) or ``MakeKeyframe`` (edge selection, the
window's hand-over of the new keyframe). The driver (``odometry.Odometry``) carries it out,
adds the outcome to the evidence and calls again; each action is asked for at most once per
frame. With every answer in, the result is the frame's ``FrameResult`` and the state is the
one the next frame starts from. The rules (docs/decisions.md), in order:

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
5. LOST: the pose is the prediction (finite, a rotation) within ``lost_extrapolate_s`` of
   the last tracked frame or with a motion prior, else the last pose, held; the keyframe stays,
   unless the loss outlasts ``kf_max_interval_s`` (a new keyframe at the guess, guessed);
6. a new keyframe is built on refined poses only (``Handover`` first); with the map, an older
   keyframe that sees the frame takes over instead where one aligns (``Revisit``); when the
   selection finds too few edges the old keyframe stays.
This module runs no JAX: each rule is tested with plain numbers (tests/pipeline/test_decision.py).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

import numpy as np

from ..config import Config
from ..derive import basin_px
from ..frontend.keyframes import keyframe_reason
from ..geometry import inverse_np, orthonormalise_np
from ..hostmem import aligned_array
from .records import (
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

__all__ = ["SHARE_HISTORY", "Confirm", "Decision", "Evidence", "FrameFacts", "Guess",
           "Handover", "Keyframe", "MakeKeyframe", "Motion", "NewKeyframe", "Placed",
           "Relocalise", "Revisit", "Search", "Tie", "Timing", "TrackerState", "begin_frame",
           "decide", "inlier_share", "lost_reason", "reference_share", "refine",
           "relative_from_world", "under", "weak_reason"]

#: frames (not lost) whose highest inlier share is the reference for the share ratios
SHARE_HISTORY = 5


# -- judging a solve ---------------------------------------------------------------------------
def inlier_share(res) -> float:
    """Level-0 inliers per keyframe edge in view of a TrackResult (0 with none in view)."""
    return float(res.inliers) / max(float(res.visible), 1.0)


def lost_reason(num_edges: int, res, config: Config) -> str | None:
    """Why a solve result cannot be used (None: it can): no edges in the frame,
    non-finite pose or covariance, too few inliers, ill-conditioned covariance."""
    if num_edges == 0:
        return "no edges in the frame"
    T = np.asarray(res.T_c_k, np.float64)
    cov = np.asarray(res.covariance, np.float64)
    if not (np.all(np.isfinite(T)) and np.all(np.isfinite(cov))):
        return "non-finite pose"
    if int(res.inliers) < config.min_inliers:
        return f"too few inliers ({int(res.inliers)})"
    eig = np.linalg.eigvalsh(0.5 * (cov + cov.T))  # symmetric: cheaper than cond's SVD
    cond = eig[-1] / eig[0] if eig[0] > 0 else np.inf
    if not cond <= config.max_covariance_condition:
        return f"covariance ill-conditioned (condition {cond:.2g})"
    return None


def weak_reason(has_depth: bool, res, config: Config) -> str | None:
    """Why a usable result is doubtful: inliers whose mean residual is over half the gate
    (random matches under the gate average half of it), or a frame without depth (it
    cannot become a keyframe)."""
    mean = float(res.mean_residual)
    if mean > 0.5 * config.max_residual[0]:
        return f"mean residual {mean:.2f} px over half the gate"
    if not has_depth:
        return "no depth (cannot become a keyframe)"
    return None


def reference_share(state: TrackerState, config: Config) -> float | None:
    """The highest inlier share of the last ``SHARE_HISTORY`` frames not lost; None before
    there are any or with the check off (``doubt_share_ratio`` 0)."""
    if not state.shares or config.doubt_share_ratio <= 0:
        return None
    return float(np.max(state.shares))


def under(res, reference: float | None, ratio: float) -> bool:
    """Whether a result's inlier share is under ``ratio`` x the reference share."""
    return reference is not None and inlier_share(res) < ratio * reference


# -- the window's hand-over ----------------------------------------------------------------------
def refine(state: TrackerState, mapped: Sequence[Any]) -> TrackerState:
    """Take the window's refined keyframe poses (``mapping.Mapped``: ``key`` the keyframe's
    id, ``pose``): each keyframe kept takes its new pose; when it is the current keyframe the
    last two frame poses move with it (their motion relative to it, which the device predicts
    from, is unchanged). A keyframe the state no longer holds (one a recovery left) is
    skipped."""
    for m in mapped:
        kf = next((k for k in (state.keyframe, *state.previous) if k is not None
                   and k.id == m.key), None)
        if kf is None:
            continue
        motion = state.motion
        if state.keyframe is not None and kf.id == state.keyframe.id:
            correction = m.pose @ inverse_np(kf.pose)
            motion = dataclasses.replace(motion, poses=tuple(correction @ p for p in motion.poses))
        state = dataclasses.replace(_with_keyframe(state, dataclasses.replace(kf, pose=m.pose)),
                                    motion=motion)
    return state


def begin_frame(state: TrackerState, due: Sequence[Any]) -> TrackerState:
    """Count the frame being concluded and take the refinements ``due`` at it (``refine``)."""
    return refine(dataclasses.replace(state, index=state.index + 1), due)


def _with_keyframe(state: TrackerState, kf: Keyframe) -> TrackerState:
    """``kf`` in place of every record of the same keyframe (current and earlier)."""
    def swap(k):
        return kf if k is not None and k.id == kf.id else k
    return dataclasses.replace(state, keyframe=swap(state.keyframe),
                               previous=tuple(swap(k) for k in state.previous))


def relative_from_world(motion: Motion, kf_pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A, B (float32) from the last two world poses and the keyframe's (float64)."""
    rel = [aligned_array(inverse_np(p) @ kf_pose, np.float32) for p in motion.poses]
    return rel[-1], rel[0]


# -- the decision ------------------------------------------------------------------------------
def decide(state: TrackerState, ev: Evidence, config: Config) -> Decision:
    """The frame's decision (module doc): the next state, the frame's result and no action;
    or the unchanged state, no result and the one action the decision needs answered first."""
    if ev.solve is None:
        return _first(state, ev, config)
    facts, res, kf = ev.facts, ev.solve, state.keyframe
    start_id, confirmed = kf.id, False
    lost = lost_reason(facts.num_edges, res, config)
    reference = reference_share(state, config)
    doubt, lost_ratio = config.doubt_share_ratio, config.lost_share_ratio
    # lost or doubted (a wrong basin, as after a prediction far off): other starts and other
    # keyframes; with no reference yet (the first frames) every start is tried
    if facts.num_edges > 0 and (lost is not None or under(res, reference, doubt)
                                or (reference is None and doubt > 0)):
        if not ev.searched:
            return Decision(state, None, (Search(None if lost else res, reference),))
        if ev.found is not None:
            kf, res, confirmed = ev.found
            lost = None
    if lost is None and under(res, reference, lost_ratio):
        lost = (f"inlier share {inlier_share(res):.2f} under {lost_ratio:g} x the recent "
                f"{reference:.2f} from every start")
    weak, doubted = None, kf.guess is not None
    if lost is None:
        weak = weak_reason(facts.has_depth, res, config)
        if weak is None and not confirmed:
            gap = None if state.tracked_t is None else facts.timestamp - state.tracked_t
            weak = _doubt_reason(res, reference, config, ev.confirmed, gap)
            if weak is _ASK:
                return Decision(state, None, (Confirm(kf, res),))
            doubted = doubted or weak is not None
        weak = weak or (kf.guess.reason if kf.guess is not None else None)
    # found again: a lost or doubted frame, or one tracked from a keyframe made at a guess,
    # asks the map where it is
    # the map's keyframe it was placed on; its pose in its chain and that chain's guess
    placed, chain, chain_guess = None, None, None
    if config.map and facts.num_edges > 0 and (lost is not None or doubted):
        if not ev.relocalise_asked:
            if lost is not None:
                return Decision(state, None, (Relocalise(state.motion.poses[-1]),))
            guess = kf.pose @ inverse_np(np.asarray(res.T_c_k, np.float64))
            return Decision(state, None, (Relocalise(
                guess, inverse_np(state.motion.poses[-1]) @ guess),))
        if ev.relocalised is not None:
            if lost is None:
                chain = kf.pose @ inverse_np(orthonormalise_np(np.asarray(res.T_c_k,
                                                                          np.float64)))
            placed, chain_guess = ev.relocalised, kf.guess
            kf, res, lost, weak = _current(placed.keyframe, facts), placed.result, None, None
    new = state
    if lost is None:
        T_c_k = orthonormalise_np(np.asarray(res.T_c_k, np.float64))
        reason = keyframe_reason(
            flow=float(res.flow), flow_t=float(res.flow_t), inliers=int(res.inliers),
            inlier_mean=float(np.mean(kf.inlier_counts)) if kf.inlier_counts else None,
            dt=facts.timestamp - kf.current_since, config=config)
        new = _tracked(state, kf, res, facts, config, over=placed is not None)
    else:  # the prediction, flagged; the keyframe stays (docs/decisions.md), unless the loss
        # outlasts the keyframe interval: the old view may be gone for good
        since = facts.timestamp - (state.tracked_t if state.tracked_t is not None
                                   else kf.timestamp)
        reason = "lost" if since >= config.kf_max_interval_s else None
    # a new keyframe is built on refined poses only; a lost frame takes them as well
    handed = False
    if reason or lost is not None:
        if ev.handover is None:
            return Decision(state, None, (Handover(),))
        new = refine(new, ev.handover)
        handed = bool(ev.handover)
    if lost is None:
        pose = new.keyframe.pose @ inverse_np(T_c_k)
    elif ev.prior is None and since > config.lost_extrapolate_s:
        # too long for the last velocity: the last pose, held
        pose = new.motion.poses[-1]
    else:  # constant velocity over a short gap; a motion prior (an IMU, wheels) is evidence
        pose = new.motion.predict(ev.prior) if handed else ev.predicted
        # lost frames in a row extrapolate again and again: keep R a rotation, stay finite
        pose = orthonormalise_np(pose) if np.all(np.isfinite(pose)) else pose
        if not np.all(np.isfinite(pose)):
            pose = new.motion.poses[-1]
    # a revisit: an older keyframe of the map that sees the frame takes over from a new one
    if config.map and reason and lost is None and placed is None and not doubted:
        if not ev.revisit_asked:
            return Decision(state, None, (Revisit(pose, _recent(new, config)),))
        if ev.revisited is not None:
            placed, chain, reason = ev.revisited, pose, None
            kf, res = _current(placed.keyframe, facts), placed.result
            T_c_k = orthonormalise_np(np.asarray(res.T_c_k, np.float64))
            new = _tracked(refine(state, ev.handover), kf, res, facts, config, over=True)
            pose = kf.pose @ inverse_np(T_c_k)
    tie = None
    if placed is not None:  # the motion moves into the map's frame with the frame, before a
        # keyframe made from it reads its velocity (rolling shutter, depth timing)
        tie = _tie(chain_guess or state.keyframe.guess, kf.id, pose, chain)
        new = dataclasses.replace(new, motion=Motion() if chain is None else dataclasses.replace(
            new.motion, poses=tuple(pose @ inverse_np(chain) @ p for p in new.motion.poses)))
    used = new.keyframe.num_edges
    made = None
    if reason:
        if not ev.made_asked:
            return Decision(state, None, (MakeKeyframe(new.num_keyframes, pose, facts.timestamp,
                                                       new.motion),))
        made = ev.made
    if made is not None:
        # a keyframe made at a loss's guess, from a doubted frame or in a guessed chain is
        # guessed: nothing verified its pose
        guess = kf.guess
        if config.map and lost is not None:
            guess = Guess(state.index - 1, made.keyframe.id,
                          f"made at a guess after {since:.1f} s lost")
        elif config.map and guess is None and doubted and placed is None and weak:
            guess = Guess(state.index - 1, made.keyframe.id, "made from a frame not verified")
        if guess is not None:
            made = made._replace(keyframe=dataclasses.replace(made.keyframe, guess=guess))
        if lost is None:  # tracked against kf: the pose graph's edge from it
            made = made._replace(keyframe=dataclasses.replace(made.keyframe, parent=kf.id))
        pose, new = made.keyframe.pose, _install(new, made.keyframe, config)
    new = dataclasses.replace(new, motion=new.motion.push(pose, facts.timestamp))
    plain = (lost is None and kf.id == start_id and made is None and res is ev.solve
             and not ev.intrinsics_moved)
    # the device predicts the next frame from A, B: the solve's own float32 pose when nothing
    # changed (as the scan carries it), else from the world poses
    rel = ((np.asarray(res.T_c_k, np.float32), state.motion.rel[0]) if plain
           else relative_from_world(new.motion, new.keyframe.pose))
    new = dataclasses.replace(new, motion=dataclasses.replace(new.motion, rel=rel))
    result = _result(ev, pose, LOST if lost else (WEAK if weak else OK), lost or weak,
                     int(res.inliers), None if lost else np.asarray(res.covariance, np.float64),
                     reason if made else None, used, made,
                     None if lost else inlier_share(res), placed)
    return Decision(new, result, (), plain, tie)


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
    return dataclasses.replace(_with_keyframe(state, kf), keyframe=kf, tracked_t=facts.timestamp,
                               shares=shares)


def _recent(state: TrackerState, config: Config) -> tuple[int, ...]:
    """Ids of the keyframes a revisit leaves out: the current one, the earlier ones recovery
    tries and the window's (the last ``window_size`` made)."""
    recent = {k.id for k in (state.keyframe, *state.previous)}
    recent.update(range(max(state.num_keyframes - config.window_size, 0), state.num_keyframes))
    return tuple(sorted(recent))


def _tie(guess: Guess | None, key: int, pose: np.ndarray, chain: np.ndarray | None) -> Tie:
    """What the driver does for a frame placed at ``pose`` against the map's keyframe ``key``
    (``Tie``): where the frame came from a chain made at a guess (``guess``), the window
    starts again, and with its pose in that chain (``chain``) the chain moves into the
    map's frame."""
    if guess is None:
        return Tie(key)
    if chain is None:
        return Tie(key, restart=True)
    return Tie(key, pose @ inverse_np(chain), guess.frame, guess.keyframe, restart=True)


_ASK = object()  # _doubt_reason: the confirmation is needed and was not asked yet


def _doubt_reason(res, reference: float | None, config: Config, confirmed: bool | None,
                  gap: float | None = None):
    """Why a usable solve nothing independent confirmed is doubtful (WEAK): its share stayed
    under ``doubt_share_ratio`` of the recent frames' from every start; or it moved farther
    from its start than the alignment's basin (``derive.basin_px``), or its frame comes more
    than ``lost_extrapolate_s`` after the last tracked one (``gap``, s: a start predicted
    across a gap that long is no evidence, and the recent shares say little of a view that
    far), and no feature start converges to it (``confirmed``: the ``Confirm`` answer;
    ``_ASK`` while not asked)."""
    doubt = config.doubt_share_ratio
    if under(res, reference, doubt):
        return (f"inlier share {inlier_share(res):.2f} under {doubt:g} x the recent "
                f"{reference:.2f}, not confirmed by features")
    basin, moved = basin_px(config), float(res.moved)
    far = gap is not None and gap > config.lost_extrapolate_s
    if moved > basin or far:
        if confirmed is None:
            return _ASK
        if not confirmed:
            return (f"moved {moved:.0f} px from its start, past the {basin:.0f} px basin, not "
                    "confirmed by features" if moved > basin else
                    f"{gap:.2f} s after the last tracked frame, not confirmed by features")
    return None


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
    the keyframe when it has enough edges with depth, else it is LOST at its prediction."""
    if not ev.made_asked:
        return Decision(state, None, (MakeKeyframe(state.num_keyframes, ev.predicted,
                                                   ev.facts.timestamp, state.motion),))
    new, pose = state, ev.predicted
    if ev.made is not None:
        pose, new = ev.made.keyframe.pose, _install(state, ev.made.keyframe, config)
    new = dataclasses.replace(new, motion=new.motion.push(pose, ev.facts.timestamp))
    if new.keyframe is not None:
        new = dataclasses.replace(new, motion=dataclasses.replace(
            new.motion, rel=relative_from_world(new.motion, new.keyframe.pose)))
    state_, reason = (OK, None) if ev.made else (LOST, "no edges with depth")
    result = _result(ev, pose, state_, reason, 0, None, "first" if ev.made else None, 0,
                     ev.made, None)
    return Decision(new, result, ())


def _result(ev: Evidence, pose, state: str, reason, inliers: int, cov, kf_reason, used: int,
            made: NewKeyframe | None, share: float | None, placed: Placed | None = None
            ) -> FrameResult:
    t = ev.timing
    return FrameResult(
        timestamp=ev.facts.timestamp, pose=pose, state=state, reason=reason, inliers=inliers,
        covariance=cov, keyframe=kf_reason, edges_used=used,
        select_ms=made.select_ms if made else None,
        mapping_ms=t.map_ms if t.map_ms is not None and (made or t.map_ms > 0.0) else None,
        preprocess_ms=t.preprocess_ms, solve_ms=t.solve_ms,
        total_ms=t.preprocess_ms + t.elapsed_ms, inlier_share=share,
        placed=None if placed is None else placed.note)
