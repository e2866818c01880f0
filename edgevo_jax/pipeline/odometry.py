"""Frame-to-keyframe edge tracking: the streaming ``Odometry`` and the sequence driver.

Per frame (DESIGN.md): host preprocessing -> one jitted device call (coarse-to-fine solve
against the keyframe's edges) -> host keyframe decision -> one trajectory line.
The jitted solve sees fixed shapes only, so it compiles once per configuration and image size.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field

import jax
import jax.numpy as jnp
import numpy as np

from ..camera import Intrinsics
from ..config import Config
from ..derive import basin_px, readout_time, solve_knobs, solve_structure
from ..frontend import features, selection
from ..frontend.align import TrackResult, track
from ..frontend.chunk import track_next_jit
from ..frontend.depth import depth_points
from ..frontend.keyframes import keyframe_reason
from ..frontend.selection import KeyframeEdges, keyframe_edges
from ..frontend.shutter import Shutter, shutter_rate, unroll_edges
from ..geometry import inverse_np, log_np, orthonormalise_np, predict_np
from ..hostmem import aligned_array, to_host
from ..image.preprocess import Frame, preprocess
from ..learn.params import Params, solve_knobs_of
from ..programs import enable_cache, program, release_compiled
from . import recovery
from .mapping import Mapped, Mapper
from .pair import rigid_transform
from .recovery import inlier_share
from .results import LOST, OK, WEAK, FrameResult, Refinement

_track_jit = program(track, static_argnames="config")

#: frames (not lost) whose highest inlier share is the reference for the share ratios of ``Config``
SHARE_HISTORY = 5

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


@dataclass
class _Keyframe:
    timestamp: float
    pose: np.ndarray  # T_world_kf
    edges: KeyframeEdges  # on device
    num_edges: int
    inlier_counts: list[int] = field(default_factory=list)
    frame: Frame | None = None  # its frame (gray image and depth for feature hypotheses)
    # keypoints by kind ("orb", "sift"), detected when recovery first needs them
    keypoints: dict[str, features.Keypoints] = field(default_factory=dict)


class Odometry:
    """Streaming RGB-D edge odometry.

    >>> odo = Odometry(Config(), Intrinsics(535.4, 539.2, 320.1, 247.6))
    >>> result = odo.track(rgb, depth_m, timestamp)  # doctest: +SKIP

    ``initial_pose`` (4, 4) is T_world_cam of the first frame (identity by default).
    ``params``: learnt ``params.Params`` (e.g. from ``scripts/learn_weights.py``) in place of
    the config's numbers: Huber radii, consistency threshold and the per-edge weighting
    model drive the solve (``params.solve_knobs_of``), ``reobs_a`` the edge selection. None
    or ``Params.default(config)`` give the plain tracker's trajectory, bit for bit.
    ``readout_s``: the camera's rolling-shutter readout time (s; the source's ``readout_s``,
    0: a global shutter), unless ``Config.readout_s`` sets one (``frontend.shutter``).
    ``track`` is synchronous. ``submit`` + ``complete`` split it: ``submit`` dispatches the
    device solve and returns at once, so the caller can prepare the next frame on another
    core before ``complete`` reads the result back (one frame in flight at a time).
    With ``Config.mapping`` the local window refines each keyframe beside tracking, on a
    worker thread (``pipeline.mapping``; ``Config.mapping_lag`` 0: inline); ``close()`` (or a
    ``with`` block) stops it. Making one switches on the on-disk program cache and the
    CLI's arithmetic (``programs.enable_cache``; ``EDGEVO_CACHE_DIR=""``: no cache).

    A motion prior (an IMU's, wheel odometry's) goes with a frame: ``track(..., prior=T)``,
    ``track_frame`` and ``submit`` take T = T_prev_cur (4, 4, metres): the frame's camera
    pose in the previous frame's camera (p_prev = T p_cur), so that its predicted pose is
    T_world_prev @ T. It replaces the constant-velocity prediction as the start of the
    solve, of the recovery search from earlier keyframes and as the pose of a LOST frame;
    the recovery tries the constant-velocity start as well. The rolling shutter's motion
    per row is read from the pose being solved (``frontend.shutter``), so the prior reaches
    it through the start. Priors are taken by this streaming API only: ``run`` /
    ``run.track_in_chunks`` solve chunks of frames on the device from constant velocity.
    ``reset()`` forgets the trajectory and starts anew (see there).
    """

    def __init__(
        self, config: Config, intrinsics: Intrinsics, *, initial_pose: np.ndarray | None = None,
        params: Params | None = None, readout_s: float = 0.0,
    ) -> None:
        enable_cache()  # programs kept on disk, the CLI's arithmetic (``programs``)
        release_compiled()  # a process that tracked under many configurations: room first
        self.config = config
        #: the rolling shutter's readout time the run uses (s): the config's, else the camera's
        self.readout_s = readout_time(config, readout_s)
        self.intrinsics = Intrinsics(*(float(x) for x in intrinsics)).validate()
        pose = np.eye(4) if initial_pose is None else np.asarray(initial_pose, np.float64)
        if pose.shape != (4, 4) or not np.all(np.isfinite(pose)):
            raise ValueError("initial_pose must be a finite 4x4 matrix")
        self._initial = pose
        # what reset() starts again from: the constructor's intrinsics, readout and pose
        self._given = (self.intrinsics, readout_s, pose)
        self._kf: _Keyframe | None = None
        self._poses: list[np.ndarray] = []  # the last two T_world_cam, for constant velocity
        self._times: list[float] = []  # their timestamps
        self._shares: list[float] = []  # inlier shares of the last frames not lost
        self._last_t: float | None = None
        self._tracked_t: float | None = None  # the last frame tracked (not lost)
        self._in_flight = False
        self.num_keyframes = 0
        self._mapper: Mapper | None = None  # made with the first keyframe (image size)
        self._index = 0  # frames concluded so far (the mapping lag counts in them)
        self.refinements: list[Refinement] = []  # the window's keyframe poses, as taken
        self._map_ms = 0.0  # the tracker's time on the local map in the current frame
        self._intrinsics_moved = False  # the window's intrinsics were taken in this frame
        self.warm_up_ms: float | None = None  # time of ``_warm_up`` (at the first keyframe)
        self._previous: list[_Keyframe] = []  # earlier keyframes, for recovery after a loss
        self._shape: tuple[int, int] | None = None  # (H, W) of the frames seen by ``track``
        # the solve's numbers, passed as (traced) arrays, and its static part: configurations
        # that differ in numbers only share one compiled program
        self.knobs, self._static = solve_knobs(config), solve_structure(config)
        self.params = params
        self._reobs_a: float | None = None  # the selection's offset a (None: the config's)
        if params is not None:
            self.knobs = solve_knobs_of(params, config)
            self._reobs_a = float(np.asarray(params.reobs_a, np.float64))
        self._constants_key: tuple[float, ...] | None = None  # see _device_constants
        # the last two poses relative to the keyframe, A = T_(i-1)_kf and B = T_(i-2)_kf
        # (float32): the device predicts the next one from them (chunk.predict_matrix)
        self._rel: tuple[np.ndarray, np.ndarray] | None = None

    # -- public -------------------------------------------------------------------------
    def track(self, rgb: np.ndarray, depth: np.ndarray, timestamp: float, *,
              prior: np.ndarray | None = None) -> FrameResult:
        """Track one frame: rgb (H, W, 3) (or gray (H, W)) uint8, depth (H, W) float in
        metres (0 or NaN = missing), timestamp in seconds, increasing; ``prior``: the
        frame's motion T_prev_cur (class doc; None: constant velocity). ValueError naming
        the problem for arrays of the wrong kind or size and a prior that is no rigid
        transform (before any JAX code runs)."""
        if prior is not None:  # refused before the frame is looked at (``submit`` takes it)
            rigid_transform(prior, name="prior")
        self._check_frame(rgb, depth, timestamp)
        t0 = time.perf_counter()
        frame = preprocess(rgb, depth, self.config)
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
        timestamp = self._advance_time(timestamp)
        t_submit = time.perf_counter()
        self._in_flight = True
        if self._kf is None:
            start = self._initial if prior is None or not self._poses else self._predict(prior)
            return _Pending(frame, timestamp, start, None, preprocess_ms, t_submit, prior)
        if prior is not None:  # from the prior: the solve recovery runs, from that start
            predicted = self._predict(prior)
            output = self._dispatch_align(self._kf, frame, inverse_np(predicted) @ self._kf.pose,
                                          self._rate(timestamp, frame))
            return _Pending(frame, timestamp, predicted, output, preprocess_ms, t_submit, prior)
        A, B = self._rel
        intr, knobs = self._device_constants()
        output = track_next_jit(self._kf.edges, frame.dist, frame.edge_map, A, B,
                                intr, knobs, self._rate(timestamp, frame), config=self._static)
        return _Pending(frame, timestamp, self._predict(), output, preprocess_ms, t_submit)

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
        # the constructor's state: nothing tracked before can leak into the new start
        Odometry.__init__(self, self.config, intrinsics,
                          initial_pose=initial if pose is None else pose,
                          params=self.params, readout_s=readout_s)
        self._given, self.warm_up_ms = given, warm_up_ms

    def complete(self, pending: _Pending) -> FrameResult:
        """Wait for a submitted frame, decide its state and keyframe, and return its result."""
        self._in_flight = False
        if pending.output is None:  # first frame (or no usable keyframe yet)
            return self._first(pending)
        res = to_host(pending.output)
        return self._conclude(pending, res, time.perf_counter())[0]

    def close(self) -> None:
        """Stop the local map's worker thread (refinements not taken yet are dropped)."""
        if self._mapper is not None:
            self._mapper.close()

    def __enter__(self) -> Odometry:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    @property
    def local_map(self):
        """The local window (``backend.local_map.LocalMap``), None before the first keyframe
        or with ``Config.mapping`` off. Beside tracking, its worker may be changing it: read
        it after ``close()``."""
        return None if self._mapper is None else self._mapper.local_map

    @property
    def mapping_worker_ms(self) -> list[float]:
        """The local window's time per keyframe taken so far (ms, in order)."""
        return [] if self._mapper is None else list(self._mapper.worker_ms)

    @property
    def has_keyframe(self) -> bool:
        """Whether a keyframe exists (frames are solved against it from then on)."""
        return self._kf is not None

    @property
    def keyframe(self) -> tuple[float, np.ndarray, np.ndarray] | None:
        """The current keyframe: (timestamp, pose T_world_kf (4, 4), its selected edges'
        pixels (N, 2) float32 (u, v)); None before the first keyframe."""
        if self._kf is None:
            return None
        edges = to_host(self._kf.edges)
        return self._kf.timestamp, self._kf.pose.copy(), np.asarray(edges.uv).T[edges.valid]

    @property
    def structure(self) -> object:
        """The static part of the solve (a jit static argument; see ``solve_inputs``)."""
        return self._static

    def solve_inputs(self) -> tuple[KeyframeEdges, np.ndarray, np.ndarray, Intrinsics, object]:
        """What a solve of the next frames needs besides the frames, for solves made
        elsewhere (``run.track_in_chunks``, ``batch.evaluate``) and concluded by
        ``accept``: the keyframe's edges, A = T_(i-1)_kf and B = T_(i-2)_kf (float32, the
        constant-velocity prediction's inputs, ``chunk.predict_matrix``), the intrinsics and the
        solve's numbers. RuntimeError before the first keyframe."""
        if self._kf is None:
            raise RuntimeError("no keyframe yet: track the first frame with track_frame")
        return (self._kf.edges, *self._rel, self.intrinsics, self.knobs)

    def accept(self, frame: Frame, timestamp: float, res: TrackResult, *,
               preprocess_ms: float = 0.0, t_submit: float | None = None
               ) -> tuple[FrameResult, bool]:
        """Conclude a frame whose solve ``res`` (host arrays) was computed elsewhere (the
        scan, a batch) from this tracker's current ``solve_inputs``. Returns its result and
        whether the state went on plainly (False: a keyframe, a loss or a recovery changed
        it, and later results of the same chunk are stale)."""
        timestamp = self._advance_time(timestamp)
        t_submit = time.perf_counter() if t_submit is None else t_submit
        pending = _Pending(frame, timestamp, self._predict(), None, preprocess_ms, t_submit)
        return self._conclude(pending, res, time.perf_counter())

    def _advance_time(self, timestamp: float) -> float:
        """The frame's timestamp as a float, made the last one; ValueError when it does not
        increase."""
        timestamp = float(timestamp)
        if self._last_t is not None and timestamp <= self._last_t:
            raise ValueError(
                f"timestamp {timestamp:.6f} does not increase (last was {self._last_t:.6f})"
            )
        self._last_t = timestamp
        return timestamp

    def _first(self, pending: _Pending) -> FrameResult:
        """The first frame (or one while there is no usable keyframe): it becomes the
        keyframe when it has enough edges with depth."""
        self._start_frame()
        made_kf = self._make_keyframe(pending.frame, pending.timestamp, pending.predicted)
        pose = pending.predicted if made_kf is None else made_kf[0]
        self._push(pose, pending.timestamp)
        state, reason = (OK, None) if made_kf else (LOST, "no edges with depth")
        if self._kf is not None:
            self._rel = self._relative_from_world()
            if self.warm_up_ms is None:
                self._warm_up(pending.frame)
        return self._result(pending, pose, state, reason, 0, None,
                            "first" if made_kf else None, 0, made_kf, time.perf_counter())

    def _conclude(self, pending: _Pending, res, t_solve: float) -> tuple[FrameResult, bool]:
        """State, recovery, keyframe decision and pose of a solved frame (see ``accept``)."""
        frame, timestamp = pending.frame, pending.timestamp
        if self._start_frame():  # refined keyframe poses taken: the prediction moved with them
            pending = dataclasses.replace(pending, predicted=self._predict(pending.prior))
        kf = start_kf = self._kf
        solved, confirmed = res, False
        lost = recovery.lost_reason(frame, res, self.config)
        # lost, or doubted (a share of inliers far under the recent frames': a wrong basin,
        # as after a prediction far off): recovery tries other starts and other keyframes
        reference = self._reference_share()
        doubt, lost_ratio = self.config.doubt_share_ratio, self.config.lost_share_ratio
        # with no reference yet (the first frames) every start is tried: the reference is
        # only as good as the frames it comes from
        if frame.num_edges > 0 and (lost is not None or self._under(res, reference, doubt)
                                    or (reference is None and doubt > 0)):
            found = self._recover(frame, pending, None if lost else res, reference)
            if found is not None:
                kf, res, confirmed = found
                lost = None
        if lost is None and self._under(res, reference, lost_ratio):
            lost = (f"inlier share {inlier_share(res):.2f} under {lost_ratio:g} x the recent "
                    f"{reference:.2f} from every start")
        inliers = int(res.inliers)
        weak = None
        if lost is None:
            T_c_k = np.asarray(res.T_c_k, np.float64)
            pose = kf.pose @ inverse_np(orthonormalise_np(T_c_k))
            reason = keyframe_reason(
                flow=float(res.flow), flow_t=float(res.flow_t), inliers=inliers,
                inlier_mean=float(np.mean(kf.inlier_counts)) if kf.inlier_counts else None,
                dt=timestamp - kf.timestamp, config=self.config,
            )
            kf.inlier_counts.append(inliers)
            self._tracked_t = timestamp
            self._shares = (self._shares + [inlier_share(res)])[-SHARE_HISTORY:]
            weak = recovery.weak_reason(frame, res, self.config) or (
                None if confirmed else self._doubt_reason(frame, kf, res, reference,
                                                          pending.timestamp))
            if kf is not self._kf:  # recovered against an earlier keyframe: it takes over
                self._kf = kf
            if reason and self._take_mapped(None):  # a new keyframe: from refined poses only
                pose = kf.pose @ inverse_np(orthonormalise_np(T_c_k))
        else:  # predicted (constant velocity), flagged
            # the keyframe stays: a guessed pose made a keyframe would carry its error into
            # every later frame. Only a loss longer than the keyframe interval starts over
            # from a new keyframe at the guess (the old one may be out of view for good)
            since = timestamp - (self._tracked_t if self._tracked_t is not None
                                 else kf.timestamp)
            reason = "lost" if since >= self.config.kf_max_interval_s else None
            pose = self._predict(pending.prior) if self._take_mapped(None) \
                else pending.predicted
            # lost frames in a row extrapolate again and again: keep R a rotation, stay finite
            pose = orthonormalise_np(pose) if np.all(np.isfinite(pose)) else pose
            if not np.all(np.isfinite(pose)):
                pose = self._poses[-1]
        used = kf.num_edges
        made_kf = self._make_keyframe(frame, timestamp, pose) if reason else None
        if made_kf is not None:
            pose = made_kf[0]  # refined in the window
        self._push(pose, timestamp)
        plain = (lost is None and kf is start_kf and made_kf is None and res is solved
                 and not self._intrinsics_moved)
        # the device predicts the next frame from A, B: the solve's own float32 pose when
        # nothing changed (as the scan carries it), else from the host's world poses
        self._rel = ((np.asarray(res.T_c_k, np.float32), self._rel[0]) if plain
                     else self._relative_from_world())
        cov = np.asarray(res.covariance, np.float64) if lost is None else None
        state = LOST if lost else (WEAK if weak else OK)
        share = None if lost else inlier_share(res)
        return self._result(pending, pose, state, lost or weak, inliers, cov,
                            reason if made_kf else None, used, made_kf, t_solve, share), plain

    def _warm_up(self, frame: Frame) -> None:
        """At the first keyframe, before any frame is tracked: compile or load, and run once,
        every program the run can need (the per-frame solve and the recovery's, for each
        slot count a keyframe can have; the selection for each candidate buffer size; the
        window's steps, on its worker), so that no frame waits for one. The tracking state is
        not touched: the keyframe's frame is solved against itself and the result dropped."""
        t0 = time.perf_counter()
        warm_map = self._mapper.warm_up() if self._mapper is not None else None
        kf, (A, B) = self._kf, self._rel
        slots = selection.bucket_sizes(self.config) if self.config.selection == "all" \
            else [kf.edges.valid.shape[0]]
        intr, knobs = self._device_constants()
        for size in slots:
            edges = kf.edges if size == kf.edges.valid.shape[0] else selection.empty_edges(
                size)._replace(depth_pts=kf.edges.depth_pts, depth_normals=kf.edges.depth_normals)
            rate = None if self.readout_s <= 0 else np.float32(0.0)
            jax.block_until_ready(track_next_jit(edges, frame.dist, frame.edge_map, A, B, intr,
                                                 knobs, rate, config=self._static))
            self._align(dataclasses.replace(kf, edges=edges), frame, np.eye(4), rate)
        h, w = frame.shape
        selection.warm_up(self.config, intr=self.intrinsics, width=w, height=h,
                          reobs_a=self._reobs_a)
        if warm_map is not None:
            warm_map.result()
        self.warm_up_ms = (time.perf_counter() - t0) * 1e3

    # -- the local map beside tracking (pipeline.mapping) ------------------------------------
    def _start_frame(self) -> bool:
        """Count the frame being concluded and take the keyframe refinements due at it;
        whether any was taken."""
        self._index += 1
        self._map_ms, self._intrinsics_moved = 0.0, False
        return self._take_mapped(self._index)

    def _take_mapped(self, frame_index: int | None) -> bool:
        """Apply the local map's refinements due at ``frame_index`` (None: all handed over,
        before a new keyframe is made); whether any was applied. A refined keyframe takes
        its new pose; when it is the current keyframe the last two frame poses move with it
        (their motion relative to it, which the device predicts from, is unchanged)."""
        if self._mapper is None:
            return False
        t0 = time.perf_counter()
        taken = self._mapper.due(frame_index)
        for m in taken:
            self._apply_mapped(m)
        if taken:
            self._map_ms += (time.perf_counter() - t0) * 1e3
        return bool(taken)

    def _apply_mapped(self, m: Mapped) -> None:
        kf: _Keyframe = m.key
        self.refinements.append(Refinement(kf.timestamp, self._index - 1, kf.pose, m.pose))
        if kf is self._kf:
            correction = m.pose @ inverse_np(kf.pose)
            self._poses = [correction @ p for p in self._poses]
        kf.pose = m.pose
        if self.config.mapping_intrinsics and tuple(m.intrinsics) != tuple(self.intrinsics):
            self.intrinsics = m.intrinsics
            self._intrinsics_moved = True  # solves made with the old ones are stale

    def _reference_share(self) -> float | None:
        """The highest inlier share (``inlier_share``) of the last ``SHARE_HISTORY`` frames
        that were not lost; None before there are any or with the check off."""
        if not self._shares or self.config.doubt_share_ratio <= 0:
            return None
        return float(np.max(self._shares))

    @staticmethod
    def _under(res, reference: float | None, ratio: float) -> bool:
        """Whether a result's inlier share is under ``ratio`` x the reference share."""
        return reference is not None and inlier_share(res) < ratio * reference

    def _doubt_reason(self, frame: Frame, kf: _Keyframe, res, reference: float | None,
                      timestamp: float) -> str | None:
        """Why a usable solve that nothing independent confirmed is doubtful (WEAK): its
        inlier share stayed under ``doubt_share_ratio`` of the recent frames' from every
        start, or it went farther from its start than the edge alignment's basin
        (``derive.basin_px``) and no feature start converges to it (``recovery.confirm``)."""
        doubt = self.config.doubt_share_ratio
        if self._under(res, reference, doubt):
            return (f"inlier share {inlier_share(res):.2f} under {doubt:g} x the recent "
                    f"{reference:.2f}, not confirmed by features")
        basin, moved = basin_px(self.config), float(res.moved)
        if moved > basin and not recovery.confirm(
                frame, kf, res, intrinsics=self.intrinsics, config=self.config,
                align=lambda k, fr, T: self._align(k, fr, T, self._rate(timestamp, fr)),
                usable=lambda out: recovery.lost_reason(frame, out, self.config) is None):
            return (f"moved {moved:.0f} px from its start, past the {basin:.0f} px basin, not "
                    "confirmed by features")
        return None

    def _recover(self, frame: Frame, pending: _Pending, first, reference: float | None):
        """``recovery.search`` from this tracker's keyframes and last poses: a
        ``recovery.Found`` (the first solve kept when nothing beats it; ``first`` None when
        it was lost), or None when nothing usable was found."""
        doubt = self.config.doubt_share_ratio
        starts = recovery.motion_starts(self._poses, self._times, pending.timestamp)
        if pending.prior is not None:  # the first solve came from the prior: also try this
            starts = [*starts, self._predict()]
        return recovery.search(
            frame, [self._kf, *reversed(self._previous)], first=first,
            predicted=pending.predicted, starts=starts,
            align=lambda kf, fr, T: self._align(kf, fr, T, self._rate(pending.timestamp, fr)),
            usable=lambda out: recovery.lost_reason(frame, out, self.config) is None,
            good_enough=None if reference is None
            else (lambda out: not self._under(out, reference, doubt)),
            intrinsics=self.intrinsics, config=self.config)

    def _align(self, kf: _Keyframe, frame: Frame, T_c_k: np.ndarray, rate=None):
        """The edge alignment of ``frame`` to ``kf`` from the start T_cur_kf (host arrays);
        ``rate``: the frame's ``shutter.Shutter.rate`` (None: a global shutter), with the
        last frame's pose as its previous one."""
        return to_host(self._dispatch_align(kf, frame, T_c_k, rate))

    def _dispatch_align(self, kf: _Keyframe, frame: Frame, T_c_k: np.ndarray, rate=None):
        """``_align`` dispatched: its result as device arrays, not waited for."""
        shutter = None if rate is None else Shutter(
            aligned_array(inverse_np(self._poses[-1]) @ kf.pose, np.float32), np.float32(rate))
        return _track_jit(
            kf.edges, frame.dist, frame.edge_map, np.asarray(T_c_k, np.float32),
            self.intrinsics, config=self._static, knobs=self.knobs, shutter=shutter)

    # -- internals ------------------------------------------------------------------------
    def _check_frame(self, rgb, depth, timestamp) -> None:
        """Clear errors for frames the pipeline cannot take (see ``track``)."""
        rgb, depth = np.asarray(rgb), np.asarray(depth)
        if rgb.dtype != np.uint8 or not (rgb.ndim == 2 or (rgb.ndim == 3 and rgb.shape[2] == 3)):
            raise ValueError(f"rgb must be uint8 (H, W, 3) or (H, W), got {rgb.dtype} "
                             f"{rgb.shape}")
        if depth.ndim != 2 or depth.dtype.kind != "f":
            hint = " (raw TUM depth PNGs: divide by 5000 for metres)" \
                if depth.dtype.kind in "ui" else ""
            raise ValueError(f"depth must be float metres (H, W), got {depth.dtype} "
                             f"{depth.shape}{hint}")
        if depth.shape != rgb.shape[:2]:
            raise ValueError(f"rgb is {rgb.shape[1]}x{rgb.shape[0]} but depth is "
                             f"{depth.shape[1]}x{depth.shape[0]} (width x height)")
        if self._shape is not None and depth.shape != self._shape:
            raise ValueError(f"frame is {depth.shape[1]}x{depth.shape[0]}, earlier frames were "
                             f"{self._shape[1]}x{self._shape[0]} (width x height)")
        if not np.isfinite(float(timestamp)):
            raise ValueError(f"timestamp must be finite, got {timestamp}")
        self._shape = depth.shape

    def _device_constants(self) -> tuple[Intrinsics, object]:
        """Intrinsics and solve knobs as device arrays, made once (and again when the local
        map refines the intrinsics): a jitted call converts each host argument anew."""
        key = tuple(self.intrinsics)
        if self._constants_key != key:
            self._constants = (Intrinsics(*jnp.asarray(key, jnp.float32)),
                               jax.device_put(self.knobs))
            self._constants_key = key
        return self._constants

    def _rate(self, timestamp: float, frame: Frame) -> np.ndarray | None:
        """``shutter_rates`` of one frame, as a float32 scalar (None: a global shutter)."""
        rates = self.shutter_rates([timestamp], frame.shape[0])
        return None if rates is None else rates[0]

    def shutter_rates(self, timestamps, height: int) -> np.ndarray | None:
        """The rolling shutter's rates (``shutter.Shutter.rate``, float32 (n,)) of the next
        frames at ``timestamps``, after the last frame concluded; None with a global shutter
        (a program without it). ``height``: the frames' rows."""
        if self.readout_s <= 0:
            return None
        t = np.asarray(timestamps, np.float64)
        prev = np.concatenate([[self._times[-1] if self._times else t[0]], t[:-1]])
        return np.array([shutter_rate(self.readout_s, height, b - a) if self._times or i
                         else 0.0 for i, (a, b) in enumerate(zip(prev, t, strict=True))],
                        np.float32)

    def _predict(self, prior: np.ndarray | None = None) -> np.ndarray:
        """The next frame's predicted T_world_cam: T_w_last @ prior with a motion prior
        T_prev_cur, else constant velocity: T_w_last (T_w_prev^-1 T_w_last)
        (``predict_np``)."""
        if prior is not None:
            return self._poses[-1] @ prior
        if len(self._poses) < 2:
            return self._poses[-1]
        prev, last = self._poses
        return predict_np(last, prev)

    def _relative_from_world(self) -> tuple[np.ndarray, np.ndarray]:
        """A, B (float32) from the last two world poses and the keyframe's (float64)."""
        rel = [aligned_array(inverse_np(p) @ self._kf.pose, np.float32) for p in self._poses]
        return rel[-1], rel[0]

    def _push(self, pose: np.ndarray, timestamp: float) -> None:
        self._poses = (self._poses + [pose])[-2:]
        self._times = (self._times + [timestamp])[-2:]

    def _make_keyframe(self, frame: Frame, timestamp: float, pose: np.ndarray
                       ) -> tuple[np.ndarray, float] | None:
        """Make the frame the keyframe: select its edges, hand it to the local map. Returns
        its pose (refined already when the map runs inline) and the selection time (ms), or
        None when it has too few usable edges (the old keyframe stays)."""
        t0 = time.perf_counter()
        # prior motion for the selection: constant velocity, T_next_kf = T_w_kf^-1 T_w_prev
        T_prior = inverse_np(pose) @ self._poses[-1] if self._poses else np.eye(4)
        edges = keyframe_edges(frame, self.config, seed=self.config.seed + self.num_keyframes,
                               T_prior=T_prior, intr=self.intrinsics, reobs_a=self._reobs_a)
        twist = None  # its motion per row, with a rolling shutter
        if self.readout_s > 0:
            twist = np.zeros(6)
            if self._poses:  # to its middle row's time: its own velocity
                rate = shutter_rate(self.readout_s, frame.shape[0],
                                    timestamp - self._times[-1])
                twist = rate * log_np(inverse_np(self._poses[-1]) @ pose)
                edges = unroll_edges(edges, twist, self.intrinsics, frame.shape[0])
        n = int(edges.valid.sum())
        if n < self.config.min_inliers:
            return None
        t1 = time.perf_counter()
        kf = _Keyframe(timestamp, pose, None, n, frame=frame)
        if self.config.mapping:
            if self._mapper is None:
                self._mapper = Mapper(self.config, self.intrinsics, frame.shape,
                                      rolling_shutter=self.readout_s > 0)
            mapped = self._mapper.add(kf, pose, edges, frame, self._index, twist)
            if mapped is not None:  # inline: refined already
                self._apply_mapped(mapped)
                pose = kf.pose
            self._map_ms += (time.perf_counter() - t1) * 1e3
        if self._kf is not None:
            self._previous = [*self._previous, self._kf][-(self.config.recovery_keyframes):]
        if self.config.depth_residual and frame.depth is not None:
            edges = edges._replace(**dict(zip(("depth_pts", "depth_normals"), depth_points(
                frame.depth, self.intrinsics, self.config.depth_points,
                min_depth=self.config.min_depth, max_depth=self.config.max_depth,
                seed=self.config.seed + self.num_keyframes), strict=True)))
        kf.edges = KeyframeEdges(*jax.tree.map(jnp.asarray, edges))
        self._kf = kf
        self.num_keyframes += 1
        return pose, (t1 - t0) * 1e3

    def _result(self, pending, pose, state, reason, inliers, cov, kf, used, made_kf,
                t_solve, share: float | None = None) -> FrameResult:
        t_end = time.perf_counter()
        solve_ms = (t_solve - pending.t_submit) * 1e3
        return FrameResult(
            timestamp=pending.timestamp, pose=pose, state=state, reason=reason, inliers=inliers,
            covariance=cov, keyframe=kf, edges_used=used,
            select_ms=made_kf[1] if made_kf else None,
            mapping_ms=self._map_ms if self._mapper is not None and (
                made_kf or self._map_ms > 0.0) else None,
            preprocess_ms=pending.preprocess_ms, solve_ms=solve_ms,
            total_ms=pending.preprocess_ms + (t_end - pending.t_submit) * 1e3,
            inlier_share=share,
        )

