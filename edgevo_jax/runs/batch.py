"""Many runs at once: sequences x configurations tracked by one compiled program.

Every (sequence, configuration) pair is a *run*. All runs step together: one call of
``vmap(chunk.track_chunk)`` tracks the next ``chunk`` frames of every run against that run's
keyframe, with the numeric settings of the solve (``derive.SolveKnobs``: Huber radii, gates,
eta, iterations, step tolerance) as vmapped arrays, so a grid of them costs one compilation.
The host then concludes each run's frames in order with that run's own ``Odometry`` (state,
recovery, keyframe decision and edge selection, local mapping), exactly as the
frame-by-frame driver does, and a run whose state changed part-way re-tracks the rest of its
chunk in the next call. Each run's trajectory is therefore the one it gets alone.

Settings of the host side (keyframe rule, selection mode, ``num_edges``, seeds, mapping) may
differ freely between runs. Runs whose keyframes hold different numbers of edge slots
(``num_edges``; ``selection=all`` sizes them per keyframe) go in separate calls of the same
program, one per slot count: padding the slots would change XLA's summation order, and with
it (through Levenberg-Marquardt's accept / reject decisions) the trajectory.
Preprocessing settings (blur, Canny thresholds, depth range) make their own groups of
pre-processed frames, each computed once per sequence and streamed: frames are made when the
slowest run needs them and dropped when every run is past them. All runs need the same
number of pyramid levels and the same image size.

Devices: the runs axis is sharded over ``devices`` (default: all local devices) with a
``NamedSharding`` over a one-axis mesh ``("runs",)``; the batch is padded with copies of the
last run to a multiple of the device count. Under ``jax.distributed`` each process takes the
runs ``process_index::process_count`` on its own local devices (runs are independent, so
nothing crosses hosts) and returns those; ``pipeline.sweep`` starts the processes, splits a
sweep's runs among them itself and gathers the results.

On one device the step is a kept program (``programs.program``): a later process loads it
instead of tracing and compiling it again.
"""

from __future__ import annotations

import dataclasses
import itertools
import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import Future, ThreadPoolExecutor, wait
from dataclasses import dataclass, field
from functools import cache, partial

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec
from tqdm import tqdm

from ..camera import Intrinsics
from ..config import Config
from ..datasets.source import Source, camera_readout, depth_lags
from ..derive import SolveStructure, solve_structure
from ..determinism import full_precision
from ..frontend.chunk import track_chunk
from ..frontend.selection import KeyframeEdges
from ..hostmem import aligned_stack, to_host
from ..image.interp import stack_edge_maps
from ..image.preprocess import Frame, preprocess
from ..programs import enable_cache, program
from ..tracking.odometry import Odometry
from ..tracking.results import FrameResult, FrameResults
from .configs import changed_fields, configs_from_spec, load_configs  # noqa: F401 (batch.*)
from .run import conclude_chunk, initial_pose

#: Config fields that change the pre-processed frames (runs differing in them do not share).
PREPROCESS_FIELDS = ("blur_ksize", "blur_sigma", "canny_low", "canny_high", "min_depth",
                     "max_depth", "iterations")


@dataclass
class BatchRun(FrameResults):
    """One run of a batch: the sequence's name, its configuration (and its index in the
    ``configs`` given), and the per-frame results in order (``poses`` (N, 4, 4)
    T_world_cam, ``timestamps`` (N,) s); ``batch_ms_per_frame``: the batch's wall time from
    its start to this run's last frame, per frame it had tracked by then over all its runs
    (ms; the batch's time shared over its runs, preprocessing and compilation included)."""

    sequence: str
    config_index: int
    config: Config
    results: list[FrameResult] = field(default_factory=list)
    num_keyframes: int = 0
    batch_ms_per_frame: float = float("nan")

    def summary_fields(self) -> dict:
        """The run's own fields for ``run.summarise``: its configuration's index and the
        batch's time per frame up to its end."""
        return {"config_index": self.config_index,
                "batch_ms_per_frame": self.batch_ms_per_frame}


@dataclass
class BatchResult:
    """The runs (sequence-major: all configurations of the first sequence first) and what
    the batch cost: wall time (s, preprocessing and compilation included), the number of
    device calls, lane-frames solved (including the ones re-tracked after a state change)
    and the devices used."""

    runs: list[BatchRun]
    wall_s: float
    calls: int
    solved: int
    devices: list[str]


class _Frames:
    """The pre-processed frames of one sequence under one preprocessing setting: made ahead
    on a background thread (decoding and OpenCV release the GIL, so this overlaps the
    device and the host logic) and dropped once every run is past them, so that memory
    stays bounded whatever the sequence's length."""

    def __init__(self, seq: Source, config: Config, n: int) -> None:
        self.seq, self.config, self.n = seq, config, n
        self.lags = depth_lags(seq)  # each depth image's time after its colour image's
        self._futures: dict[int, Future] = {}
        self._low = 0  # frames before this one are dropped
        self._lock = threading.Lock()  # runs are concluded on two threads (_concluders)

    def _make(self, i: int) -> Frame:
        frame = preprocess(*self.seq.rectify_frame(*self.seq.decode_frame(i)), self.config)
        if self.lags is None:
            return frame
        return dataclasses.replace(frame, depth_lag_s=float(self.lags[i]))

    def prefetch(self, upto: int) -> None:
        """Start making the frames up to index ``upto`` (exclusive) not yet asked for."""
        for i in range(self._low, min(upto, self.n)):
            if i not in self._futures:
                self._futures[i] = _prefetcher().submit(self._make, i)

    def __getitem__(self, i: int) -> Frame:
        i = min(i, self.n - 1)
        with self._lock:
            if i not in self._futures:
                self._futures[i] = _prefetcher().submit(self._make, i)
            job = self._futures[i]
        return job.result()

    def drop_before(self, i: int) -> None:
        """Forget the frames before index ``i``."""
        self._low = max(self._low, i)
        for k in [k for k in self._futures if k < i]:
            del self._futures[k]


@cache
def _prefetcher() -> ThreadPoolExecutor:
    """One thread that decodes and pre-processes frames ahead of the batch."""
    return ThreadPoolExecutor(max_workers=1, thread_name_prefix="edgevo-batch")


@cache
def _concluders() -> ThreadPoolExecutor:
    """Two threads that conclude runs' chunks side by side (a run's host logic, selection
    and local mapping; XLA's calls release the GIL, so two runs' windows refine at once)."""
    return ThreadPoolExecutor(max_workers=2, thread_name_prefix="edgevo-conclude")


@dataclass
class _Lane:
    run: BatchRun
    odo: Odometry
    frames: _Frames
    timestamps: np.ndarray
    position: int = 0
    reported: bool = False

    @property
    def done(self) -> bool:
        return self.position >= len(self.timestamps)


@dataclass
class _Call:
    """What every device call of a batch shares: the compiled step (``_batched``), the runs
    axis' sharding (None on one device), the frame sources, ``chunk`` frames per run per
    call, ``width`` (chunk + max_lag) frames of each source's window, the device count and
    whether the runs carry rolling-shutter rates."""

    step: Callable
    sharding: NamedSharding | None
    srcs: list[_Frames]
    chunk: int
    width: int
    num_devices: int
    shutter: bool


def _preprocess_key(config: Config) -> tuple:
    return tuple(getattr(config, f) for f in PREPROCESS_FIELDS)


def _step(kf, window_dist, window_ng, source, offset, A, B, intr, knobs, rates, *, config,
          chunk):
    """One run's chunk: frames ``offset .. offset + chunk`` of window ``source``; ``rates``
    (chunk,) their rolling-shutter rates (None: every run has a global shutter)."""
    dist = tuple(jax.lax.dynamic_slice_in_dim(w[source], offset, chunk) for w in window_dist)
    ng = jax.tree.map(lambda w: jax.lax.dynamic_slice_in_dim(w[source], offset, chunk),
                      window_ng)
    return track_chunk(kf, dist, ng, A, B, intr, knobs, rates, config=config)


_IN_AXES = (0, None, None, 0, 0, 0, 0, 0, 0, 0)


def batch_step(kf, window_dist, window_ng, source, offset, A, B, intr, knobs, rates, *,
               config: SolveStructure, chunk: int):
    """The batch step: ``_step`` vmapped over runs (the frame windows shared, not mapped);
    ``config``: the solve's static part."""
    return jax.vmap(partial(_step, config=config, chunk=chunk), in_axes=_IN_AXES)(
        kf, window_dist, window_ng, source, offset, A, B, intr, knobs, rates)


#: the batch step on one device, kept across processes (``programs.program``)
batch_step_kept = program(batch_step, static_argnames=("config", "chunk"))


@cache
def _batched(config: SolveStructure, chunk: int, sharding: NamedSharding | None):
    """The compiled batch step for ``config`` and ``chunk``: the kept program on one device,
    else jitted with its outputs sharded over the runs axis."""
    if sharding is None:
        return partial(batch_step_kept, config=config, chunk=chunk)
    return full_precision(jax.jit(partial(batch_step, config=config, chunk=chunk),
                                  out_shardings=sharding))


def _structure(configs: Sequence[Config]) -> SolveStructure:
    """The static part of the solve that every run shares (``derive.solve_structure``)."""
    levels = {c.num_levels for c in configs}
    if len(levels) != 1:
        raise ValueError(f"all configurations of a batch need the same number of pyramid "
                         f"levels (len(iterations)); got {sorted(levels)}")
    return solve_structure(configs[0])


def evaluate(
    sequences: Sequence[Source],
    configs: Sequence[Config],
    *,
    chunk: int = 2,
    max_frames: int | None = None,
    max_lag: int | None = None,
    devices: Sequence[jax.Device] | None = None,
    progress: bool = True,
    runs: Sequence[tuple[int, int]] | None = None,
    on_run: Callable[[BatchRun], None] | None = None,
) -> BatchResult:
    """Track every sequence under every configuration in one compiled program per step.

    ``chunk`` frames per run per device call (a run's chunk is cut at its next keyframe and
    re-tracked, so short chunks waste least where keyframes are frequent); ``max_frames``
    limits each sequence; a run more than ``max_lag`` (default ``chunk``) frames ahead of the
    slowest run that shares its pre-processed frames waits (each call carries chunk +
    max_lag frames of every preprocessing group and sequence); ``devices`` to shard
    the runs over (default ``jax.local_devices()``).
    ``runs``: the (sequence index, configuration index) pairs to track, in that order
    (default: every pair, sequence-major, and under ``jax.distributed`` this process's share
    ``process_index::process_count`` of them); ``on_run(run)`` is called with each run as
    soon as it is finished (its results complete, its tracker closed), on the calling thread.
    Returns the runs tracked, in order, with each run's per-frame results.
    """
    if not sequences or not configs:
        raise ValueError("evaluate needs at least one sequence and one configuration")
    enable_cache()  # before any JAX computation: programs kept on disk, batch-exact arithmetic
    if chunk < 1:
        raise ValueError(f"chunk must be positive, got {chunk}")
    max_lag = chunk if max_lag is None else max_lag
    pairs = _checked_pairs(sequences, configs, runs)
    static = _structure([configs[c] for _, c in pairs] or configs)
    t_start = time.perf_counter()
    sources, mine = _lanes(sequences, configs, pairs, max_frames)
    devices = list(jax.local_devices() if devices is None else devices)
    sharding = _runs_sharding(devices)
    # one program for all: rolling-shutter rates for every run when any run has one (a
    # rate of 0 is a global shutter's solve, to the bit)
    call = _Call(_batched(static, chunk, sharding), sharding, list(sources.values()), chunk,
                 chunk + max_lag, len(devices), any(lane.odo.readout_s > 0 for lane in mine))
    total = sum(len(lane.timestamps) for lane in mine)
    bar = tqdm(total=total, desc="batch", unit="frame", disable=not progress, leave=False)
    calls = solved = 0
    try:
        while True:
            _track_first_frames(mine, bar)
            _report_finished(mine, t_start, on_run)
            live = [lane for lane in mine if not lane.done]
            if not live:
                break
            slowest, stepping = _windows(call, mine, live, max_lag)
            made, frames = _step_groups(call, mine, slowest, stepping, bar)
            calls, solved = calls + made, solved + frames
            _drop_passed(call.srcs, mine)
    finally:
        bar.close()
        for lane in mine:
            lane.odo.close()
            lane.run.num_keyframes = lane.odo.num_keyframes
    return BatchResult(runs=[lane.run for lane in mine], wall_s=time.perf_counter() - t_start,
                       calls=calls, solved=solved, devices=[str(d) for d in devices])


def _checked_pairs(sequences: Sequence[Source], configs: Sequence[Config],
                   runs: Sequence[tuple[int, int]] | None) -> list[tuple[int, int]]:
    """The (sequence index, configuration index) pairs to track, in order: ``runs``, or
    every pair sequence-major (this process's share ``process_index::process_count``).
    ValueError when the sequences' image sizes (H, W) differ or a pair names no sequence
    and configuration."""
    sizes = {(s.height, s.width) for s in sequences}
    if len(sizes) != 1:
        raise ValueError(f"all sequences of a batch need one image size, got {sorted(sizes)}")
    if runs is None:
        pairs = list(itertools.product(range(len(sequences)), range(len(configs))))
        return pairs[jax.process_index()::jax.process_count()]
    pairs = list(runs)
    bad = [p for p in pairs if not (0 <= p[0] < len(sequences) and 0 <= p[1] < len(configs))]
    if bad:
        raise ValueError(f"runs {bad} name no (sequence, configuration) of "
                         f"{len(sequences)} sequences and {len(configs)} configurations")
    return pairs


def _lanes(sequences: Sequence[Source], configs: Sequence[Config],
           pairs: list[tuple[int, int]], max_frames: int | None
           ) -> tuple[dict[tuple, _Frames], list[_Lane]]:
    """A lane per pair (its run, its own ``Odometry`` from the sequence's initial pose, its
    first ``max_frames`` timestamps (s)), and the frame sources they read, one per sequence
    and preprocessing setting (key: (sequence index, ``_preprocess_key``)), shared."""
    sources: dict[tuple, _Frames] = {}
    mine: list[_Lane] = []
    for s, c in pairs:
        seq, config = sequences[s], configs[c]
        n = len(seq) if max_frames is None else min(len(seq), max_frames)
        key = (s, _preprocess_key(config))
        if key not in sources:
            sources[key] = _Frames(seq, config, n)
        run = BatchRun(seq.name, c, config)
        odo = Odometry(config, seq.intrinsics, initial_pose=initial_pose(seq),
                       readout_s=camera_readout(seq))
        mine.append(_Lane(run, odo, sources[key], np.asarray(seq.timestamps[:n])))
    return sources, mine


def _runs_sharding(devices: list[jax.Device]) -> NamedSharding | None:
    """The runs axis sharded over ``devices`` (a one-axis mesh ``("runs",)``); None for a
    single device (the kept program)."""
    return (NamedSharding(Mesh(np.array(devices), ("runs",)), PartitionSpec("runs"))
            if len(devices) > 1 else None)


def _track_first_frames(lanes: list[_Lane], bar: tqdm) -> None:
    """Track, frame by frame on the host, each run's first frames (and the frames before any
    usable keyframe): those the batch step cannot solve without a keyframe."""
    for lane in lanes:
        while not lane.done and not lane.odo.has_keyframe:
            i = lane.position
            lane.run.results.append(lane.odo.track_frame(lane.frames[i], lane.timestamps[i]))
            lane.position += 1
            bar.update(1)


def _windows(call: _Call, lanes: list[_Lane], live: list[_Lane], max_lag: int
             ) -> tuple[list[int], list[bool]]:
    """Each source's window start (the position of the slowest ``live`` run reading it, 0
    when none does), its frames made ahead, and which runs step now: the runs not done and
    at most ``max_lag`` frames ahead of their window's start (a run further ahead waits:
    bounded memory, fixed shapes)."""
    slowest = [min((la.position for la in live if la.frames is src), default=0)
               for src in call.srcs]
    for src, low in zip(call.srcs, slowest, strict=True):
        src.prefetch(low + 2 * call.width)
    stepping = [not lane.done and lane.position - slowest[call.srcs.index(lane.frames)]
                <= max_lag for lane in lanes]
    return slowest, stepping


def _step_groups(call: _Call, lanes: list[_Lane], slowest: list[int], stepping: list[bool],
                 bar: tqdm) -> tuple[int, int]:
    """One device call per keyframe edge count K among the runs with a keyframe (padding K
    would change XLA's summation order and so the trajectory; grouped, each run gives what
    it gives alone), for the groups with a run ``stepping``; each stepping run's chunk is
    then concluded in order. Returns the number of calls and of lane-frames solved."""
    groups: dict[int, list[int]] = {}
    for b, lane in enumerate(lanes):
        if lane.odo.num_keyframes:
            groups.setdefault(lane.odo.solve_inputs()[0].valid.shape[0], []).append(b)
    calls = solved = 0
    for members in groups.values():
        if not any(stepping[b] for b in members):
            continue
        inputs = _stack_inputs([lanes[b] for b in members], call.srcs, slowest, call.width,
                               call.num_devices, call.chunk, call.shutter)
        if call.sharding is not None:
            per_run = jax.device_put([*inputs[:1], *inputs[3:]], call.sharding)
            inputs = (per_run[0], *inputs[1:3], *per_run[1:])
        out = to_host(call.step(*inputs))
        calls += 1
        solved += sum(stepping[b] for b in members) * call.chunk
        # runs are independent: each one's conclusions go in order on one thread
        jobs = [_concluders().submit(_conclude_chunk, lanes[b],
                                     jax.tree.map(lambda a, k=k: a[k], out), call.chunk, bar)
                for k, b in enumerate(members) if stepping[b]]
        wait(jobs)  # both finish before an error in either is raised
        for job in jobs:
            job.result()
    return calls, solved


def _drop_passed(srcs: list[_Frames], lanes: list[_Lane]) -> None:
    """Drop each source's frames before the position of the slowest unfinished run reading
    it (all of them when no such run is left)."""
    for src in srcs:
        users = [lane.position for lane in lanes if lane.frames is src and not lane.done]
        src.drop_before(min(users) if users else 1 << 62)


def _report_finished(lanes: list[_Lane], t_start: float,
                     on_run: Callable[[BatchRun], None] | None) -> None:
    """Close the trackers of runs that just finished, stamp their batch time per frame and
    hand them to ``on_run``."""
    tracked = sum(lane.position for lane in lanes)
    for lane in lanes:
        if lane.done and not lane.reported:
            lane.reported = True
            lane.odo.close()
            lane.run.num_keyframes = lane.odo.num_keyframes
            lane.run.batch_ms_per_frame = (time.perf_counter() - t_start) * 1e3 / max(tracked, 1)
            if on_run is not None:
                on_run(lane.run)


def _conclude_chunk(lane: _Lane, out, chunk: int, bar: tqdm) -> None:
    """Conclude a run's chunk in order, up to the first frame that changes its state."""
    stop = min(lane.position + chunk, len(lane.timestamps))
    frames = [lane.frames[i] for i in range(lane.position, stop)]  # prefetched: just solved
    done = conclude_chunk(lane.odo, frames, lane.timestamps[lane.position:stop], out)
    lane.run.results += done
    lane.position += len(done)
    bar.update(len(done))


def _stack_inputs(lanes: list[_Lane], srcs: list[_Frames], slowest: list[int], width: int,
                  num_devices: int, chunk: int, shutter: bool) -> tuple:
    """The step's inputs for runs whose keyframes have the same number of edge slots: per run
    (stacked on a leading runs axis, padded to a power of two times the device count with
    copies of the last run, so that few shapes compile) the keyframe edges, its window and
    offset, A, B, intrinsics, solve knobs and, with ``shutter``, the rolling-shutter rates
    of its next ``chunk`` frames (0 for a global shutter); and the windows, ``width`` frames
    of each source from its slowest run on (the last frame repeated past the end)."""
    per_lane = []
    for lane in lanes:
        kf, A, B, intr, knobs = lane.odo.solve_inputs()
        s = srcs.index(lane.frames)
        offset = np.int32(min(max(lane.position - slowest[s], 0), width - 1))
        rates = None
        if shutter:
            ts = lane.timestamps[lane.position:lane.position + chunk]
            rates = lane.odo.shutter_rates(ts, lane.frames.seq.height) if len(ts) else None
            rates = np.zeros(chunk, np.float32) if rates is None else np.concatenate(
                [rates, np.repeat(rates[-1:], chunk - len(rates))])
        per_lane.append((KeyframeEdges(*jax.tree.map(np.asarray, kf)), np.int32(s), offset,
                         A, B, np.asarray(intr, np.float32), knobs, rates))
    size = 1 << (len(per_lane) - 1).bit_length()
    size += -size % num_devices
    per_lane += [per_lane[-1]] * (size - len(per_lane))
    kf, source, offset, A, B, intr, knobs, rates = jax.tree.map(lambda *xs: aligned_stack(xs),
                                                                *per_lane)
    frames = [[src[low + j] for j in range(width)] for src, low in zip(srcs, slowest,
                                                                       strict=True)]
    levels = len(frames[0][0].dist)
    window_dist = tuple(aligned_stack([aligned_stack([f.dist[lv] for f in fs]) for fs in frames])
                        for lv in range(levels))
    window_ng = stack_edge_maps([stack_edge_maps([f.edge_map for f in fs]) for fs in frames])
    return (kf, window_dist, window_ng, source, offset, A, B, Intrinsics(*intr.T), knobs,
            rates)
