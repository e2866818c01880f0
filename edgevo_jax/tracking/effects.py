"""The streaming tracker's host effects, carried out for its decision (``decision``): device
solves (the per-frame solve and the alignment the recovery runs), the making of a keyframe
(edge selection, the depth residual's points; the back end takes it from there:
``backend``) and the warm-up that compiles every program before the first tracked frame.

``Solver`` holds what every solve of one tracker shares: the configuration's static part and
numbers, the intrinsics (which the window may refine) and the rolling shutter's readout.
"""

from __future__ import annotations

import time
from typing import NamedTuple

import jax
import numpy as np

from ..camera import Intrinsics
from ..config import Config
from ..derive import basin_px, solve_knobs, solve_structure
from ..frontend import selection
from ..frontend.chunk import track_next_jit
from ..frontend.depth import depth_agreement, depth_points
from ..frontend.features import Detections
from ..frontend.selection import KeyframeEdges, keyframe_edges
from ..frontend.shutter import depths_at_colour_time, shutter_rate, unroll_edges
from ..geometry import inverse_np, log_np
from ..hostmem import aligned_array, to_host
from ..image.preprocess import Frame, beside
from ..learn.params import Params, solve_knobs_of
from ..window.worker import Window
from . import recovery
from .decision import (
    Check,
    Confirm,
    Keyframe,
    MakeKeyframe,
    Search,
    TrackerState,
    lost_reason,
    under,
)


class Made(NamedTuple):
    """A keyframe as ``make_keyframe`` made it, the selection time (ms), its edges on the host
    (what the window and the keyframe map take) and, with a rolling shutter, its motion per
    level-0 row (a twist (6,); None with a global shutter)."""

    keyframe: Keyframe
    select_ms: float
    host_edges: KeyframeEdges
    row_twist: np.ndarray | None


class Solver:
    """The solves of one tracker: ``config``, ``intrinsics`` (replaced when the window refines
    them), ``readout_s`` (0: a global shutter), learnt ``params`` (None: the config's
    numbers). The solve's numbers go in as (traced) arrays and its static part as a jit
    static argument: configurations that differ in numbers only share one program."""

    def __init__(self, config: Config, intrinsics: Intrinsics, readout_s: float,
                 params: Params | None) -> None:
        self.config, self.intrinsics, self.readout_s = config, intrinsics, readout_s
        self.knobs, self.structure = solve_knobs(config), solve_structure(config)
        self.reobs_a: float | None = None  # the selection's offset a (None: the config's)
        if params is not None:
            self.knobs = solve_knobs_of(params, config)
            self.reobs_a = float(np.asarray(params.reobs_a, np.float64))
        self._constants_key: tuple[float, ...] | None = None

    def constants(self) -> tuple[Intrinsics, object]:
        """Intrinsics and solve knobs as device arrays, made once (and again when the window
        refines the intrinsics): a jitted call converts each host argument anew."""
        key = tuple(self.intrinsics)
        if self._constants_key != key:
            self._constants = (Intrinsics(*jax.device_put(tuple(np.float32(v) for v in key))),
                               jax.device_put(self.knobs))
            self._constants_key = key
        return self._constants

    def rates(self, timestamps, height: int, times: tuple[float, ...]) -> np.ndarray | None:
        """The rolling shutter's rates (``shutter.Shutter.rate``, float32 (n,)) of frames at
        ``timestamps`` after the frames at ``times`` (the last concluded last); None with a
        global shutter."""
        if self.readout_s <= 0:
            return None
        t = np.asarray(timestamps, np.float64)
        prev = np.concatenate([[times[-1] if times else t[0]], t[:-1]])
        return np.array([shutter_rate(self.readout_s, height, b - a) if times or i
                         else 0.0 for i, (a, b) in enumerate(zip(prev, t, strict=True))],
                        np.float32)

    def rate(self, timestamp: float, frame: Frame, times: tuple[float, ...]):
        """``rates`` of one frame, as a float32 scalar (None: a global shutter)."""
        rates = self.rates([timestamp], frame.shape[0], times)
        return None if rates is None else rates[0]

    def next(self, kf: Keyframe, frame: Frame, rel, rate):
        """The per-frame solve from the device's constant-velocity prediction (A, B ``rel``),
        dispatched: device arrays, not waited for."""
        intr, knobs = self.constants()
        return track_next_jit(kf.edges, frame.dist, frame.edge_map, *rel, intr, knobs, rate,
                              config=self.structure)

    def dispatch(self, kf: Keyframe, frame: Frame, T_c_k: np.ndarray, rate, last_pose):
        """The edge alignment of ``frame`` to ``kf`` from the start T_cur_kf, dispatched;
        ``rate``: the frame's shutter rate (None: a global shutter), with ``last_pose`` (the
        last frame's T_world_cam) as its previous one. It runs the per-frame solve's program
        (one program to compile, not two): A = T_last_kf (the shutter's previous pose; the
        start itself where there is no last frame) and B = A T^-1 A, whose constant-velocity
        prediction A B^-1 A is the start T (to float32 rounding)."""
        T = np.asarray(T_c_k, np.float64)
        A = T if last_pose is None else inverse_np(last_pose) @ kf.pose
        B = A @ inverse_np(T) @ A
        return self.next(kf, frame, (aligned_array(A, np.float32), aligned_array(B, np.float32)),
                         None if rate is None else np.float32(rate))

    def align(self, kf: Keyframe, frame: Frame, T_c_k: np.ndarray, rate, last_pose):
        """``dispatch``, read back (host arrays)."""
        return to_host(self.dispatch(kf, frame, T_c_k, rate, last_pose))


def aligner(solver: Solver, state: TrackerState, frame: Frame, timestamp: float):
    """``align(kf, frame, T_cur_kf)`` and ``usable(solve)`` for the recovery's solves of a
    frame at ``timestamp``, after the frames of ``state``."""
    last = state.motion.poses[-1] if state.motion.poses else None

    def align(kf, fr, T_c_k):
        return solver.align(kf, fr, T_c_k, solver.rate(timestamp, fr, state.motion.times), last)

    def usable(out) -> bool:
        return lost_reason(frame.num_edges, out, solver.config) is None

    return align, usable


def search(solver: Solver, state: TrackerState, frame: Frame, ask: Search, timestamp: float,
           predicted: np.ndarray, prior: np.ndarray | None, found: Detections | None
           ) -> recovery.Found | None:
    """The recovery search ``ask`` asks for (``recovery.search``) from the state's keyframes
    (the current one, then the earlier ones, newest first) and last poses; with a motion
    prior, the constant-velocity start as well. ``found``: the frame's keypoints."""
    config = solver.config
    align, usable = aligner(solver, state, frame, timestamp)
    starts = recovery.motion_starts(state.motion.poses, state.motion.times, timestamp)
    if prior is not None:  # the first solve came from the prior: also try this
        starts = [*starts, state.motion.predict()]
    reference, doubt = ask.reference, config.doubt_share_ratio
    return recovery.search(
        frame, [state.keyframe, *reversed(state.previous)], first=ask.first,
        predicted=predicted, starts=starts, align=align, usable=usable,
        good_enough=None if reference is None else (lambda out: not under(out, reference, doubt)),
        intrinsics=solver.intrinsics, config=config, found=found,
        # with the map, a frame far from every start is the map's to find
        basin=basin_px(config) if config.map else None)


def confirm(solver: Solver, state: TrackerState, frame: Frame, ask: Confirm,
            timestamp: float, found: Detections | None) -> bool:
    """Whether a feature start converges to the solve ``ask`` names (``recovery.confirm``;
    ``found``: the frame's keypoints)."""
    align, usable = aligner(solver, state, frame, timestamp)
    return recovery.confirm(frame, ask.keyframe, ask.solve, align=align, usable=usable,
                            intrinsics=solver.intrinsics, config=solver.config, found=found)


def check(solver: Solver, previous: np.ndarray | None, frame: Frame, ask: Check
          ) -> float | None:
    """The second opinion ``ask`` asks for (``frontend.depth.depth_agreement``) between the
    depth image of the last frame not LOST (``previous``; None: none kept) and ``frame``'s,
    seeded by the configuration's seed; None where either has no depth image."""
    if previous is None or frame.depth is None:
        return None
    config = solver.config
    return depth_agreement(previous, frame.depth, ask.T_cur_prev, solver.intrinsics,
                           tol_m=config.depth_check_tol_m, min_depth=config.min_depth,
                           max_depth=config.max_depth, seed=config.seed)


def make_keyframe(solver: Solver, frame: Frame, ask: MakeKeyframe, found: Detections | None
                  ) -> Made | None:
    """Make ``frame`` (``found``: its keypoints, which the keyframe keeps) the keyframe ``ask``
    describes: select its edges (seeded by the keyframe's number; prior motion: constant
    velocity, T_next_kf = T_w_kf^-1 T_w_prev), move their depths to the colour image's time
    where the depth image was taken apart from it (``frame.depth_lag_s``; the velocity from
    the previous frame), unroll them for a rolling shutter (its own velocity to its middle
    row) and add the depth residual's points (not moved: that residual pairs two depth
    images, each taken apart from its colour image alike). None when it has too few usable
    edges."""
    config, motion, pose = solver.config, ask.motion, ask.pose
    t0 = time.perf_counter()
    points = None  # the depth residual's points, on the preprocessing's idle worker meanwhile
    if config.depth_residual and frame.depth is not None:
        points = beside(depth_points, frame.depth, solver.intrinsics, config.depth_points,
                        min_depth=config.min_depth, max_depth=config.max_depth,
                        seed=config.seed + ask.id)
    T_prior = inverse_np(pose) @ motion.poses[-1] if motion.poses else np.eye(4)
    edges = keyframe_edges(frame, config, seed=config.seed + ask.id, T_prior=T_prior,
                           intr=solver.intrinsics, reobs_a=solver.reobs_a)
    # its motion since the previous frame (a twist) and the time it took
    step = log_np(inverse_np(motion.poses[-1]) @ pose) if motion.poses else None
    dt = ask.timestamp - motion.times[-1] if motion.poses else 0.0
    if frame.depth_lag_s != 0.0 and step is not None:
        edges = depths_at_colour_time(edges, step / max(dt, 1e-3), frame.depth_lag_s,
                                      solver.intrinsics)
    twist = None  # its motion per row, with a rolling shutter
    if solver.readout_s > 0:
        twist = np.zeros(6)
        if step is not None:
            twist = shutter_rate(solver.readout_s, frame.shape[0], dt) * step
            edges = unroll_edges(edges, twist, solver.intrinsics, frame.shape[0])
    n = int(edges.valid.sum())
    if n < config.min_inliers:
        return None
    t1 = time.perf_counter()
    if points is not None:
        edges = edges._replace(**dict(zip(("depth_pts", "depth_normals"), points.result(),
                                          strict=True)))
    kf = Keyframe(ask.id, ask.timestamp, pose, n, frame=frame, features=found,
                  edges=jax.device_put(edges))
    return Made(kf, (t1 - t0) * 1e3, edges, twist)


def warm_up(solver: Solver, window: Window | None, kf: Keyframe, frame: Frame) -> None:
    """At the first keyframe, before any frame is tracked: compile or load, and run once,
    every program the run can need (the solve, which the recovery shares, for the
    keyframe's slot count; the selection for each candidate buffer size, on the
    preprocessing's idle worker meanwhile), and wait for the window's (``Window.warm_up``,
    started on its worker when it was made), so that no frame waits for one.
    With ``selection=all`` the slot count follows the keyframe's edges (``selection._bucket``:
    1024 to ``max_edges``, five sizes at the default): a keyframe whose count is new compiles
    its solve when it is made (a recording meets one or two sizes; compiling all five first
    took 80 s here). The keyframe's frame is solved against itself and the result dropped."""
    config = solver.config
    h, w = frame.shape
    sizes = beside(selection.warm_up, config, intr=solver.intrinsics, width=w, height=h,
                   reobs_a=solver.reobs_a)
    rel = (aligned_array(inverse_np(kf.pose) @ kf.pose, np.float32),) * 2
    rate = None if solver.readout_s <= 0 else np.float32(0.0)
    jax.block_until_ready(solver.next(kf, frame, rel, rate))  # the recovery's program too
    sizes.result()
    if window is not None:
        window.warmed()

