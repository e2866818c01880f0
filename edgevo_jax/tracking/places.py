"""The keyframe map in the tracker's hands (``Places``): keyframes join it as they are made,
and it answers the decision's ``Relocalise`` (found again) and ``Revisit`` (an older keyframe
takes over) and the loops' search (``loop``); every answer is an alignment judged by the one
judgement of a verified alignment (``verify.verified``).

Found again (``relocalise``): the frame's fern code picks the ``Config.map_candidates``
anchored keyframes that look most like it (``map.recognition``), and the keyframe a camera
at the guessed pose would see best joins them (predicted overlap); each in turn gives a
start from its ORB landmarks matched to the frame's keypoints (EPnP in RANSAC), the edge
alignment refines it, and the place is accepted when verified against the keyframe's own
standard (the best share a frame ever had against it): at the doubt ratio on its own, at
the lost ratio with a second keyframe that puts the frame at the same pose (``confirmed``).
The first candidate accepted wins; none: the query found nothing, and says so (None).
Beside tracking (``Relocalise.beside``: a run started in a map loaded from a file, its
frames tracked in their own frame): one frame's query at a time runs on a worker of its own
and is taken ``Config.map_query_lag`` frames later; a place it found puts the chain in the
map's frame, and the frame then is aligned to that keyframe from there and accepted when
verified at the lost ratio and within ``SECOND_M``, ``SECOND_DEG`` of where the earlier
frame's place puts it (``_placed_beside``): the tracker pays a fern code and one alignment.

Revisit (``revisit``): the anchored keyframes outside the window that would see the frame at
its tracked pose (predicted overlap at least ``Config.map_overlap``), best first; the first
whose alignment from that pose is verified at the doubt ratio of the recent share takes
over from the new keyframe the frame asked for. A loop (``loop``) is found the same way for a
new keyframe, and confirmed by a second keyframe.

A keyframe joins the map when it is made; its appearance (ORB keypoints and the fern code)
is described on a worker of its own, at the lowest priority, while the tracker goes on, and
joins it, in order, before the next query that reads it (``settle``; a revisit reads
geometry only): when it is computed never changes what the map holds.
"""

from __future__ import annotations

import copy
from collections.abc import Callable
from functools import partial
from typing import NamedTuple

import jax
import numpy as np

from ..camera import Intrinsics
from ..config import Config
from ..derive import basin_px
from ..frontend.features import Detections, detect, landmark_pose, refine_pose
from ..frontend.selection import KeyframeEdges
from ..geometry import inverse_np
from ..image.preprocess import Frame
from ..map import (
    Candidate,
    KeyframeMap,
    MapKeyframe,
    Poses,
    describe,
    edge_points,
    encode,
    make_ferns,
)
from ..workers import Worker
from .decision import (
    Keyframe,
    Placed,
    Relocalise,
    Revisit,
    TrackerState,
    inlier_share,
    reference_share,
)
from .effects import Solver, aligner
from .verify import SECOND_DEG, SECOND_M, agree, verified

#: ORB keypoints of a frame being relocalised (a keyframe keeps 1000): twice as many match a
#: keyframe's across a wide baseline (teddy 17 degrees apart: 30 ratio-test matches against
#: none with 1000); only relocalising frames pay the ~3 ms more
QUERY_FEATURES = 2000
#: keyframes a loop search tries, most alike first: recognition's top 3 hold a keyframe that
#: sees the query well for 94-100 % of the shared clips' frames (scripts/place_recognition.py),
#: and each costs the loops' worker a PnP and one or two alignments
LOOP_CANDIDATES = 3
#: keyframes a query beside tracking tries (the most alike): one each, as the next frame's
#: query follows ``map_query_lag`` frames later; each costs the worker a match and a PnP
BESIDE_CANDIDATES = 1
#: Lowe's ratio for the matches PnP starts from: looser than the recovery's 0.8 (more
#: matches across a wide baseline; RANSAC, guided matching and the edge solve's
#: verification after it keep a wrong pose out)
QUERY_RATIO = 0.9


class Places:
    """The map of one tracker (module doc), for frames of ``shape`` (H, W) through
    ``intrinsics``; the keyframes' poses are ``poses``' (the run's one record of them);
    ``kmap``: a map loaded from a file to start from (its poses in ``poses``)."""

    def __init__(self, config: Config, intrinsics: Intrinsics, shape: tuple[int, int],
                 poses: Poses, *, kmap: KeyframeMap | None = None) -> None:
        self.config = config
        self.map = kmap if kmap is not None else KeyframeMap(
            intrinsics, shape, max_keyframes=config.map_max_keyframes, poses=poses)
        self.ferns = make_ferns()
        self._worker = Worker("places")  # describes keyframes
        self._describing = self._worker.queue()
        self._asking: Worker | None = None  # queries beside tracking (made at the first)
        self._queries = None  # their results: (frame index, its pose in its chain)

    # -- what the tracker tells it --------------------------------------------------------
    def add(self, kf: Keyframe, edges: KeyframeEdges, frame: Frame,
            intrinsics: Intrinsics) -> None:
        """A keyframe was made: ``kf`` (anchored unless ``kf.guess``) joins the map with its
        host edges at once; its appearance is described from ``frame`` (and the keypoints
        ``kf.features``) on a worker."""
        config = self.config
        if not self.map.add(MapKeyframe(kf.id, kf.timestamp, kf.pose, edges,
                                        edge_points(edges, self.map.intrinsics), None, None,
                                        anchored=kf.guess is None)):
            return
        self._describing.submit(kf.id, kf.id, partial(
            describe, self.ferns, kf.features, frame.depth, intrinsics,
            min_depth=config.min_depth, max_depth=config.max_depth))

    def note_share(self, key: int, share: float) -> None:
        """A frame was tracked against keyframe ``key`` with this inlier share."""
        self.map.note_share(key, share)

    def close(self) -> None:
        """Describe what is pending and stop the workers (a query beside tracking not taken
        is dropped)."""
        self.settle()
        self._worker.close()
        if self._asking is not None:
            self._queries.clear()
            self._asking.close()

    def placed_in_map(self) -> None:
        """The chain is tied to the map: queries beside tracking still pending are dropped
        (their tasks finish on the worker)."""
        if self._queries is not None:
            self._queries.clear()

    def anchor(self, first: int, correction: np.ndarray) -> list[int]:
        """The chain made at a guess from keyframe ``first`` on is tied to the map: its
        keyframes (and the frames tracked from them) take ``correction`` and are anchored;
        their ids."""
        keys = [k for k in self.map.ids if k >= first and not self.map[k].anchored]
        self.map.anchor(keys, correction)
        return keys

    def settle(self, before: int | None = None) -> None:
        """The keyframes made so far (``before``: those with a smaller id) take their
        appearance, in the order they were made (waiting for the worker where needed)."""
        for key, appearance in self._describing.due(None if before is None else before - 1):
            self.map.describe(key, appearance.landmarks, appearance.code)

    # -- what the decision asks ---------------------------------------------------------------
    def relocalise(self, solver: Solver, state: TrackerState, frame: Frame, ask: Relocalise,
                   timestamp: float, found: Detections | None) -> Placed | None:
        """Where the map places the frame (module doc; ``found``: its keypoints), or None."""
        if ask.beside:
            return self._beside(solver, state, frame, ask, timestamp)
        self.settle()
        if frame.gray is None or found is None or not len(self.map):
            return None
        candidates = self._by_appearance(encode(self.ferns, frame.gray, frame.depth),
                                         k=self.config.map_candidates, guess=ask.guess)
        if not candidates:
            return None
        # the rolling shutter's velocity: the frame's own motion as its chain tracked it
        # (its last pose is in the chain's frame, not the map's), none for a lost frame
        align, usable = _aligner(solver, state, frame, timestamp, ask.motion)
        return place(candidates, found.get("orb", QUERY_FEATURES), frame, align, usable,
                     reference_share(state, self.config), self.config, intr=solver.intrinsics,
                     label="found again")

    def _beside(self, solver: Solver, state: TrackerState, frame: Frame, ask: Relocalise,
                timestamp: float) -> Placed | None:
        """A frame tracked in its own frame, asking the map beside tracking (module doc):
        the query due at this frame is taken (a place it found: ``_placed_beside``), and
        where none is in flight this frame's starts on the worker. The loaded map's
        keyframes are described when loaded: this waits for no description."""
        index, placed = state.index - 1, None
        if self._queries is None:
            self._asking = Worker("queries")
            self._queries = self._asking.queue(self.config.map_query_lag)
        for (j, chain_j), answer in self._queries.due(index):
            if answer is not None and placed is None:
                placed = self._placed_beside(solver, state, frame, ask, timestamp, answer,
                                             chain_j, j)
        if placed is None and not len(self._queries) and frame.gray is not None:
            candidates = self._by_appearance(encode(self.ferns, frame.gray, frame.depth),
                                             k=BESIDE_CANDIDATES)
            if candidates:
                self._queries.submit(index, (index, ask.guess), partial(
                    _query, copy.copy(solver), state, frame, timestamp, ask.motion,
                    candidates, reference_share(state, self.config), self.config))
        return placed

    def _placed_beside(self, solver: Solver, state: TrackerState, frame: Frame,
                       ask: Relocalise, timestamp: float, answer: Placed,
                       chain_j: np.ndarray, j: int) -> Placed | None:
        """The frame aligned to the keyframe the query of frame ``j`` (``chain_j``: its pose
        in its chain then) placed it on, from the pose that place gives this frame's pose
        in the chain (``ask.guess``); a ``Placed`` when verified at the lost ratio and
        within ``SECOND_M``, ``SECOND_DEG`` of that pose, else None."""
        entry = self.map[answer.keyframe.id]
        kf, config = _keyframe(entry), self.config
        placed_j = answer.keyframe.pose @ inverse_np(np.asarray(answer.result.T_c_k,
                                                                np.float64))
        pose = placed_j @ inverse_np(chain_j) @ ask.guess
        align, usable = _aligner(solver, state, frame, timestamp, ask.motion)
        out = align(kf, frame, inverse_np(pose) @ kf.pose)
        if not (verified(out, usable, basin_px=basin_px(config),
                         standard=entry.share or reference_share(state, config) or 1.0,
                         ratio=config.lost_share_ratio) and
                agree(pose, kf.pose @ inverse_np(np.asarray(out.T_c_k, np.float64)),
                      metres=SECOND_M, degrees=SECOND_DEG)):
            return None
        return Placed(kf, out, f"{answer.note}; at frame {j}, beside tracking: this frame "
                      f"aligned from there, inlier share {inlier_share(out):.2f}")

    def _by_appearance(self, code: np.ndarray, *, k: int, guess: np.ndarray | None = None,
                       exclude=()) -> list[_Candidate]:
        """The ``k`` anchored keyframes (not in ``exclude``) whose fern codes are most like
        ``code``, and, with a ``guess`` (T_world_cam), the keyframe a camera there sees with
        the nearest view (``map_overlap`` or more of it), as ``_Candidate``s: the map's
        entries as they are now, which a search beside tracking may read."""
        how = {c.id: "place recognition"
               for c in self.map.recognise(code, k=k, exclude=exclude)}
        if guess is not None:
            for c in self.map.overlapping(guess, k=1, min_overlap=self.config.map_overlap,
                                          exclude=exclude):
                how.setdefault(c.id, "the guessed pose")
        return [_Candidate(self.map[key], source, self._confirmers(key, exclude))
                for key, source in how.items()]

    def _confirmers(self, key: int, exclude=()) -> list[MapKeyframe]:
        """The two anchored keyframes (not in ``exclude``) most covisible with keyframe
        ``key``, as they are now."""
        near = sorted(self.map.covisible(key).items(), key=lambda kv: -kv[1])
        return [self.map[k] for k, _ in
                [kv for kv in near if self.map[kv[0]].anchored and kv[0] not in exclude][:2]]

    def revisit(self, solver: Solver, state: TrackerState, frame: Frame, ask: Revisit,
                timestamp: float) -> Placed | None:
        """An older keyframe of the map that takes over from a new one (module doc), or
        None. Geometry only: it waits for no description."""
        # a place left and seen again: not one the recent keyframes still see
        recent = set(ask.exclude)
        seen = recent.union(*(self.map.covisible(k) for k in recent if k in self.map))
        candidates = self._candidates(ask.pose, seen)
        if not candidates:
            return None
        align, usable = aligner(solver, state, frame, timestamp)
        found = self._verified(align, usable, reference_share(state, self.config), frame,
                               ask.pose, candidates)
        if found is None:
            return None
        kf, out, c = found
        return Placed(kf, out, f"revisit: keyframe {c.id} takes over (predicted overlap "
                      f"{c.score:.2f}, inlier share {inlier_share(out):.2f})")

    def loop(self, solver: Solver, state: TrackerState, frame: Frame, kf: Keyframe,
             exclude: set[int], timestamp: float) -> Callable[[], Placed | None] | None:
        """The search for an older keyframe of the map, not in ``exclude``, that sees the new
        keyframe ``kf`` (made from ``frame``, after the frames of ``state``), found by what
        the camera sees and verified without the chain's pose (``map.loops``): the
        ``LOOP_CANDIDATES`` keyframes whose fern codes are most like the frame's, each a
        start from its landmarks matched to the frame's keypoints (PnP in RANSAC), refined by
        the edge alignment, verified (``verify.verified``) and always confirmed by a second
        keyframe covisible with the old one (``confirmed``). The candidates are chosen now;
        what is returned reads nothing that changes (it runs on the loops' worker): the
        solve of the frame against the first that passes (``result.T_c_k``: T_kf_old), or
        None. None: no candidate (no gray image, nothing alike)."""
        self.settle(before=kf.id)  # its own description may go on beside tracking
        if frame.gray is None or kf.features is None:
            return None
        candidates = self._by_appearance(encode(self.ferns, frame.gray, frame.depth),
                                         k=LOOP_CANDIDATES, exclude=exclude)
        if not candidates:
            return None
        solver = copy.copy(solver)  # its intrinsics as they are now
        # the frame's own motion in its chain, for the rolling shutter's velocity
        motion = inverse_np(state.motion.poses[-1]) @ kf.pose if state.motion.poses else None
        reference, config, found = reference_share(state, self.config), self.config, kf.features

        def verify() -> Placed | None:
            align, usable = _aligner(solver, state, frame, timestamp, motion)
            return place(candidates, found.get("orb", QUERY_FEATURES), frame, align, usable,
                         reference, config, intr=solver.intrinsics, label="loop",
                         always_confirm=True, newer=kf.id)
        return verify

    def _candidates(self, pose: np.ndarray, exclude) -> list[tuple[Keyframe, Candidate]]:
        """The two anchored keyframes (not in ``exclude``) a camera at ``pose`` (T_world_cam)
        sees best, with a predicted overlap of at least ``map_overlap``, as ``Keyframe``s
        (their poses as they are now)."""
        return [(_keyframe(self.map[c.id]), c) for c in self.map.overlapping(
            pose, k=2, min_overlap=self.config.map_overlap, exclude=exclude)]

    def _verified(self, align, usable, reference: float | None, frame: Frame, pose: np.ndarray,
                  candidates: list[tuple[Keyframe, Candidate]]):
        """The first candidate the frame, at ``pose``, aligns to (``align``, ``usable``:
        ``effects.aligner``'s) verified at the doubt ratio of the recent share ``reference``;
        (its ``Keyframe``, the solve, its ``Candidate``) or None."""
        config = self.config
        for kf, c in candidates:
            out = align(kf, frame, inverse_np(pose) @ kf.pose)
            if verified(out, usable, basin_px=basin_px(config), standard=reference,
                        ratio=config.doubt_share_ratio):
                return kf, out, c
        return None


class _Candidate(NamedTuple):
    """A keyframe of the map a search tries: its entry (pose as it was when chosen, edges,
    landmarks, standard share), how it was found and the keyframes that may confirm it."""

    entry: MapKeyframe
    source: str
    confirmers: list[MapKeyframe]


def place(candidates: list[_Candidate], kps, frame: Frame, align, usable,
          reference: float | None, config: Config, *, intr: Intrinsics, label: str,
          always_confirm: bool = False, newer: int | None = None) -> Placed | None:
    """The frame placed on the first of ``candidates`` that passes (module doc): a start
    from the candidate's landmarks matched to the frame's keypoints ``kps`` (EPnP in RANSAC,
    refined by guided matching), the edge alignment from there (``align``, ``usable``:
    ``_aligner``'s), verified at the lost ratio of the candidate's standard share (its own
    best, else ``reference``), and at the doubt ratio or confirmed by a second keyframe
    (``confirmed``; ``always_confirm``: confirmed in any case). None: none passes. Reads
    only what it is given: it may run beside tracking."""
    basin = basin_px(config)
    for c in candidates:
        entry = c.entry
        if entry.landmarks is None:
            continue
        start = landmark_pose(entry.landmarks, kps, intr, ratio=QUERY_RATIO)
        if start is None:
            continue
        start = refine_pose(entry.landmarks, kps, start, intr)
        kf = _keyframe(entry)
        out = align(kf, frame, start.T_c_k)
        standard = entry.share or reference or 1.0
        if not verified(out, usable, basin_px=basin, standard=standard,
                        ratio=config.lost_share_ratio):
            continue
        what = f"keyframe {newer} to keyframe {entry.id}" if newer is not None \
            else f"keyframe {entry.id}"
        note = (f"{label}: {what} ({c.source}, {start.inliers} ORB inliers, inlier share "
                f"{inlier_share(out):.2f}")
        if not always_confirm and verified(out, usable, basin_px=basin, standard=standard,
                                           ratio=config.doubt_share_ratio):
            return Placed(kf, out, note + ")")
        other = confirmed(kf, out, c.confirmers, frame, align, usable, reference, config)
        if other is not None:
            return Placed(kf, out, note + f", confirmed by keyframe {other})")
    return None


def _query(solver: Solver, state: TrackerState, frame: Frame, timestamp: float,
           motion: np.ndarray | None, candidates: list[_Candidate], reference: float | None,
           config: Config) -> Placed | None:
    """A frame's query beside tracking (``Places._beside``): its keypoints detected here,
    placed on the first of ``candidates`` that passes (``place``). Reads only what it is
    given."""
    align, usable = _aligner(solver, state, frame, timestamp, motion)
    kps = detect(frame.gray, kind="orb", max_features=QUERY_FEATURES)
    return place(candidates, kps, frame, align, usable, reference, config,
                 intr=solver.intrinsics, label="found in the loaded map")


def confirmed(kf: Keyframe, res, confirmers: list[MapKeyframe], frame: Frame, align, usable,
              reference: float | None, config: Config) -> int | None:
    """The first of ``confirmers`` (keyframes of the map) that confirms the pose ``res``
    gives the frame against ``kf``: aligned from that pose, verified at the lost ratio of
    its own standard share, and placing the frame within ``SECOND_M``, ``SECOND_DEG`` of the
    same world pose; its id, or None."""
    pose = kf.pose @ inverse_np(np.asarray(res.T_c_k, np.float64))
    for entry in confirmers:
        other = _keyframe(entry)
        out = align(other, frame, inverse_np(pose) @ other.pose)
        if verified(out, usable, basin_px=basin_px(config),
                    standard=entry.share or reference or 1.0,
                    ratio=config.lost_share_ratio) and agree(
                pose, other.pose @ inverse_np(np.asarray(out.T_c_k, np.float64)),
                metres=SECOND_M, degrees=SECOND_DEG):
            return other.id
    return None


def _aligner(solver: Solver, state: TrackerState, frame: Frame, timestamp: float,
             motion: np.ndarray | None):
    """``align(kf, frame, T_cur_kf)`` and ``usable(solve)`` for a frame placed on keyframes
    of the map: the rolling shutter's velocity from ``motion`` (T_last_cur: the frame's own
    motion in its chain, whose frame is not the map's; None: none, for a lost frame)."""
    rate = solver.rate(timestamp, frame, state.motion.times)
    _, usable = aligner(solver, state, frame, timestamp)

    def align(kf: Keyframe, fr: Frame, T_c_k: np.ndarray):
        last = None if motion is None else kf.pose @ inverse_np(T_c_k) @ inverse_np(motion)
        return solver.align(kf, fr, T_c_k, rate, last)
    return align, usable


def _keyframe(entry: MapKeyframe) -> Keyframe:
    """The tracker's record of a keyframe of the map (its edges on the device; no frame)."""
    return Keyframe(entry.id, entry.timestamp, entry.pose,
                    int(np.count_nonzero(entry.edges.valid)),
                    edges=jax.device_put(entry.edges))
