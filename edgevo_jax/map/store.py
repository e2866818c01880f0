"""The keyframe map: every keyframe the tracker made, with what aligning a frame to it again
needs, its appearance code, and which keyframes see the same scene.

A ``MapKeyframe`` keeps its pose T_world_kf, its selected edges with their inverse depths
and the depth residual's points (``KeyframeEdges`` on the host: what the edge alignment of a
later frame reads; the frame's own distance fields are the other half), its ORB keypoints
lifted with the keyframe's depth (``features.Landmarks``: a feature start without the
keyframe's images) and its fern code (``recognition``). No image is kept.

``KeyframeMap`` answers two questions: which keyframes look like a frame
(``recognise``: place recognition by fern codes) and which would see a camera at a pose
(``overlapping``: the share of a keyframe's edges that project into the image, its
*predicted overlap*). Covisibility (``covisible``) is the same overlap between keyframes,
taken both ways when a keyframe joins. A keyframe made at a guess (after a loss) joins
unanchored: no query returns it until ``anchor`` ties it to the map.

Memory: ``nbytes``; ``max_keyframes`` caps it, and a keyframe refused at the cap is said
(``full_at`` and a ``MapFullWarning``). Host side, numpy; not thread-safe (the tracker's
thread owns it).
"""

from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Iterable
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from ..camera import Intrinsics
from ..frontend.features import Detections, Keypoints, Landmarks, landmarks
from ..frontend.selection import KeyframeEdges
from ..geometry import inverse_np
from .poses import Poses
from .recognition import NUM_FERNS, Ferns, encode, similarity

__all__ = ["Appearance", "Candidate", "KeyframeMap", "MapFullWarning", "MapKeyframe", "edge_points",
           "describe", "predicted_overlap"]

#: a keyframe viewed from an optical axis more than this far from its own (degrees) is not
#: projected for its overlap: past the field of view (~60 degrees across) little is shared
MAX_AXIS_DEG = 60.0
#: nor one whose camera is farther from the query's than this many times the median depth
#: of its edges: its scene would be seen across more than twice its own distance
MAX_DISTANCE_DEPTHS = 2.0
#: the points per keyframe a query projects (an even subsample of its edges): a share of
#: 64 points is within ~6 % of the share of all of them (binomial), and a query over 1,000
#: keyframes projects them in one array
QUERY_POINTS = 64


class MapFullWarning(UserWarning):
    """The map reached ``Config.map_max_keyframes``: later keyframes are not kept in it."""


@dataclass(frozen=True)
class MapKeyframe:
    """One keyframe of the map (module doc): ``id`` (the tracker's keyframe number),
    ``timestamp`` (s), ``pose`` T_world_kf (4, 4) float64, ``edges`` (host arrays),
    ``points`` (3, N) float32: its valid edges' points in its camera (m), ``landmarks`` (None
    without a gray image and depth, or not described yet), ``code`` (NUM_FERNS,) uint8 (None:
    not described yet; ``KeyframeMap.describe``), ``anchored`` (False: made at a guess, not
    tied to the map yet) and ``share``: the highest inlier share of a frame
    tracked against it (0: none yet), the standard a relocalised frame is held to."""

    id: int
    timestamp: float
    pose: np.ndarray
    edges: KeyframeEdges
    points: np.ndarray
    landmarks: Landmarks | None
    code: np.ndarray | None
    anchored: bool = True
    share: float = 0.0

    @property
    def nbytes(self) -> int:
        """Bytes held by its arrays."""
        arrays = [a for a in self.edges if a is not None]
        return int(sum(np.asarray(a).nbytes for a in arrays) + self.points.nbytes
                   + (0 if self.code is None else self.code.nbytes)
                   + (0 if self.pose is None else self.pose.nbytes)
                   + (self.landmarks.nbytes if self.landmarks is not None else 0))


class Appearance(NamedTuple):
    """What a frame shows place recognition and the feature start: its ORB keypoints (None
    without a gray image), those lifted with its depth (None without depth) and its fern
    code."""

    keypoints: Keypoints | None
    landmarks: Landmarks | None
    code: np.ndarray


def describe(ferns: Ferns, found: Detections | None, depth: np.ndarray | None,
             intr: Intrinsics, *, min_depth: float, max_depth: float) -> Appearance:
    """A keyframe's ``Appearance`` from its keypoints (``found``: its image's
    ``features.Detections``, of which ORB is taken; None: no gray image) and depth
    (``features.landmarks``; the fern code, from the depth alone without a gray image)."""
    if found is None:
        h, w = depth.shape if depth is not None else (1, 1)
        return Appearance(None, None, encode(ferns, np.zeros((h, w), np.uint8), depth))
    kps = found.get("orb")
    lm = None if depth is None else landmarks(kps, depth, intr, min_depth=min_depth,
                                              max_depth=max_depth)
    return Appearance(kps, lm, encode(ferns, found.gray, depth))


class Candidate(NamedTuple):
    """A keyframe a query returned and its score (fern similarity or predicted overlap)."""

    id: int
    score: float


def edge_points(edges: KeyframeEdges, intr: Intrinsics) -> np.ndarray:
    """(3, N) float32: the valid edges' points in the keyframe's camera (m), from their pixels
    and inverse depths."""
    valid = np.asarray(edges.valid, bool)
    uv = np.asarray(edges.uv, np.float64)[:, valid]
    z = 1.0 / np.asarray(edges.rho, np.float64)[valid]
    fx, fy, cx, cy = (float(v) for v in intr)
    return np.stack([(uv[0] - cx) / fx * z, (uv[1] - cy) / fy * z, z]).astype(np.float32)


def predicted_overlap(points: np.ndarray, T_c_k: np.ndarray, intr: Intrinsics,
                      shape: tuple[int, int], *, min_depth: float = 0.1) -> float:
    """The share (0-1) of a keyframe's edge points (3, N) in its camera that a camera at
    T_cur_kf (4, 4) sees: in front of it (depth over ``min_depth``) and inside its image
    (H, W). 0 for a keyframe without points."""
    if points.shape[1] == 0:
        return 0.0
    T = np.asarray(T_c_k, np.float64)
    p = T[:3, :3] @ points.astype(np.float64) + T[:3, 3:]
    fx, fy, cx, cy = (float(v) for v in intr)
    z = p[2]
    front = z > min_depth
    zs = np.where(front, z, 1.0)
    u, v = fx * p[0] / zs + cx, fy * p[1] / zs + cy
    h, w = shape
    inside = front & (u >= -0.5) & (u <= w - 0.5) & (v >= -0.5) & (v <= h - 0.5)
    return float(np.count_nonzero(inside)) / points.shape[1]


class KeyframeMap:
    """Every keyframe of a run, for a camera with ``intrinsics`` and frames of ``shape``
    (H, W); at most ``max_keyframes`` of them (module doc)."""

    def __init__(self, intrinsics: Intrinsics, shape: tuple[int, int], *,
                 max_keyframes: int, poses: Poses | None = None) -> None:
        if max_keyframes < 1:
            raise ValueError(f"max_keyframes must be positive, got {max_keyframes}")
        self.intrinsics, self.shape, self.max_keyframes = intrinsics, tuple(shape), max_keyframes
        self.full_at: int | None = None  #: the first keyframe refused at the cap
        #: the keyframes' poses (the run's one record of them; its own where none is given)
        self.poses = Poses() if poses is None else poses
        self._entries: dict[int, MapKeyframe] = {}
        self._covisible: dict[int, dict[int, float]] = {}
        self._rows: dict[int, int] = {}  # id -> row of the arrays below
        self._row_ids: list[int] = []  # row -> id
        cap = 64
        self._codes = np.zeros((cap, NUM_FERNS), np.uint8)
        self._depths = np.zeros(cap)  # median depth of each keyframe's edges
        self._points = np.full((cap, QUERY_POINTS, 3), np.nan, np.float32)  # NaN: none
        self._live = np.zeros(cap, bool)  # anchored: what queries may return
        self._described = np.zeros(cap, bool)  # with a code: what recognition may return

    # -- contents ------------------------------------------------------------------------
    def __len__(self) -> int:
        return len(self._entries)

    def __contains__(self, key: int) -> bool:
        return key in self._entries

    def __getitem__(self, key: int) -> MapKeyframe:
        """Keyframe ``key`` with its pose as it is now (``poses``)."""
        return dataclasses.replace(self._entries[key], pose=self.poses.keyframe(key))

    @property
    def ids(self) -> list[int]:
        """The keyframes' ids, in the order they joined."""
        return list(self._entries)

    @property
    def nbytes(self) -> int:
        """Bytes held by the keyframes and the query arrays."""
        arrays = (self._codes, self._depths, self._live, self._described, self._points)
        return int(sum(e.nbytes for e in self._entries.values())
                   + sum(a.nbytes for a in arrays) + 16 * 8 * len(self._entries))  # poses

    def add(self, kf: MapKeyframe) -> bool:
        """Keep ``kf`` (its covisibility with the keyframes that overlap it is taken now); its
        pose joins ``poses`` unless they hold it already. False, and a ``MapFullWarning`` the
        first time, when the map holds ``max_keyframes`` already. ValueError for an id
        already kept or a code of another length."""
        if kf.id in self._entries:
            raise ValueError(f"keyframe {kf.id} is in the map already")
        if kf.code is not None and kf.code.shape != (NUM_FERNS,):
            raise ValueError(f"a code has {NUM_FERNS} ferns, got shape {kf.code.shape}")
        if len(self._entries) >= self.max_keyframes:
            if self.full_at is None:
                self.full_at = kf.id
                warnings.warn(f"the keyframe map holds {self.max_keyframes} keyframes "
                              f"(Config.map_max_keyframes): keyframe {kf.id} and later ones "
                              "are not kept in it", MapFullWarning, stacklevel=2)
            return False
        row = len(self._rows)
        if row == len(self._live):
            self._grow()
        self._rows[kf.id] = row
        self._row_ids.append(kf.id)
        if kf.id not in self.poses:
            self.poses.add_keyframe(kf.id, kf.pose, kf.timestamp)
        self._entries[kf.id] = dataclasses.replace(kf, pose=None)  # ``poses`` holds it
        if kf.code is not None:
            self._codes[row], self._described[row] = kf.code, True
        n = kf.points.shape[1]
        if n:
            pick = np.linspace(0, n - 1, min(n, QUERY_POINTS)).astype(int)
            self._points[row, :len(pick)] = kf.points[:, pick].T
        self._place(kf)
        self._covisible[kf.id] = {}
        if kf.anchored:
            self._link(kf.id)
        return True

    def describe(self, key: int, landmarks: Landmarks | None, code: np.ndarray) -> None:
        """A kept keyframe's appearance, described after it joined: recognition returns it
        from now on."""
        if code.shape != (NUM_FERNS,):
            raise ValueError(f"a code has {NUM_FERNS} ferns, got shape {code.shape}")
        row = self._rows[key]
        self._entries[key] = dataclasses.replace(self._entries[key], landmarks=landmarks,
                                                 code=code)
        self._codes[row], self._described[row] = code, True

    def note_share(self, key: int, share: float) -> None:
        """A frame was tracked against keyframe ``key`` with this inlier share."""
        kf = self._entries.get(key)
        if kf is not None and share > kf.share:
            self._entries[key] = dataclasses.replace(kf, share=float(share))

    def anchor(self, keys: Iterable[int], correction: np.ndarray) -> None:
        """Tie keyframes made at a guess to the map: each of ``keys`` kept is moved by
        ``correction`` (T_world_new_world_guess (4, 4); ``poses.move``: the frames tracked
        from it move with it) and anchored."""
        C = np.asarray(correction, np.float64)
        keys = [key for key in keys if key in self._entries]
        self.poses.move({key: C for key in keys})
        for key in keys:
            kf = self._entries[key]
            self._entries[key] = dataclasses.replace(kf, anchored=True)
            self._place(self._entries[key])
            if not kf.anchored:
                self._link(key)

    def covisible_as(self, key: int, weights: dict[int, float]) -> None:
        """Keyframe ``key``'s covisibility set to ``weights`` (other id -> weight, both ways),
        as a saved map had it (``archive``): the weights ``add`` takes from the poses of the
        moment a keyframe joins, which later refinements move."""
        for other in list(self._covisible[key]):
            self._covisible[other].pop(key, None)
        self._covisible[key] = {}
        for other, weight in weights.items():
            self._covisible[key][int(other)] = float(weight)
            self._covisible[int(other)][key] = float(weight)

    def covisible(self, key: int) -> dict[int, float]:
        """Keyframes that see the scene of keyframe ``key``: id -> covisibility (0-1, the
        smaller of the two predicted overlaps when the later one joined)."""
        return dict(self._covisible.get(key, {}))

    # -- queries ---------------------------------------------------------------------------
    def recognise(self, code: np.ndarray, *, k: int, exclude: Iterable[int] = ()
                  ) -> list[Candidate]:
        """The ``k`` anchored, described keyframes (not in ``exclude``) whose codes are most
        like ``code``, most alike first (ties: the older first); empty when there is none."""
        rows = self._live_rows(exclude)
        rows = rows[self._described[rows]]
        if not rows.size:
            return []
        score = similarity(self._codes[rows], np.asarray(code, np.uint8))
        order = np.argsort(-score, kind="stable")[:k]
        return [Candidate(self._row_ids[rows[i]], float(score[i])) for i in order]

    def overlapping(self, T_w_c: np.ndarray, *, k: int, min_overlap: float,
                    exclude: Iterable[int] = ()) -> list[Candidate]:
        """The ``k`` anchored keyframes (not in ``exclude``) that a camera at T_world_cam
        would see best, by predicted overlap (at least ``min_overlap``), best first."""
        T = np.asarray(T_w_c, np.float64)
        rows = self._near(T, self._live_rows(exclude))
        if not rows.size:
            return []
        share = self._overlaps(inverse_np(T), rows)
        # of those that see enough of it, the nearest views first (a far keyframe sees all
        # of a camera's view as well, across a baseline its features do not match over)
        poses = self._poses_of(rows)
        angle = np.arccos(np.clip(poses[:, :3, 2] @ T[:3, 2], -1.0, 1.0))
        dist = np.linalg.norm(poses[:, :3, 3] - T[:3, 3], axis=1) / np.maximum(
            self._depths[rows], 1e-3) + angle
        keep = np.flatnonzero(share >= min_overlap)
        order = keep[np.argsort(dist[keep], kind="stable")][:k]
        return [Candidate(self._row_ids[rows[i]], float(share[i])) for i in order]

    # -- internals -------------------------------------------------------------------------
    def _grow(self) -> None:
        def bigger(a: np.ndarray) -> np.ndarray:
            out = np.zeros((2 * len(a), *a.shape[1:]), a.dtype)
            out[:len(a)] = a
            return out
        self._codes, self._depths, self._live, self._described = (
            bigger(a) for a in (self._codes, self._depths, self._live, self._described))
        points = np.full((2 * len(self._points), *self._points.shape[1:]), np.nan, np.float32)
        points[:len(self._points)] = self._points
        self._points = points

    def _place(self, kf: MapKeyframe) -> None:
        row = self._rows[kf.id]
        self._depths[row] = float(np.median(kf.points[2])) if kf.points.shape[1] else 0.0
        self._live[row] = kf.anchored

    def _live_rows(self, exclude: Iterable[int]) -> np.ndarray:
        live = self._live[:len(self._rows)].copy()
        for key in exclude:
            if key in self._rows:
                live[self._rows[key]] = False
        return np.flatnonzero(live)

    def _near(self, T_w_c: np.ndarray, rows: np.ndarray) -> np.ndarray:
        """The rows of ``rows`` whose keyframes' views could overlap a camera at T_w_c
        (``MAX_AXIS_DEG``, ``MAX_DISTANCE_DEPTHS``), in the order they joined."""
        if not rows.size:
            return rows
        poses = self._poses_of(rows)
        cos = poses[:, :3, 2] @ T_w_c[:3, 2]  # the optical axes
        dist = np.linalg.norm(poses[:, :3, 3] - T_w_c[:3, 3], axis=1)
        near = (cos >= np.cos(np.radians(MAX_AXIS_DEG))) \
            & (dist <= MAX_DISTANCE_DEPTHS * self._depths[rows])
        return rows[near]

    def _overlaps(self, T_c_w: np.ndarray, rows: np.ndarray) -> np.ndarray:
        """The predicted overlap of the keyframes of ``rows`` with a camera at T_cam_world:
        (len(rows),)."""
        return self._share(T_c_w[None] @ self._poses_of(rows), self._points[rows])

    def _share(self, T_c_k: np.ndarray, points: np.ndarray) -> np.ndarray:
        """``predicted_overlap`` of points (n, P, 3) (NaN rows: none) at T_cur_kf (n, 4, 4),
        in one array: (n,)."""
        p = points.astype(np.float64) @ np.swapaxes(T_c_k[:, :3, :3], 1, 2) \
            + T_c_k[:, None, :3, 3]
        fx, fy, cx, cy = (float(v) for v in self.intrinsics)
        z = p[..., 2]
        has = np.isfinite(z)
        front = has & (z > 0.1)
        zs = np.where(front, z, 1.0)
        u, v = fx * p[..., 0] / zs + cx, fy * p[..., 1] / zs + cy
        h, w = self.shape
        inside = front & (u >= -0.5) & (u <= w - 0.5) & (v >= -0.5) & (v <= h - 0.5)
        return np.count_nonzero(inside, axis=1) / np.maximum(np.count_nonzero(has, axis=1), 1)

    def _poses_of(self, rows: np.ndarray) -> np.ndarray:
        """(len(rows), 4, 4) T_world_kf of the keyframes of ``rows``."""
        return self.poses.keyframes([self._row_ids[r] for r in rows])

    def _link(self, key: int) -> None:
        """Covisibility of an anchored keyframe with the anchored ones near it: the smaller
        of the two predicted overlaps (each keyframe's points seen from the other)."""
        pose = self.poses.keyframe(key)
        rows = self._near(pose, self._live_rows([key]))
        if not rows.size:
            return
        poses = self._poses_of(rows)
        theirs = self._share(inverse_np(pose)[None] @ poses, self._points[rows])
        mine = self._share(inverse_np(poses) @ pose,
                           np.broadcast_to(self._points[self._rows[key]],
                                           (len(rows), QUERY_POINTS, 3)))
        for r, weight in zip(rows, np.minimum(theirs, mine), strict=True):
            if weight > 0:
                other = self._row_ids[r]
                self._covisible[key][other] = float(weight)
                self._covisible[other][key] = float(weight)
