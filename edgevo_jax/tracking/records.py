"""The streaming tracker's records: its state (``TrackerState``: the keyframe and the earlier
ones, the motion history), what the decision reads of a frame (``FrameFacts``, ``Timing``,
``Evidence``), the actions it asks the driver for (host effects) and their answers, and its
answer (``Decision``). Frozen records of plain numbers and host arrays; the rules that use
them are ``decision``'s."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np

from ..geometry import predict_np
from .results import FrameResult


class Guess(NamedTuple):
    """Where a chain of keyframes made at a guess began: the frame (its index; its timestamp
    ``t``, s) at which keyframe ``keyframe`` was made at a pose nothing verified (``why``: a
    loss's held or predicted pose, or a doubted frame's). Frames tracked from it, or from
    keyframes made after it in the chain, are not tied to the map until a frame of the
    chain is found in it. ``loaded``: the chain a run started in a map loaded from a file
    begins with (its frames ask the map beside tracking, ``Relocalise.beside``)."""

    frame: int
    keyframe: int
    why: str
    t: float
    loaded: bool = False

    @property
    def reason(self) -> str:
        """Why a frame tracked from the chain is WEAK."""
        return f"tracked from keyframe {self.keyframe}, {self.why}: not tied to the map"


@dataclass(frozen=True)
class Keyframe:
    """A keyframe: its number (``id``, from 0), timestamp (s), pose T_world_kf (4, 4), selected
    edges in use and the level-0 inliers of the frames tracked against it. ``guess``: the
    chain made at a guess it belongs to (None: tied to the map); ``since``: when it became
    the current keyframe (s; None: at its timestamp; a keyframe of the map taking over
    later counts its interval from then); ``parent``: the keyframe the frame it was made
    from was tracked against (None: the first, or one made at a loss's guess). ``edges``
    (device arrays), ``frame`` (its ``Frame``; None for a keyframe taken from the map) and
    ``features`` (its image's keypoints, each kind detected once: ``frontend.features
    .Detections``; None without a frame) are the driver's; the decision never reads them.
    ``pose`` is the tracker's copy of the map's record (``map.poses``), followed each frame
    (``decision.follow``)."""

    id: int
    timestamp: float
    pose: np.ndarray
    num_edges: int
    inlier_counts: tuple[int, ...] = ()
    guess: Guess | None = None
    since: float | None = None
    parent: int | None = None
    edges: Any = field(default=None, compare=False, repr=False)
    frame: Any = field(default=None, compare=False, repr=False)
    features: Any = field(default=None, compare=False, repr=False)

    @property
    def current_since(self) -> float:
        """When it became the current keyframe (s)."""
        return self.timestamp if self.since is None else self.since


@dataclass(frozen=True)
class Motion:
    """The last (at most two) frames' T_world_cam and timestamps, oldest first, the
    device's inputs for the next prediction: A = T_(i-1)_kf, B = T_(i-2)_kf (float32), and
    ``tracked``: T_world_cam of the last frame not LOST (None: none since the motion began),
    which the second opinion compares a frame with."""

    poses: tuple[np.ndarray, ...] = ()
    times: tuple[float, ...] = ()
    rel: tuple[np.ndarray, np.ndarray] | None = None
    tracked: np.ndarray | None = None

    def predict(self, prior: np.ndarray | None = None) -> np.ndarray:
        """The next T_world_cam: T_w_last @ prior (prior = T_prev_cur), else constant velocity
        T_w_last (T_w_prev^-1 T_w_last) (``predict_np``); the last pose with one frame."""
        if prior is not None:
            return self.poses[-1] @ prior
        if len(self.poses) < 2:
            return self.poses[-1]
        return predict_np(self.poses[1], self.poses[0])

    def push(self, pose: np.ndarray, timestamp: float, *, tracked: bool = True) -> Motion:
        """The motion with a frame at ``pose``, ``timestamp`` added (the oldest dropped);
        ``tracked``: the frame is not LOST."""
        return Motion((*self.poses, pose)[-2:], (*self.times, timestamp)[-2:], self.rel,
                      pose if tracked else self.tracked)

    def moved(self, correction: np.ndarray) -> Motion:
        """The motion with its poses moved by ``correction`` (T_world_new_world_old)."""
        return dataclasses.replace(
            self, poses=tuple(correction @ p for p in self.poses),
            tracked=None if self.tracked is None else correction @ self.tracked)


@dataclass(frozen=True)
class TrackerState:
    """What the tracker carries from frame to frame (module doc). ``previous``: the earlier
    keyframes recovery tries, oldest first; ``asked_t``: when a frame tracked in a chain made
    at a guess last asked the map where it is (s; None: none since the chain was made or
    tied); ``index``: frames concluded so far; ``loaded``: the run began in a map loaded
    from a file (its first keyframe is made at a guess: nothing ties it to that map yet)."""

    keyframe: Keyframe | None = None
    previous: tuple[Keyframe, ...] = ()
    motion: Motion = Motion()
    shares: tuple[float, ...] = ()
    tracked_t: float | None = None
    asked_t: float | None = None
    index: int = 0
    num_keyframes: int = 0
    loaded: bool = False


class FrameFacts(NamedTuple):
    """What the decision reads of the frame itself: timestamp (s), its edge count, whether any
    edge has depth."""

    timestamp: float
    num_edges: int
    has_depth: bool


class Timing(NamedTuple):
    """The driver's clocks for the frame's result (ms): preprocessing, solve (dispatch to
    read-back), the tracker's time on the local window (None with the window off), and from
    dispatch to the decision."""

    preprocess_ms: float = 0.0
    solve_ms: float = 0.0
    map_ms: float | None = None
    elapsed_ms: float = 0.0


# -- actions: host effects the decision asks for -----------------------------------------------
class Search(NamedTuple):
    """Align the frame again from other starts and keyframes (``recovery.search``); ``first``:
    the solve from the prediction, None when unusable; ``reference``: the share to beat."""

    first: Any
    reference: float | None


class Confirm(NamedTuple):
    """Align the frame to ``keyframe`` from a feature start; does it converge to ``solve``?"""

    keyframe: Keyframe
    solve: Any


class Check(NamedTuple):
    """The second opinion: the share of the depth points of the last frame not LOST that the
    frame's depth puts on their surfaces at ``T_cur_prev`` (4, 4; p_cur = T p_prev), the
    frame's motion from that frame as decided (``frontend.depth.depth_agreement``). The
    answer is that share, or None where it cannot be judged (no depth on either side, too
    little in view)."""

    T_cur_prev: np.ndarray


class Relocalise(NamedTuple):
    """Find the frame in the keyframe map (``places.Places.relocalise``): place recognition over
    its anchored keyframes and those a camera at ``guess`` (T_world_cam; None: none) would
    see, each aligned from a feature start and verified. ``motion``: the frame's motion
    from the last frame T_last_cur as its chain tracked it (the rolling shutter's velocity;
    None for a lost frame: none). ``beside``: a frame tracked in the chain a loaded map's run
    begins with: the query runs beside tracking, and the answer is the frame aligned to the
    keyframe an earlier frame's query found (``places.Places.relocalise``). The answer is a
    ``Placed`` or None."""

    guess: np.ndarray | None
    motion: np.ndarray | None = None
    beside: bool = False


class Revisit(NamedTuple):
    """Does an older keyframe of the map, one not in ``exclude`` (ids), see the frame at
    ``pose`` (T_world_cam) well enough to take over from a new keyframe
    (``places.Places.revisit``)? The answer is a ``Placed`` or None."""

    pose: np.ndarray
    exclude: tuple[int, ...]


class Placed(NamedTuple):
    """The answer to ``Relocalise`` or ``Revisit``: the map's keyframe the frame was aligned
    to, the solve (host ``TrackResult``) and how it was found (the result's ``placed``)."""

    keyframe: Keyframe
    result: Any
    note: str


class Tie(NamedTuple):
    """What a frame placed against the map's keyframe ``keyframe`` asks of the driver after
    the decision: ``correction`` (T_world_new_world_old (4, 4), or None) moves the frames
    from index ``since`` on and the keyframes of the guessed chain from id ``guessed`` on
    (None: none) into the map's frame; ``restart``: the window starts again (it holds
    keyframes of a guessed chain, whose frame is not the map's, or from before a loss)."""

    keyframe: int
    correction: np.ndarray | None = None
    since: int | None = None
    guessed: int | None = None
    restart: bool = False


class Handover(NamedTuple):
    """Wait for every refinement handed to the window and give them (``Window.due(None)``)."""


class MakeKeyframe(NamedTuple):
    """Make the frame keyframe number ``id`` at ``pose`` (T_world_cam), with the motion of the
    frames before it: select its edges and hand it to the window. The answer is its
    ``Keyframe`` (pose refined where the window runs inline) and the selection time, or None
    when it has too few usable edges."""

    id: int
    pose: np.ndarray
    timestamp: float
    motion: Motion


class NewKeyframe(NamedTuple):
    """The answer to ``MakeKeyframe``: the keyframe made and its selection's time (ms)."""

    keyframe: Keyframe
    select_ms: float


@dataclass(frozen=True)
class Evidence:
    """The frame's facts, its solve and the answers of the actions asked for so far.
    ``solve``: a ``frontend.align.TrackResult`` on the host (None for a frame with no
    keyframe to solve against); ``predicted``: the frame's predicted T_world_cam; ``prior``:
    its motion prior T_prev_cur, if given; ``intrinsics_moved``: the window's intrinsics were
    taken in this frame. ``answers``: (action type, answer) pairs, one per action asked
    (``answered``, ``asked``, ``answer``): ``Search`` a ``recovery.Found`` or None,
    ``Confirm`` a bool, ``Check`` a share or None, ``Handover`` the window's refinements
    (``window.worker.Refined``), ``Relocalise`` and ``Revisit`` a ``Placed`` or None,
    ``MakeKeyframe`` a ``NewKeyframe`` or None."""

    facts: FrameFacts
    solve: Any
    predicted: np.ndarray
    prior: np.ndarray | None = None
    timing: Timing = Timing()
    intrinsics_moved: bool = False
    answers: tuple[tuple[type, Any], ...] = ()

    def answered(self, action: Any, answer: Any) -> Evidence:
        """The evidence with ``action`` (an action record) answered by ``answer``."""
        return dataclasses.replace(self, answers=(*self.answers, (type(action), answer)))

    def asked(self, kind: type) -> bool:
        """Whether an action of type ``kind`` was asked (and answered)."""
        return any(k is kind for k, _ in self.answers)

    def answer(self, kind: type) -> Any:
        """The answer to the action of type ``kind`` (None where it was not asked)."""
        return next((a for k, a in self.answers if k is kind), None)


class Decision(NamedTuple):
    """``decide``'s answer (its doc). ``plain``: the state went on as the solve predicted it
    (no loss, recovery, keyframe or new intrinsics), so that solves of later frames made from
    the old state (a chunk, a batch) still hold; ``tie``: what a frame placed against the
    map asks of the driver (``Tie``)."""

    state: TrackerState
    result: FrameResult | None
    actions: tuple
    plain: bool = False
    tie: Tie | None = None


