"""The back end: what outlives a frame, behind the one small interface the driver
(``odometry.Odometry``) calls.

Events: ``tick`` (a frame begins: the loops' solve and searches due, the window's
refinements due), ``start`` and ``keyframe_made`` (its pose recorded; handed to the window) and
``concluded`` (the frame recorded, hanging from its keyframe; the keyframe it made joins the
map and looks for a loop; a tie to the map carried out). Queries the decision waits for:
``handover`` (every refinement the window has made), ``relocalise`` (where is this frame)
and ``revisit`` (does an older keyframe take over). What moved: the keyframes the tracker's
state must follow (``tick`` returns them, ``Moved``), earlier frames (``corrections``) and the
window's refinements (``refinements``).

The back end owns the run's one record of poses (``map.poses.Poses``): every keyframe's pose
(the window's refinements, the pose graph's and the ties' corrections are written there and
nowhere else) and every frame, hanging from its keyframe. The window (``window.worker``)
runs whether or not the map does; with ``Config.map`` off the map is a ``NullMap``, which
keeps nothing, answers no query and moves no frame (the paper's odometry, bit for bit).
"""

from __future__ import annotations

import dataclasses
import time
from typing import NamedTuple

import numpy as np

from ..config import Config
from ..frontend.features import Detections
from ..image.preprocess import Frame
from ..map.archive import MapFileError, load_map, map_settings
from ..map.ledger import Ledger
from ..map.loops import Closed, Loops
from ..map.poses import Correction, Poses
from ..window.worker import Refined, Window
from .decision import Decision, Placed, Relocalise, Revisit, TrackerState
from .effects import Made, Solver
from .places import Places
from .results import LOST, OK, Refinement


class Moved(NamedTuple):
    """A keyframe whose pose moved in the record: its id (``key``) and new ``pose``
    T_world_kf (what ``decision.follow`` reads)."""

    key: int
    pose: np.ndarray


class Backend:
    """The back end of one tracker (module doc): ``solver`` is the tracker's (the window's
    intrinsics are written to it where ``Config.mapping_intrinsics``), ``readout_s`` its
    rolling shutter's readout (0: a global one)."""

    def __init__(self, config: Config, solver: Solver, readout_s: float) -> None:
        self.config, self.solver, self._readout_s = config, solver, readout_s
        self.poses = Poses()
        self.window: Window | None = None  # made with the first keyframe (image size)
        self.map: NullMap = KeyframeMapPart(self) if config.map else NullMap()
        self.refinements: list[Refinement] = []  # as taken
        self.corrections: list[Correction] = []  # earlier poses moved, in order
        self.moved: list[Moved] = []  # keyframes moved after the last tick (a tie's chain)
        self.ms = 0.0  # the tracker's time on the window in this frame (ms)
        self.intrinsics_moved = False  # the window's intrinsics were taken in this frame
        self.loaded = None  # a map loaded from a file (``load``: ``archive.Saved``) to start in
        self.loaded_path = None  # its file

    def load(self, path) -> int:
        """Start in the keyframe map saved at ``path`` (``map.archive``; MapFileError where it
        does not fit this run's camera or settings): its keyframes' poses join the record;
        the id the next keyframe takes."""
        if not self.config.map:
            raise ValueError("a map file needs the keyframe map: Config.map is off")
        self.loaded = load_map(path, intrinsics=self.solver.intrinsics,
                               settings=map_settings(self.config),
                               max_keyframes=self.config.map_max_keyframes, poses=self.poses)
        self.loaded_path = path
        return max(self.loaded.kmap.ids) + 1

    # -- events ------------------------------------------------------------------------------
    def tick(self, index: int) -> list[Moved]:
        """Frame ``index`` begins: the loops' solve due is taken (its keyframes move, and the
        frames tracked from them: a ``Correction``), their searches due join the graph and
        the next solve is submitted; then the window's refinements due at it are taken. The
        keyframes that moved since the last frame (a tie's chain), in order."""
        self.ms, self.intrinsics_moved = 0.0, False
        moved, self.moved = self.moved, []
        moved += self.map.tick(index)
        return moved + [Moved(r.key, r.pose) for r in self._due(index + 1, index)]

    def handover(self, index: int) -> list[Refined]:
        """Every refinement handed to the window, waited for and taken (frame ``index``, being
        concluded, makes a keyframe or is lost)."""
        return self._due(None, index)

    def start(self, shape: tuple[int, int], *, warm_up: bool) -> None:
        """A keyframe is about to be made from a frame of ``shape`` (H, W): the first makes
        the window (its programs compiling beside tracking from now where ``warm_up``) and
        the map."""
        if self.config.mapping and self.window is None:
            self.window = Window(self.config, self.solver.intrinsics, shape,
                                 rolling_shutter=self._readout_s > 0)
            if warm_up:
                self.window.warm_up()
        self.map.start(shape)

    def keyframe_made(self, made: Made, frame: Frame, index: int) -> Made:
        """A keyframe made from frame ``index``: its pose joins the record and it goes to the
        window; with the window inline, the keyframe as refined."""
        kf = made.keyframe
        self.poses.add_keyframe(kf.id, kf.pose, kf.timestamp)
        if self.window is None:
            return made
        t0 = time.perf_counter()
        refined = self.window.add(kf.id, kf.pose, made.host_edges, frame, index + 1,
                                  made.row_twist)
        if refined is not None:  # inline: refined already
            made = made._replace(keyframe=dataclasses.replace(kf, pose=refined.pose))
            self._take(refined, index)
        self.ms += (time.perf_counter() - t0) * 1e3
        return made

    def concluded(self, d: Decision, made: Made | None, frame: Frame, before: TrackerState
                  ) -> None:
        """A frame was concluded (``d``; ``made``: the keyframe it made from ``frame``, if any;
        ``before``: the state it was tracked from): it hangs from its keyframe in the record,
        and the map takes its part."""
        kf, result = d.state.keyframe, d.result
        index = self.poses.add_frame(None if kf is None else kf.id, result.timestamp,
                                     result.pose, lost=result.state == LOST)
        self.map.concluded(d, made, frame, before, index)

    def finish(self, index: int) -> list[Moved]:
        """The run ends after frame ``index``: what is pending is finished now, not dropped:
        the window's refinements are taken, the loops' searches join the graph and a last
        pose-graph solve moves the keyframes (and the frames tracked from them: a
        ``Correction``). The keyframes that moved, in order."""
        moved = [Moved(r.key, r.pose) for r in self._due(None, index)]
        return moved + self.map.finish(index)

    def restart_window(self) -> None:
        """Stop the window (its refinements on their way dropped); the next keyframe starts
        a new one."""
        if self.window is not None:
            self.window.close()
            self.window = None

    def close(self) -> None:
        """Stop the workers: the window's (refinements not taken are dropped), the map's
        describer (keyframes made are described first) and the loops' (a search or solve not
        taken is dropped)."""
        if self.window is not None:
            self.window.close()
        self.map.close()

    # -- queries -------------------------------------------------------------------------------
    def relocalise(self, state: TrackerState, frame: Frame, ask: Relocalise, timestamp: float,
                   found: Detections | None) -> Placed | None:
        """Where the map places the frame (``places.Places.relocalise``), or None."""
        return self.map.relocalise(state, frame, ask, timestamp, found)

    def revisit(self, state: TrackerState, frame: Frame, ask: Revisit, timestamp: float
                ) -> Placed | None:
        """An older keyframe of the map that takes over (``places.Places.revisit``), or
        None."""
        return self.map.revisit(state, frame, ask, timestamp)

    # -- internals -----------------------------------------------------------------------------
    def _due(self, frame: int | None, index: int) -> list[Refined]:
        """The window's refinements due at ``frame`` (None: all handed over), waited for and
        taken at frame ``index`` (``_take``)."""
        if self.window is None:
            return []
        t0 = time.perf_counter()
        taken = self.window.due(frame)
        for refined in taken:
            self._take(refined, index)
        if taken:
            self.ms += (time.perf_counter() - t0) * 1e3
        return taken

    def _take(self, refined: Refined, index: int) -> None:
        """A refinement taken at frame ``index``: the keyframe's pose in the record (the
        pose graph's edge from its parent measured), ``refinements``, and the window's
        intrinsics where they are refined."""
        key = refined.key
        self.refinements.append(Refinement(self.poses.keyframe_time(key), index,
                                           self.poses.keyframe(key), refined.pose))
        self.poses.refine(key, refined.pose)
        self.map.measure(key)
        if self.config.mapping_intrinsics and \
                tuple(refined.intrinsics) != tuple(self.solver.intrinsics):
            self.solver.intrinsics = refined.intrinsics
            self.intrinsics_moved = True  # solves made with the old ones are stale


class NullMap:
    """The keyframe map with ``Config.map`` off: it keeps nothing beyond the record of poses,
    answers no query and moves no frame."""

    keyframe_map = None  #: the keyframe map (``map.store.KeyframeMap``): none
    loop_stats = None  #: the pose graph's statistics (``map.loops.Loops.stats``): none

    def start(self, shape: tuple[int, int]) -> None:
        """A keyframe is made from frames of ``shape`` (H, W)."""

    def graph_edges(self, keys) -> list:
        """The pose graph's measured edges between keyframes of ``keys``: none."""
        return []

    def tick(self, index: int) -> list[Moved]:
        """Frame ``index`` begins: the keyframes the loops moved (none)."""
        return []

    def finish(self, index: int) -> list[Moved]:
        """The run ends after frame ``index``: the keyframes the loops moved (none)."""
        return []

    def measure(self, key: int) -> None:
        """Keyframe ``key``'s pose is final (refined)."""

    def concluded(self, d: Decision, made: Made | None, frame: Frame, before: TrackerState,
                  index: int) -> None:
        """The map's part of concluded frame ``index`` (none)."""

    def relocalise(self, state: TrackerState, frame: Frame, ask: Relocalise, timestamp: float,
                   found: Detections | None) -> Placed | None:
        """Where the frame is: nowhere known."""
        return None

    def revisit(self, state: TrackerState, frame: Frame, ask: Revisit, timestamp: float
                ) -> Placed | None:
        """No older keyframe takes over."""
        return None

    def close(self) -> None:
        """Nothing to stop."""


class KeyframeMapPart(NullMap):
    """The keyframe map's part of ``backend`` (``Config.map``; made with the first keyframe):
    the map (``places.Places``: every keyframe, recognition, the queries), the ledger of
    frames a tie may still move (``map.ledger``) and, with ``Config.loops``, the loops and
    their pose graph (``map.loops``)."""

    def __init__(self, backend: Backend) -> None:
        self.backend, self.config = backend, backend.config
        self.places: Places | None = None
        self.loops: Loops | None = None
        self.ledger = Ledger(backend.poses)

    @property
    def keyframe_map(self):
        """The keyframe map (``map.store.KeyframeMap``; None before the first keyframe), its
        keyframes described."""
        if self.places is None:
            return None
        self.places.settle()
        return self.places.map

    @property
    def loop_stats(self) -> dict | None:
        """The pose graph so far (``Loops.stats``; None with ``Config.loops`` off)."""
        if not self.config.loops:
            return None
        if self.loops is None:
            return {"closed": [], "rejected": [], "solves": []}
        return self.loops.stats(self.places.map)

    def start(self, shape: tuple[int, int]) -> None:
        """The first keyframe makes the map (and the loops)."""
        if self.places is None:
            b, loaded = self.backend, self.backend.loaded
            if loaded is not None and tuple(loaded.kmap.shape) != tuple(shape):
                h, w = loaded.kmap.shape
                raise MapFileError(f"{b.loaded_path}: the map was made from {w}x{h} images, "
                                   f"this run's are {shape[1]}x{shape[0]}: another camera")
            self.places = Places(self.config, b.solver.intrinsics, shape, b.poses,
                                 kmap=None if loaded is None else loaded.kmap)
            self.loops = Loops(self.config) if self.config.loops else None
            if self.loops is not None and loaded is not None:
                self.loops.load(loaded.kmap.ids, loaded.edges)

    def tick(self, index: int) -> list[Moved]:
        """The loops' solve due at frame ``index`` taken (``_close``), their searches due
        joined to the graph and the next solve submitted; the keyframes it moved."""
        if self.loops is None:
            return []
        closed = self.loops.due(index)
        moved = [] if closed is None else self._close(closed)
        self.loops.found(index)
        self.loops.submit(self.places.map, index)
        return moved

    def finish(self, index: int) -> list[Moved]:
        """The run ends after frame ``index``: the solve in flight is taken, the searches in
        flight join the graph, and a solve they call for is made and taken now."""
        if self.loops is None:
            return []
        closed = self.loops.due(None)
        moved = [] if closed is None else self._close(closed)
        self.loops.found(None)
        if self.loops.submit(self.places.map, index):
            moved += self._close(self.loops.due(None))
        return moved

    def measure(self, key: int) -> None:
        """Keyframe ``key``'s pose is final: the pose graph's edge from its parent takes it."""
        if self.loops is not None:
            self.loops.measure(key, self.places.map)

    def concluded(self, d: Decision, made: Made | None, frame: Frame, before: TrackerState,
                  index: int) -> None:
        """The map's part of concluded frame ``index`` (``Backend.concluded``): the keyframe
        it made joins the map (and the pose graph, which looks for a loop it closes); its
        share counts for its keyframe; a ``Tie`` moves the guessed chain into the map's frame
        (with the frames tracked from it: ``corrections``) and starts the window again (its
        keyframes were in the chain's frame); the frames it settles may move (``ledger``:
        LOST frames filled in)."""
        kf, result, tie = d.state.keyframe, d.result, d.tie
        if self.places is not None:
            if made is not None and result.keyframe is not None:
                self.places.add(kf, made.host_edges, frame, self.backend.solver.intrinsics)
                self._search(kf, result.covariance, frame, before, index)
            if result.state == OK and result.inlier_share is not None:
                self.places.note_share(kf.id, result.inlier_share)
        chain = []
        if tie is not None and tie.correction is not None and tie.guessed is not None:
            self.places.placed_in_map()
            chain = self.places.anchor(tie.guessed, tie.correction)
            self.backend.moved += [Moved(k, self.backend.poses.keyframe(k)) for k in chain]
        settled = tie is not None or (result.state == OK and kf is not None
                                      and kf.guess is None)
        moved = self.ledger.record(index, settled=settled, moved=frozenset(chain))
        if moved is not None:
            self.backend.corrections.append(moved)
        if tie is not None and tie.restart:
            self.backend.restart_window()

    def relocalise(self, state: TrackerState, frame: Frame, ask: Relocalise, timestamp: float,
                   found: Detections | None) -> Placed | None:
        """``places.Places.relocalise`` (None before the first keyframe)."""
        if self.places is None:
            return None
        return self.places.relocalise(self.backend.solver, state, frame, ask, timestamp, found)

    def revisit(self, state: TrackerState, frame: Frame, ask: Revisit, timestamp: float
                ) -> Placed | None:
        """``places.Places.revisit`` (None before the first keyframe)."""
        if self.places is None:
            return None
        return self.places.revisit(self.backend.solver, state, frame, ask, timestamp)

    def close(self) -> None:
        """Stop the describer (keyframes made are described first) and the loops' worker."""
        if self.places is not None:
            self.places.close()
        if self.loops is not None:
            self.loops.close()

    def graph_edges(self, keys) -> list:
        """The pose graph's measured edges between keyframes of ``keys`` (``Loops.edges``;
        none with ``Config.loops`` off)."""
        return [] if self.loops is None else self.loops.edges(keys)

    def _search(self, kf, covariance, frame: Frame, before: TrackerState, index: int) -> None:
        """A keyframe joined the map: it joins the pose graph (its edge from its parent
        measured now unless the window has it beside tracking), and where no search is in
        flight, one for a loop it closes starts beside tracking (``places.Places.loop``),
        joining the graph ``loop_lag`` frames later."""
        loops = self.loops
        if loops is None:
            return
        loops.keyframe(kf.id, kf.parent, covariance)
        window = self.backend.window
        if window is None or kf.id not in window.pending:
            loops.measure(kf.id, self.places.map)
        if kf.guess is None and loops.searches():
            verify = self.places.loop(self.backend.solver, before, frame, kf,
                                      loops.tied(kf.id), kf.timestamp)
            if verify is not None:
                loops.search(kf.id, verify, index + 1)

    def _close(self, closed: Closed) -> list[Moved]:
        """A solved pose graph: each keyframe of the map it moves moves in the record (and
        the frames tracked from it: one ``Correction`` "loop") and in the window (refinements
        on their way are moved as they come: ``Window.move``)."""
        poses, kmap = self.backend.poses, self.places.map
        moves = self.loops.corrections(closed, kmap.ids)
        if not moves:
            return []
        poses.move(moves, orthonormalise=True)
        if self.backend.window is not None:
            self.backend.window.move(moves)
        first = poses.first_hanging_from(moves)
        if first is not None:
            self.backend.corrections.append(Correction(first, len(poses) - 1,
                                                       poses.poses(first), reason="loop"))
        return [Moved(key, poses.keyframe(key)) for key in moves]
