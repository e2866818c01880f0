"""The streaming tracker ``Odometry``: a thin driver over the per-frame decision.

Per frame (docs/architecture.md): host preprocessing -> one jitted device solve against the
keyframe's edges -> the back end's tick (keyframes that moved: the state follows them) ->
``decision.decide`` (state, solve, frame facts) -> the actions it asks for (recovery search,
confirmation, the map's queries, the window's hand-over, a new keyframe: ``effects``,
``backend``) -> the frame's result, the next state, and the back end told.
"""

from __future__ import annotations

import dataclasses
import time
import warnings
from dataclasses import dataclass

import numpy as np

from ..camera import Intrinsics
from ..config import Config
from ..derive import readout_time
from ..frontend.align import TrackResult
from ..frontend.features import Detections
from ..frontend.selection import KeyframeEdges
from ..geometry import inverse_np
from ..hostmem import to_host
from ..image.preprocess import Frame, preprocess
from ..learn.params import Params
from ..map import archive
from ..programs import enable_cache, release_compiled
from . import decision
from .backend import Backend
from .effects import Made, Solver, check, confirm, make_keyframe, search, warm_up
from .inputs import check_frame, increasing, rigid_transform
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
    ``map_file``: a keyframe map saved by ``save_map`` to start in (``map.archive``; a
    MapFileError at once where its camera or settings are not this tracker's, or at the
    first frame where its image size is not the frames'): the first frames are tracked in
    their own frame, WEAK (not tied to the loaded map), and ask it where they are; the
    first frame found (``found_in_loaded``, its index) moves them into the map's frame, and
    the new keyframes join the map (``save_map`` writes the grown one).
    ``params``: learnt ``params.Params`` in place of the config's numbers (Huber radii,
    consistency threshold and the per-edge weighting model drive the solve, ``reobs_a`` the
    selection); None or ``Params.default(config)`` give the plain tracker's trajectory, bit
    for bit. ``readout_s``: the camera's rolling-shutter readout time (s; 0: a global
    shutter), unless ``Config.readout_s`` sets one (``frontend.shutter``).
    ``track`` is synchronous. ``submit`` + ``complete`` split it: ``submit`` dispatches the
    device solve and returns at once, so the caller can prepare the next frame on another
    core before ``complete`` reads the result back (one frame in flight at a time).
    With ``Config.mapping`` the sliding window refines each keyframe beside tracking, on a
    worker thread (``window.worker``; ``Config.mapping_lag`` 0: inline); ``close()`` (or a
    ``with`` block) stops it. Making one switches on the on-disk program cache and the
    CLI's arithmetic (``programs.enable_cache``; ``EDGEVO_CACHE_DIR=""``: no cache).
    ``state`` is the tracker's state (``decision.TrackerState``), ``refinements`` the window's
    keyframe poses as taken. With ``Config.map`` every keyframe joins a map
    (``places.Places``; ``keyframe_map``) that finds lost frames again and closes loops;
    where it ties a chain of keyframes made at a guess back to it, or a loop moves
    keyframes, the frames tracked from them move with them: ``corrections`` lists each move
    (``Correction``: earlier results' poses as they are now), in order, and ``poses()`` gives
    every frame's pose as it is now (the online poses are the results').

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
        params: Params | None = None, readout_s: float = 0.0, map_file=None,
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
        # what reset() starts again from: the constructor's intrinsics, readout and pose
        self._given = (intrinsics, readout_s, pose)
        self._map_file = map_file
        self.warm_up_ms: float | None = None  # time of the warm-up (at the first keyframe)
        self._start(pose)

    def _start(self, pose: np.ndarray) -> None:
        """A new trajectory from ``pose`` (T_world_cam of its first frame)."""
        self._initial = pose
        self._solver = Solver(self.config, self._given[0], self.readout_s, self.params)
        self._backend = Backend(self.config, self._solver, self.readout_s)
        self.state = decision.TrackerState()
        #: the index of the first frame placed in the loaded map (None: none yet, or no map
        #: loaded)
        self.found_in_loaded: int | None = None
        if self._map_file is not None:
            first = self._backend.load(self._map_file)
            self.state = decision.TrackerState(num_keyframes=first, loaded=True)
        self._last_t: float | None = None
        self._in_flight = False
        self._shape: tuple[int, int] | None = None  # (H, W) of the frames seen by ``track``
        self._tracked_depth: np.ndarray | None = None  # the last frame not LOST, for Check

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
        metres, of the frames' size), as a lost frame is found again (``places``): the
        map's keyframe, the solve (``result.T_c_k``: T_cam_kf) and how it was found; None
        when no place is verified (or before the first keyframe, or with ``Config.map``
        off). The tracker's state does not change. ValueError as ``track``."""
        self._shape = check_frame(rgb, depth, self._last_t or 0.0, self._shape)
        frame = preprocess(rgb, depth, self.config)
        t = self._last_t if self._last_t is not None else 0.0
        found = None if frame.gray is None else Detections(frame.gray)
        return self._backend.relocalise(self.state, frame, decision.Relocalise(None), t, found)

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
        if pose is not None:
            rigid_transform(pose, name="pose")  # checked; taken as given, as the constructor's
        self.close()
        self._start(self._given[2] if pose is None else np.asarray(pose, np.float64))

    def finish(self) -> None:
        """Finish what the back end has pending, as at the end of a run: the window's
        refinements are taken, the loops' searches join the pose graph and a last solve
        moves the keyframes and the frames tracked from them (``corrections``, ``poses()``;
        the results keep the poses as reported). Tracking may go on after it.
        RuntimeError while a frame is in flight."""
        if self._in_flight:
            raise RuntimeError("complete() the frame in flight before finish()")
        self.state = decision.follow(self.state, self._backend.finish(self.state.index - 1))

    def save_map(self, path) -> int:
        """Write the keyframe map as it is now (every keyframe it holds, with its pose in the
        record of poses, its edges, landmarks, fern code and covisibility, and the pose graph's
        edges) to ``path``
        (``map.archive``: one versioned file, written atomically); its size in bytes. It
        only reads the map: the run goes on as it would have. ValueError with the map off
        (``Config.map``) or before the first keyframe; RuntimeError while a frame is in
        flight."""
        if self._in_flight:
            raise RuntimeError("complete() the frame in flight before save_map()")
        kmap = self.keyframe_map
        if kmap is None or not len(kmap):
            raise ValueError("no keyframe map to save: Config.map is off, or no keyframe yet")
        return archive.save_map(path, kmap, settings=archive.map_settings(self.config),
                                library=archive.library_version(),
                                edges=self._backend.map.graph_edges(kmap.ids))

    def close(self) -> None:
        """Stop the back end's workers: the window's (refinements not taken yet are dropped),
        the keyframe map's (keyframes made are described first) and the loops' (a search or
        solve not taken yet is dropped)."""
        self._backend.close()

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
    def refinements(self) -> list[Refinement]:
        """The window's keyframe poses, as taken (``Refinement``), in order."""
        return self._backend.refinements

    @property
    def corrections(self) -> list[Correction]:
        """Earlier poses moved (a guessed chain tied to the map, LOST frames filled in, a loop
        closed: ``Correction``), in order."""
        return self._backend.corrections

    def poses(self) -> np.ndarray:
        """(N, 4, 4) T_world_cam of every frame concluded, as it is now: its pose as reported,
        moved by every correction of its keyframe since (``map.poses``)."""
        return self._backend.poses.poses()

    @property
    def window(self):
        """The sliding window (``window.sliding.SlidingWindow``), None before the first
        keyframe or with ``Config.mapping`` off. Beside tracking, its worker may be changing
        it: read it after ``close()``."""
        window = self._backend.window
        return None if window is None else window.sliding

    @property
    def local_map(self):
        """Deprecated name of ``window``."""
        warnings.warn("Odometry.local_map is deprecated: use Odometry.window",
                      DeprecationWarning, stacklevel=2)
        return self.window

    @property
    def keyframe_map(self):
        """The keyframe map (``map.KeyframeMap``) with every keyframe made so far, None before
        the first keyframe or with ``Config.map`` off."""
        return self._backend.map.keyframe_map

    @property
    def loop_stats(self) -> dict | None:
        """The pose graph so far (``map.loops.Loops.stats``; None with ``Config.map`` or
        ``Config.loops`` off)."""
        return self._backend.map.loop_stats

    @property
    def mapping_worker_ms(self) -> list[float]:
        """The sliding window's time per keyframe taken so far (ms, in order)."""
        window = self._backend.window
        return [] if window is None else list(window.worker_ms)

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
        moved = self._backend.tick(self.state.index)
        self.state = decision.begin_frame(self.state, moved)
        if moved and res is not None:  # keyframe poses moved: the prediction with them
            pending = dataclasses.replace(pending, predicted=self.state.motion.predict(
                pending.prior))
        frame = pending.frame
        job = _Job(pending, None if frame.gray is None else Detections(frame.gray))
        ev = decision.Evidence(decision.FrameFacts(pending.timestamp, frame.num_edges,
                                                   bool(np.any(frame.edge_depth > 0))),
                               res, pending.predicted, pending.prior)
        while True:
            ev = dataclasses.replace(ev, intrinsics_moved=self._backend.intrinsics_moved,
                                     timing=self._timing(pending, res, t_solve))
            d = decision.decide(self.state, ev, self.config)
            if not d.actions:
                before, self.state = self.state, d.state
                self._backend.concluded(d, job.made, frame, before)
                if before.loaded and self.found_in_loaded is None and d.tie is not None:
                    self.found_in_loaded = before.index - 1
                if d.result.state != LOST:
                    self._tracked_depth = frame.depth
                return d.result, d.plain
            action = d.actions[0]
            ev = ev.answered(action, self._act(action, job))

    def _timing(self, pending: _Pending, res, t_solve: float) -> decision.Timing:
        """The frame's clocks so far (``decision.Timing``)."""
        now = time.perf_counter()
        return decision.Timing(
            pending.preprocess_ms, ((t_solve if res is not None else now)
                                    - pending.t_submit) * 1e3,
            None if self._backend.window is None else self._backend.ms,
            (now - pending.t_submit) * 1e3)

    def _act(self, action, job: _Job):
        """Carry out one action of the decision (``decision``'s module doc); its answer."""
        p, state, backend = job.pending, self.state, self._backend
        if isinstance(action, decision.Search):
            return search(self._solver, state, p.frame, action, p.timestamp, p.predicted,
                          p.prior, job.found)
        if isinstance(action, decision.Confirm):
            return confirm(self._solver, state, p.frame, action, p.timestamp, job.found)
        if isinstance(action, decision.Check):
            return check(self._solver, self._tracked_depth, p.frame, action)
        if isinstance(action, decision.Handover):
            return tuple(backend.handover(state.index - 1))
        if isinstance(action, decision.Relocalise):
            return backend.relocalise(state, p.frame, action, p.timestamp, job.found)
        if isinstance(action, decision.Revisit):
            return backend.revisit(state, p.frame, action, p.timestamp)
        assert isinstance(action, decision.MakeKeyframe), action
        return self._make_keyframe(action, job)

    def _make_keyframe(self, action: decision.MakeKeyframe, job: _Job
                       ) -> decision.NewKeyframe | None:
        """Make the keyframe ``action`` asks for and hand it to the back end; at the first,
        warm up every program before any frame is tracked (``effects.warm_up``)."""
        frame, first = job.pending.frame, self.warm_up_ms is None
        self._backend.start(frame.shape, warm_up=first)
        made = make_keyframe(self._solver, frame, action, job.found)
        if made is None:
            return None
        made = job.made = self._backend.keyframe_made(made, frame, self.state.index - 1)
        if first:
            window = self._backend.window
            t0 = window.warm_since if window is not None else time.perf_counter()
            warm_up(self._solver, window, made.keyframe, frame)
            self.warm_up_ms = (time.perf_counter() - t0) * 1e3
        return decision.NewKeyframe(made.keyframe, made.select_ms)


@dataclass
class _Job:
    """One frame being concluded: its pending solve, its keypoints (each kind detected once,
    by whichever action needs them first; None without a gray image) and the keyframe it
    made (``effects.Made``, for the back end)."""

    pending: _Pending
    found: Detections | None
    made: Made | None = None
