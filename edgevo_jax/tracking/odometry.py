"""The streaming tracker ``Odometry``: a thin driver over the per-frame decision.

Per frame (DESIGN.md): host preprocessing -> one jitted device solve against the keyframe's
edges -> ``decision.decide`` (state, solve, frame facts) -> the actions it asks for
(recovery search, confirmation, the window's hand-over, a new keyframe: ``effects``) ->
the frame's result and the next state.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass

import numpy as np

from ..camera import Intrinsics
from ..config import Config
from ..derive import readout_time
from ..frontend.align import TrackResult
from ..frontend.selection import KeyframeEdges
from ..geometry import inverse_np, orthonormalise_np
from ..hostmem import to_host
from ..image.preprocess import Frame, preprocess
from ..learn.params import Params
from ..map.ledger import Ledger
from ..map.loops import Closed, Loops
from ..programs import enable_cache, release_compiled
from ..window.worker import Mapped, Mapper
from . import decision
from .effects import Solver, confirm, make_keyframe, search, warm_up
from .inputs import check_frame, increasing, rigid_transform
from .places import Places
from .results import LOST, OK, WEAK, Correction, FrameResult, Refinement

__all__ = ["LOST", "OK", "WEAK", "Correction", "FrameResult", "Odometry"]


@dataclass(frozen=True)
class _Pending:
    """A frame whose solve has been dispatched (asynchronously) but not read back yet."""

    frame: Frame
    timestamp: float
    predicted: np.ndarray
    output: object  # TrackResult of device arrays, or None for the first frame
    preprocess_ms: float
    t_submit: float
    prior: np.ndarray | None = None  # T_prev_cur (4, 4) given with the frame


class Odometry:
    """Streaming RGB-D edge odometry.

    >>> odo = Odometry(Config(), Intrinsics(535.4, 539.2, 320.1, 247.6))
    >>> result = odo.track(rgb, depth_m, timestamp)  # doctest: +SKIP

    ``initial_pose`` (4, 4) is T_world_cam of the first frame (identity by default).
    ``params``: learnt ``params.Params`` in place of the config's numbers (Huber radii,
    consistency threshold and the per-edge weighting model drive the solve, ``reobs_a`` the
    selection); None or ``Params.default(config)`` give the plain tracker's trajectory, bit
    for bit. ``readout_s``: the camera's rolling-shutter readout time (s; 0: a global
    shutter), unless ``Config.readout_s`` sets one (``frontend.shutter``).
    ``track`` is synchronous. ``submit`` + ``complete`` split it: ``submit`` dispatches the
    device solve and returns at once, so the caller can prepare the next frame on another
    core before ``complete`` reads the result back (one frame in flight at a time).
    With ``Config.mapping`` the local window refines each keyframe beside tracking, on a
    worker thread (``pipeline.mapping``; ``Config.mapping_lag`` 0: inline); ``close()`` (or a
    ``with`` block) stops it. Making one switches on the on-disk program cache and the
    CLI's arithmetic (``programs.enable_cache``; ``EDGEVO_CACHE_DIR=""``: no cache).
    ``state`` is the tracker's state (``decision.TrackerState``), ``refinements`` the window's
    keyframe poses as taken. With ``Config.map`` every keyframe joins a map
    (``relocalise.Places``; ``keyframe_map``) that finds lost frames again; where it ties
    a chain of keyframes made at a guess back to it, the frames tracked in that chain move
    into the map's frame: ``corrections`` lists each such move (``Correction``: which earlier
    results' poses to left-multiply by which transform), in order.

    A motion prior (an IMU's, wheel odometry's) goes with a frame: ``track(..., prior=T)``,
    ``track_frame`` and ``submit`` take T = T_prev_cur (4, 4, metres): the frame's camera
    pose in the previous frame's camera (p_prev = T p_cur), so that its predicted pose is
    T_world_prev @ T. It replaces the constant-velocity prediction as the start of the
    solve, of the recovery search from earlier keyframes and as the pose of a LOST frame;
    the recovery tries the constant-velocity start as well. The rolling shutter's motion
    per row is read from the pose being solved, so the prior reaches it through the start.
    Priors are taken by this streaming API only: ``run`` / ``run.track_in_chunks`` solve
    chunks of frames on the device from constant velocity. ``reset()`` starts anew.
    """

    def __init__(
        self, config: Config, intrinsics: Intrinsics, *, initial_pose: np.ndarray | None = None,
        params: Params | None = None, readout_s: float = 0.0,
    ) -> None:
        enable_cache()  # programs kept on disk, the CLI's arithmetic (``programs``)
        release_compiled()  # a process that tracked under many configurations: room first
        self.config, self.params = config, params
        #: the rolling shutter's readout time the run uses (s): the config's, else the camera's
        self.readout_s = readout_time(config, readout_s)
        intrinsics = Intrinsics(*(float(x) for x in intrinsics)).validate()
        pose = np.eye(4) if initial_pose is None else np.asarray(initial_pose, np.float64)
        if pose.shape != (4, 4) or not np.all(np.isfinite(pose)):
            raise ValueError("initial_pose must be a finite 4x4 matrix")
        self._initial = pose
        # what reset() starts again from: the constructor's intrinsics, readout and pose
        self._given = (intrinsics, readout_s, pose)
        self._solver = Solver(config, intrinsics, self.readout_s, params)
        self.state = decision.TrackerState()
        self.refinements: list = []  # the window's keyframe poses, as taken (``Refinement``)
        self.warm_up_ms: float | None = None  # time of the warm-up (at the first keyframe)
        self._mapper: Mapper | None = None  # made with the first keyframe (image size)
        self._places: Places | None = None  # the keyframe map, made with the first keyframe
        self._ledger = Ledger() if config.map else None  # frames the map may still move
        self._loops: Loops | None = None  # the pose graph (``loops``), made with the map
        self._made = None  # the keyframe this frame made (``effects.Made``), for the map
        #: earlier poses moved into the map's frame (``Correction``), in order
        self.corrections: list[Correction] = []
        self._handed: dict[int, tuple[float, np.ndarray]] = {}  # in the window: time, pose
        self._map_ms, self._moved = 0.0, False  # this frame's time on the window; new intrinsics
        self._last_t: float | None = None
        self._in_flight = False
        self._shape: tuple[int, int] | None = None  # (H, W) of the frames seen by ``track``

    # -- public -------------------------------------------------------------------------
    def track(self, rgb: np.ndarray, depth: np.ndarray, timestamp: float, *,
              prior: np.ndarray | None = None, depth_lag_s: float = 0.0) -> FrameResult:
        """Track one frame: rgb (H, W, 3) (or gray (H, W)) uint8, depth (H, W) float in
        metres (0 or NaN = missing), timestamp in seconds, increasing; ``prior``: the
        frame's motion T_prev_cur (class doc; None: constant velocity); ``depth_lag_s``: how
        long after the colour image the depth image was taken (s; a calibrated camera's
        ``depth_time_offset_s`` where the two stamps agree; ``Frame.depth_lag_s``).
        ValueError naming the problem for arrays of the wrong kind or size, a prior that is
        no rigid transform and a lag that is not finite (before any JAX code runs)."""
        if prior is not None:  # refused before the frame is looked at (``submit`` takes it)
            rigid_transform(prior, name="prior")
        if not np.isfinite(depth_lag_s):
            raise ValueError(f"depth_lag_s must be finite, got {depth_lag_s}")
        self._shape = check_frame(rgb, depth, timestamp, self._shape)
        t0 = time.perf_counter()
        frame = preprocess(rgb, depth, self.config)
        if depth_lag_s:
            frame = dataclasses.replace(frame, depth_lag_s=float(depth_lag_s))
        pre_ms = (time.perf_counter() - t0) * 1e3
        return self.complete(self.submit(frame, timestamp, preprocess_ms=pre_ms, prior=prior))

    def track_frame(self, frame: Frame, timestamp: float, *,
                    prior: np.ndarray | None = None) -> FrameResult:
        """Track one pre-processed frame (synchronous; ``prior`` as in ``track``)."""
        return self.complete(self.submit(frame, timestamp, prior=prior))

    def submit(self, frame: Frame, timestamp: float, *, preprocess_ms: float = 0.0,
               prior: np.ndarray | None = None) -> _Pending:
        """Dispatch the solve of one pre-processed frame; read it back with ``complete``.
        ``prior``: the frame's motion T_prev_cur (class doc; None: constant velocity); the
        first frame has none to use (it starts at the initial pose)."""
        if self._in_flight:
            raise RuntimeError("complete() the frame in flight before submitting another")
        prior = None if prior is None else rigid_transform(prior, name="prior")
        timestamp = self._last_t = increasing(timestamp, self._last_t)
        t_submit = time.perf_counter()
        self._in_flight = True
        kf, motion = self.state.keyframe, self.state.motion
        if kf is None:
            start = self._initial if prior is None or not motion.poses else motion.predict(prior)
            return _Pending(frame, timestamp, start, None, preprocess_ms, t_submit, prior)
        rate = self._solver.rate(timestamp, frame, motion.times)
        if prior is not None:  # from the prior: the solve recovery runs, from that start
            predicted = motion.predict(prior)
            output = self._solver.dispatch(kf, frame, inverse_np(predicted) @ kf.pose, rate,
                                           motion.poses[-1])
            return _Pending(frame, timestamp, predicted, output, preprocess_ms, t_submit, prior)
        output = self._solver.next(kf, frame, motion.rel, rate)
        return _Pending(frame, timestamp, motion.predict(), output, preprocess_ms, t_submit)

    def complete(self, pending: _Pending) -> FrameResult:
        """Wait for a submitted frame, decide its state and keyframe, and return its result."""
        self._in_flight = False
        res = None if pending.output is None else to_host(pending.output)
        return self._conclude(pending, res, time.perf_counter())[0]

    def accept(self, frame: Frame, timestamp: float, res: TrackResult, *,
               preprocess_ms: float = 0.0, t_submit: float | None = None
               ) -> tuple[FrameResult, bool]:
        """Conclude a frame whose solve ``res`` (host arrays) was computed elsewhere (the
        scan, a batch) from this tracker's current ``solve_inputs``. Returns its result and
        whether the state went on plainly (False: a keyframe, a loss or a recovery changed
        it, and later results of the same chunk are stale)."""
        timestamp = self._last_t = increasing(timestamp, self._last_t)
        t_submit = time.perf_counter() if t_submit is None else t_submit
        pending = _Pending(frame, timestamp, self.state.motion.predict(), None, preprocess_ms,
                           t_submit)
        return self._conclude(pending, res, time.perf_counter())

    def locate(self, rgb: np.ndarray, depth: np.ndarray) -> decision.Placed | None:
        """Where the keyframe map places an image (rgb (H, W, 3) or gray uint8, depth (H, W)
        metres, of the frames' size), as a lost frame is found again (``relocalise``): the
        map's keyframe, the solve (``result.T_c_k``: T_cam_kf) and how it was found; None
        when no place is verified (or before the first keyframe, or with ``Config.map``
        off). The tracker's state does not change. ValueError as ``track``."""
        self._shape = check_frame(rgb, depth, self._last_t or 0.0, self._shape)
        if self._places is None:
            return None
        frame = preprocess(rgb, depth, self.config)
        t = self._last_t if self._last_t is not None else 0.0
        return self._places.relocalise(self._solver, self.state, frame,
                                       decision.Relocalise(None), t)

    def reset(self, *, pose: np.ndarray | None = None) -> None:
        """Forget the trajectory: keyframes, poses, the local window (its worker stopped),
        the inlier-share history, the refinements, timestamps and frame size. The next frame
        starts anew at ``pose`` (T_world_cam (4, 4); None: the constructor's
        ``initial_pose``), with the constructor's intrinsics, and the frames after it are
        tracked as a new ``Odometry`` would track them, bit for bit. Compiled programs stay
        (none compiles again for frames of a size seen before); ``warm_up_ms`` keeps the
        first warm-up's time. RuntimeError while a frame is in flight; ValueError naming
        ``pose`` when it is no rigid transform."""
        if self._in_flight:
            raise RuntimeError("complete() the frame in flight before reset()")
        given, warm_up_ms = self._given, self.warm_up_ms
        intrinsics, readout_s, initial = given
        if pose is not None:
            rigid_transform(pose, name="pose")  # checked; taken as given, as the constructor's
        self.close()
        Odometry.__init__(self, self.config, intrinsics,
                          initial_pose=initial if pose is None else pose,
                          params=self.params, readout_s=readout_s)
        self._given, self.warm_up_ms = given, warm_up_ms

    def close(self) -> None:
        """Stop the local map's worker thread (refinements not taken yet are dropped), the
        keyframe map's (keyframes made are described first) and the pose graph's (a solve not
        taken yet is dropped)."""
        if self._mapper is not None:
            self._mapper.close()
        if self._places is not None:
            self._places.close()
        if self._loops is not None:
            self._loops.close()

    def __enter__(self) -> Odometry:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # -- views -----------------------------------------------------------------------------
    @property
    def intrinsics(self) -> Intrinsics:
        """The intrinsics in use (the window's when ``Config.mapping_intrinsics``)."""
        return self._solver.intrinsics

    @property
    def knobs(self):
        """The solve's numbers (``derive.solve_knobs`` or the learnt ``params``')."""
        return self._solver.knobs

    @property
    def structure(self) -> object:
        """The static part of the solve (a jit static argument; see ``solve_inputs``)."""
        return self._solver.structure

    @property
    def num_keyframes(self) -> int:
        """Keyframes made so far."""
        return self.state.num_keyframes

    @property
    def has_keyframe(self) -> bool:
        """Whether a keyframe exists (frames are solved against it from then on)."""
        return self.state.keyframe is not None

    @property
    def keyframe(self) -> tuple[float, np.ndarray, np.ndarray] | None:
        """The current keyframe: (timestamp, pose T_world_kf (4, 4), its selected edges'
        pixels (N, 2) float32 (u, v)); None before the first keyframe."""
        kf = self.state.keyframe
        if kf is None:
            return None
        edges = to_host(kf.edges)
        return kf.timestamp, kf.pose.copy(), np.asarray(edges.uv).T[edges.valid]

    @property
    def local_map(self):
        """The local window (``backend.local_map.LocalMap``), None before the first keyframe
        or with ``Config.mapping`` off. Beside tracking, its worker may be changing it: read
        it after ``close()``."""
        return None if self._mapper is None else self._mapper.local_map

    @property
    def keyframe_map(self):
        """The keyframe map (``map.KeyframeMap``) with every keyframe made so far, None before
        the first keyframe or with ``Config.map`` off."""
        if self._places is None:
            return None
        self._places.settle()
        return self._places.map

    @property
    def loop_stats(self) -> dict | None:
        """The pose graph so far (``Loops.stats``; None with ``Config.map`` or
        ``Config.loops`` off)."""
        if not (self.config.map and self.config.loops):
            return None
        if self._loops is None:
            return {"closed": [], "rejected": [], "solves": []}
        return self._loops.stats(self._places.map)

    @property
    def mapping_worker_ms(self) -> list[float]:
        """The local window's time per keyframe taken so far (ms, in order)."""
        return [] if self._mapper is None else list(self._mapper.worker_ms)

    def solve_inputs(self) -> tuple[KeyframeEdges, np.ndarray, np.ndarray, Intrinsics, object]:
        """What a solve of the next frames needs besides the frames, for solves made
        elsewhere (``run.track_in_chunks``, ``batch.evaluate``) and concluded by
        ``accept``: the keyframe's edges, A = T_(i-1)_kf and B = T_(i-2)_kf (float32, the
        constant-velocity prediction's inputs, ``chunk.predict_matrix``), the intrinsics and the
        solve's numbers. RuntimeError before the first keyframe."""
        if self.state.keyframe is None:
            raise RuntimeError("no keyframe yet: track the first frame with track_frame")
        return (self.state.keyframe.edges, *self.state.motion.rel, self.intrinsics, self.knobs)

    def shutter_rates(self, timestamps, height: int) -> np.ndarray | None:
        """The rolling shutter's rates (``shutter.Shutter.rate``, float32 (n,)) of the next
        frames at ``timestamps``, after the last frame concluded; None with a global shutter
        (a program without it). ``height``: the frames' rows."""
        return self._solver.rates(timestamps, height, self.state.motion.times)

    # -- the frame's decision and its actions ------------------------------------------------
    def _conclude(self, pending: _Pending, res, t_solve: float) -> tuple[FrameResult, bool]:
        """Run the decision on a solved frame (``res`` None: no keyframe to solve against),
        carrying out the actions it asks for; its result and whether the state went on
        plainly (``decision.Decision.plain``)."""
        self._map_ms, self._moved = 0.0, False
        closed = None
        if self._loops is not None:  # the pose graph's results due now, then its next solve
            closed = self._loops.due(self.state.index)
            if closed is not None:
                self._close(closed)
            self._loops.found(self.state.index)
            self._loops.submit(self._places.map, self.state.index)
        due = self._due(self.state.index + 1)
        self.state = decision.begin_frame(self.state, due)
        if (due or closed is not None) and res is not None:  # keyframe poses moved: the
            # prediction moved with them
            pending = dataclasses.replace(pending, predicted=self.state.motion.predict(
                pending.prior))
        frame = pending.frame
        ev = decision.Evidence(decision.FrameFacts(pending.timestamp, frame.num_edges,
                                 bool(np.any(frame.edge_depth > 0))), res, pending.predicted,
                      pending.prior)
        while True:
            now = time.perf_counter()
            ev = dataclasses.replace(ev, intrinsics_moved=self._moved, timing=decision.Timing(
                pending.preprocess_ms, ((t_solve if res is not None else now)
                                        - pending.t_submit) * 1e3,
                None if self._mapper is None else self._map_ms, (now - pending.t_submit) * 1e3))
            d = decision.decide(self.state, ev, self.config)
            if not d.actions:
                before, self.state = self.state, d.state
                self._placed(d, frame, before)
                return d.result, d.plain
            ev = self._act(d.actions[0], ev, pending)

    def _act(self, action, ev: decision.Evidence, pending: _Pending) -> decision.Evidence:
        """Carry out one action of the decision; the evidence with its answer."""
        frame, state = pending.frame, self.state
        if isinstance(action, decision.Search):
            return dataclasses.replace(ev, searched=True, found=search(
                self._solver, state, frame, action, pending.timestamp, pending.predicted,
                pending.prior))
        if isinstance(action, decision.Confirm):
            return dataclasses.replace(ev, confirmed=confirm(self._solver, state, frame, action,
                                                             pending.timestamp))
        if isinstance(action, decision.Handover):
            return dataclasses.replace(ev, handover=tuple(self._due(None)))
        if isinstance(action, decision.Relocalise):
            return dataclasses.replace(ev, relocalise_asked=True, relocalised=None
                                       if self._places is None else self._places.relocalise(
                                           self._solver, state, frame, action,
                                           pending.timestamp))
        if isinstance(action, decision.Revisit):
            return dataclasses.replace(ev, revisit_asked=True, revisited=None
                                       if self._places is None else self._places.revisit(
                                           self._solver, state, frame, action,
                                           pending.timestamp))
        assert isinstance(action, decision.MakeKeyframe), action
        if self.config.mapping and self._mapper is None:  # the window, made with the first keyframe
            self._mapper = Mapper(self.config, self.intrinsics, frame.shape,
                                  rolling_shutter=self.readout_s > 0)
            if self.warm_up_ms is None:  # its programs compile on its worker from now
                self._mapper.warm_up()
        if self.config.map and self._places is None:
            self._places = Places(self.config, self.intrinsics, frame.shape)
            if self.config.loops:
                self._loops = Loops(self.config)
        made = self._made = make_keyframe(self._solver, self._mapper, frame, action,
                                          state.index)
        if made is None:
            return dataclasses.replace(ev, made_asked=True)
        self._map_ms += made.map_ms
        if self._mapper is not None:
            self._handed[made.keyframe.id] = (made.keyframe.timestamp, action.pose)
        if made.mapped is not None:
            self._take(made.mapped, state.index - 1)
        if self.warm_up_ms is None:
            t0 = self._mapper.warm_since if self._mapper is not None else time.perf_counter()
            warm_up(self._solver, self._mapper, made.keyframe, frame)
            self.warm_up_ms = (time.perf_counter() - t0) * 1e3
        return dataclasses.replace(ev, made_asked=True,
                                   made=decision.NewKeyframe(made.keyframe, made.select_ms))

    def _placed(self, d: decision.Decision, frame: Frame, before: decision.TrackerState
                ) -> None:
        """The map's part of a concluded frame (``before``: the state it was tracked from):
        the keyframe it made joins the map (and the pose graph, which looks for a loop it
        closes), its share counts for its keyframe, the earlier frames it
        settles may move (``corrections``: a guessed chain it ties to the map, LOST frames
        filled in; ``ledger``), and a ``Tie`` out of a guessed chain starts the window again
        (its keyframes are in the chain's frame)."""
        made, self._made = self._made, None
        if self._ledger is None:
            return
        kf, result, tie = self.state.keyframe, d.result, d.tie
        settled = tie is not None or (result.state == OK and kf is not None
                                      and kf.guess is None)
        moved = self._ledger.record(self.state.index - 1, result, settled=settled, tie=tie)
        if moved is not None:
            self.corrections.append(moved)
        if self._loops is not None:
            self._loops.frame(None if kf is None else kf.id, result.pose, moved)
        if self._places is None:
            return
        if made is not None and result.keyframe is not None:
            self._places.add(kf, made.host_edges, frame, self.intrinsics)
            if self._loops is not None:
                self._loops.keyframe(kf.id, kf.parent, result.covariance)
                if kf.id not in self._handed:  # no window beside tracking: its pose is final
                    self._loops.measure(kf.id, self._places.map)
                if kf.guess is None and self._loops.searches():  # a loop it closes: beside
                    # tracking, joining the graph ``loop_lag`` frames later (``Places.loop``)
                    verify = self._places.loop(self._solver, before, frame, kf,
                                               self._loops.tied(kf.id), kf.timestamp)
                    if verify is not None:
                        self._loops.search(kf.id, verify, self.state.index)
        if result.state == OK and result.inlier_share is not None:
            self._places.note_share(kf.id, result.inlier_share)
        if tie is not None:
            self._places.tie(tie)
            if tie.restart and self._mapper is not None:
                self._mapper.close()
                self._mapper, self._handed = None, {}

    def _close(self, closed: Closed) -> None:
        """Take a solved pose graph: each keyframe of the map moves (``Loops.corrections``),
        and with it the tracker's records of it, the window's (refinements on their way are
        moved as they come: ``Mapper.move``) and every frame tracked from it (one
        ``Correction``)."""
        kmap = self._places.map
        moves = self._loops.corrections(closed, kmap.ids)
        if not moves:
            return
        for key, C in moves.items():
            kmap.set_pose(key, orthonormalise_np(C @ kmap[key].pose))
        held = [k for k in (self.state.keyframe, *self.state.previous)
                if k is not None and k.id in moves]
        self.state = decision.refine(self.state, [
            Mapped(k.id, orthonormalise_np(moves[k.id] @ k.pose), None) for k in held])
        if self._mapper is not None:
            self._mapper.move(moves)
        frames = self._loops.moved_frames(moves)
        if frames is not None:
            self.corrections.append(frames)
            self._ledger.move(frames.first, frames.poses)

    def _due(self, frame_index: int | None) -> list[Mapped]:
        """The window's refinements due at ``frame_index`` (None: all handed over), waited
        for and recorded (``_take``)."""
        if self._mapper is None:
            return []
        t0 = time.perf_counter()
        taken = self._mapper.due(frame_index)
        index = self.state.index if frame_index is not None else self.state.index - 1
        for m in taken:
            self._take(m, index)
        if taken:
            self._map_ms += (time.perf_counter() - t0) * 1e3
        return taken

    def _take(self, m: Mapped, index: int) -> None:
        """Record a refinement taken at frame ``index`` (``refinements``: its keyframe's pose
        as handed to the window, and refined) and take the window's intrinsics with it."""
        timestamp, before = self._handed.pop(m.key)
        self.refinements.append(Refinement(timestamp, index, before, m.pose))
        if self._places is not None:
            self._places.set_pose(m.key, m.pose)
            if self._loops is not None:
                self._loops.measure(m.key, self._places.map)
        if self.config.mapping_intrinsics and tuple(m.intrinsics) != tuple(self.intrinsics):
            self._solver.intrinsics = m.intrinsics
            self._moved = True  # solves made with the old ones are stale
