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

import jax
import numpy as np

from ..camera import Intrinsics
from ..config import Config
from ..derive import basin_px
from ..frontend.features import Detections, landmark_pose, refine_pose
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
#: Lowe's ratio for the matches PnP starts from: looser than the recovery's 0.8 (more
#: matches across a wide baseline; RANSAC, guided matching and the edge solve's
#: verification after it keep a wrong pose out)
QUERY_RATIO = 0.9


class Places:
    """The map of one tracker (module doc), for frames of ``shape`` (H, W) through
    ``intrinsics``; the keyframes' poses are ``poses``' (the run's one record of them)."""

    def __init__(self, config: Config, intrinsics: Intrinsics, shape: tuple[int, int],
                 poses: Poses) -> None:
        self.config = config
        self.map = KeyframeMap(intrinsics, shape, max_keyframes=config.map_max_keyframes,
                               poses=poses)
        self.ferns = make_ferns()
        self._worker = Worker("places")  # describes keyframes
        self._describing = self._worker.queue()

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
        self._describing.submit(0, kf.id, partial(
            describe, self.ferns, kf.features, frame.depth, intrinsics,
            min_depth=config.min_depth, max_depth=config.max_depth))

    def note_share(self, key: int, share: float) -> None:
        """A frame was tracked against keyframe ``key`` with this inlier share."""
        self.map.note_share(key, share)

    def close(self) -> None:
        """Describe what is pending and stop the worker."""
        self.settle()
        self._worker.close()

    def anchor(self, first: int, correction: np.ndarray) -> list[int]:
        """The chain made at a guess from keyframe ``first`` on is tied to the map: its
        keyframes (and the frames tracked from them) take ``correction`` and are anchored;
        their ids."""
        keys = [k for k in self.map.ids if k >= first and not self.map[k].anchored]
        self.map.anchor(keys, correction)
        return keys

    def settle(self) -> None:
        """The keyframes described so far take their appearance, in the order they were
        made (waiting for the worker where needed)."""
        for key, appearance in self._describing.due(None):
            self.map.describe(key, appearance.landmarks, appearance.code)

    # -- what the decision asks ---------------------------------------------------------------
    def relocalise(self, solver: Solver, state: TrackerState, frame: Frame, ask: Relocalise,
                   timestamp: float, found: Detections | None) -> Placed | None:
        """Where the map places the frame (module doc; ``found``: its keypoints), or None."""
        self.settle()
        config = self.config
        if frame.gray is None or found is None or not len(self.map):
            return None
        code = encode(self.ferns, frame.gray, frame.depth)
        how = {c.id: "place recognition"
               for c in self.map.recognise(code, k=config.map_candidates)}
        if ask.guess is not None:
            for c in self.map.overlapping(ask.guess, k=1, min_overlap=config.map_overlap):
                how.setdefault(c.id, "the guessed pose")
        if not how:
            return None
        kps = found.get("orb", QUERY_FEATURES)
        # the rolling shutter's velocity: the frame's own motion as its chain tracked it
        # (its last pose is in the chain's frame, not the map's), none for a lost frame
        rate = solver.rate(timestamp, frame, state.motion.times)
        _, usable = aligner(solver, state, frame, timestamp)

        def align(kf: Keyframe, fr: Frame, T_c_k: np.ndarray):
            last = None if ask.motion is None else kf.pose @ inverse_np(T_c_k) \
                @ inverse_np(ask.motion)
            return solver.align(kf, fr, T_c_k, rate, last)
        reference = reference_share(state, config)
        for key, source in how.items():
            placed = self._found_on(key, source, kps, solver, frame, align, usable, reference)
            if placed is not None:
                return placed
        return None

    def _found_on(self, key: int, source: str, kps, solver: Solver, frame: Frame, align,
                  usable, reference: float | None) -> Placed | None:
        """The frame placed on keyframe ``key`` from its landmarks' pose (module doc), or
        None."""
        config, entry = self.config, self.map[key]
        if entry.landmarks is None:
            return None
        start = landmark_pose(entry.landmarks, kps, solver.intrinsics, ratio=QUERY_RATIO)
        if start is None:
            return None
        start = refine_pose(entry.landmarks, kps, start, solver.intrinsics)
        kf = _keyframe(entry)
        out = align(kf, frame, start.T_c_k)
        standard = entry.share or reference or 1.0
        if not verified(out, usable, basin_px=basin_px(config), standard=standard,
                        ratio=config.lost_share_ratio):
            return None
        note = (f"found again: keyframe {key} ({source}, {start.inliers} ORB inliers, "
                f"inlier share {inlier_share(out):.2f}")
        if verified(out, usable, basin_px=basin_px(config), standard=standard,
                    ratio=config.doubt_share_ratio):
            return Placed(kf, out, note + ")")
        other = confirmed(kf, out, self._confirmers(kf.id), frame, align, usable, reference,
                          config)
        return None if other is None else Placed(kf, out,
                                                 note + f", confirmed by keyframe {other})")

    def _confirmers(self, key: int, exclude=()) -> list[tuple[Keyframe, float | None]]:
        """The two anchored keyframes (not in ``exclude``) most covisible with keyframe
        ``key``, as ``Keyframe``s with their standard inlier share (as they are now)."""
        near = sorted(self.map.covisible(key).items(), key=lambda kv: -kv[1])
        return [(_keyframe(self.map[k]), self.map[k].share) for k, _ in
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
        keyframe ``kf`` (made from ``frame``, after the frames of ``state``) at its pose
        (``map.loops``): verified as ``revisit`` verifies, and confirmed as a doubtful frame
        found again is (``confirmed``: a keyframe covisible with the old one, not in
        ``exclude``). The candidates are chosen now; what is returned aligns the frame to
        them and reads nothing that changes (it may run on another thread): the solve of the
        frame against the first that passes (``result.T_c_k``: T_kf_old), or None. None: no
        candidate."""
        candidates = self._candidates(kf.pose, exclude)
        if not candidates:
            return None
        confirmers = {c.id: self._confirmers(c.id, exclude) for _, c in candidates}
        solver = copy.copy(solver)  # its intrinsics as they are now

        def verify() -> Placed | None:
            align, usable = aligner(solver, state, frame, timestamp)
            reference = reference_share(state, self.config)
            for old, c in candidates:
                found = self._verified(align, usable, reference, frame, kf.pose, [(old, c)])
                if found is None:
                    continue
                out = found[1]
                other = confirmed(old, out, confirmers[c.id], frame, align, usable,
                                  reference, self.config)
                if other is not None:
                    return Placed(old, out, f"loop: keyframe {kf.id} to keyframe {c.id} "
                                  f"(predicted overlap {c.score:.2f}, inlier share "
                                  f"{inlier_share(out):.2f}, confirmed by keyframe {other})")
            return None
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


def confirmed(kf: Keyframe, res, confirmers: list[tuple[Keyframe, float | None]],
              frame: Frame, align, usable, reference: float | None, config: Config
              ) -> int | None:
    """The first of ``confirmers`` (keyframe, its standard share) that confirms the pose
    ``res`` gives the frame against ``kf``: aligned from that pose, verified at the lost
    ratio of its own standard, and placing the frame within ``SECOND_M``, ``SECOND_DEG`` of
    the same world pose; its id, or None."""
    pose = kf.pose @ inverse_np(np.asarray(res.T_c_k, np.float64))
    for other, share in confirmers:
        out = align(other, frame, inverse_np(pose) @ other.pose)
        if verified(out, usable, basin_px=basin_px(config), standard=share or reference or 1.0,
                    ratio=config.lost_share_ratio) and agree(
                pose, other.pose @ inverse_np(np.asarray(out.T_c_k, np.float64)),
                metres=SECOND_M, degrees=SECOND_DEG):
            return other.id
    return None


def _keyframe(entry: MapKeyframe) -> Keyframe:
    """The tracker's record of a keyframe of the map (its edges on the device; no frame)."""
    return Keyframe(entry.id, entry.timestamp, entry.pose,
                    int(np.count_nonzero(entry.edges.valid)),
                    edges=jax.device_put(entry.edges))
