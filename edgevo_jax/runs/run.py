"""Running the tracker over a whole TUM sequence: decoding, pipelining, trajectory file,
progress bar and the run's statistics; and tracking in device-side chunks (the scan).

Frame i is decoded, frame i-1 submitted to the device, frame i's edges found and its distance
transform started on a worker thread; frame i-1 is completed (its solve result read back,
keyframe decision and edge selection) while that transform runs, then frame i's
preprocessing finished. JAX dispatch is asynchronous and OpenCV releases the GIL, so the two
cores share the work. The solve overlaps preprocessing only, never decoding, so the reported
per-frame time (decoding excluded) is what a live camera would see. Tracking results are
identical to the synchronous ``Odometry.track``: preprocessing does not depend on the tracking
state.
"""

from __future__ import annotations

import dataclasses
import math
import sys
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import jax
import numpy as np
from tqdm import tqdm

from ..config import Config
from ..datasets.groundtruth import groundtruth_pose_at
from ..datasets.source import Source, camera_readout, depth_lags
from ..derive import structural_fields
from ..frontend.align import TrackResult
from ..frontend.chunk import track_chunk_jit
from ..hostmem import aligned_stack, to_host
from ..image.interp import stack_edge_maps
from ..image.preprocess import Frame, start_preprocess
from ..io import TrajectoryWriter, matrices_to_poses7, poses7_to_matrices
from ..learn.params import Params
from ..metrics import ate, rpe_per_second
from ..programs import enable_cache
from ..tracking.decision import DEPTH_DISAGREES
from ..tracking.odometry import Odometry
from ..tracking.results import LOST, OK, WEAK, Correction, FrameResult, FrameResults
from .truth import DIVERGED_ROT_DEG, DIVERGED_TRANS_M, groundtruth_at, silently_wrong


@dataclass
class RunResult(FrameResults):
    """A finished (or interrupted) run: per-frame results in order, the wall time of each
    frame with image decoding excluded (ms; with pipelining this is the frame period), the
    decode times (ms); the start-up (s): from the start (``run_sequence``'s ``started``) to
    the first pose, which includes ``warm_up_s``, the tracker's compiling or loading of every
    program the run needs (``effects.warm_up``); the local window's time per keyframe on
    its worker (ms); ``corrections``: earlier poses moved into the keyframe map's frame or
    by a closed loop (``results.Correction``, applied to ``results`` and the trajectory file
    at the end of the run), and ``online_poses`` (N, 4, 4): the poses as each frame was
    reported, before them (None when none moved); the map's keyframes, bytes and the first
    keyframe it refused at its cap (None each with ``Config.map`` off; ``map_full_at`` None
    below the cap); ``loops``: the loops closed and rejected and the pose graph's solves
    (``Odometry.loop_stats``; None with ``Config.loops`` or the map off); ``map_file``: the
    map the run started in (None: none), ``found_in_loaded``: the index of the first frame
    placed in it (None: never)."""

    results: list[FrameResult] = field(default_factory=list)
    frame_ms: list[float] = field(default_factory=list)
    decode_ms: list[float] = field(default_factory=list)
    startup_s: float = float("nan")
    warm_up_s: float = float("nan")
    num_keyframes: int = 0
    mapping_worker_ms: list[float] = field(default_factory=list)
    stopped_at: int | None = None  # index of the first frame not processed, if interrupted
    config: Config | None = None
    corrections: list[Correction] = field(default_factory=list)
    map_keyframes: int | None = None
    map_bytes: int | None = None
    map_full_at: int | None = None
    online_poses: np.ndarray | None = None
    loops: dict | None = None
    map_file: str | None = None
    found_in_loaded: int | None = None

    def summary_fields(self) -> dict:
        """Timing statistics and the per-frame record (``per_frame_record``) for
        ``summarise``. The first frame carries the start-up (``startup_s``); the frame
        statistics cover every frame after it (keyframes and searches included; image
        decoding excluded): ms_per_frame, its parts, select_ms (keyframes), mapping_ms (the
        tracker's time on the local map where it spent any: inline the window step, beside
        tracking the hand-over and any wait) and mapping_worker_ms (the window's step per
        keyframe on its worker)."""
        warm = np.asarray(self.frame_ms[1:], np.float64)
        out = {
            "startup_s": self.startup_s,
            "warm_up_s": self.warm_up_s,
            "ms_per_frame": _describe(warm),
            "preprocess_ms": _describe([r.preprocess_ms for r in self.results[1:]]),
            "solve_wait_ms": _describe([r.solve_ms for r in self.results[1:]]),
            "decode_ms": _describe(self.decode_ms[1:]),
            "select_ms": _describe([r.select_ms for r in self.results[1:]
                                    if r.select_ms is not None]),
            "mapping_ms": _describe([r.mapping_ms for r in self.results[1:]
                                     if r.mapping_ms is not None]),
            "mapping_worker_ms": _describe(self.mapping_worker_ms[1:]),
            "edges_used_mean": float(np.mean([r.edges_used for r in self.results[1:]]))
            if len(self.results) > 1 else float("nan"),
        }
        if self.stopped_at is not None:
            out["stopped_at_frame"] = self.stopped_at
        if self.map_keyframes is not None:
            placed = [r.placed for r in self.results if r.placed]
            out["map"] = {"keyframes": self.map_keyframes, "megabytes": self.map_bytes / 1e6,
                          "full_at_keyframe": self.map_full_at,
                          "found_again": sum(p.startswith("found again") for p in placed),
                          "revisits": sum(p.startswith("revisit") for p in placed),
                          "frames_moved": len({i for c in self.corrections
                                               for i in range(c.first, c.last + 1)})}
            if self.map_file is not None:
                out["map"]["loaded"] = self.map_file
                out["map"]["found_in_loaded"] = self.found_in_loaded
            if self.loops is not None:
                out["map"]["loops"] = {
                    "closed": len(self.loops["closed"]),
                    "rejected": len(self.loops["rejected"]),
                    "pose_graph_ms": _describe([s["ms"] for s in self.loops["solves"]]),
                    "largest_graph_keyframes": max((s["keyframes"]
                                                    for s in self.loops["solves"]), default=0)}
        out["per_frame"] = [per_frame_record(r) for r in self.results]
        return out


def per_frame_record(result: FrameResult) -> dict:
    """One frame of the ``--stats`` JSON's ``per_frame`` list (one per trajectory line, in
    order): timestamp (s), state (OK / WEAK / LOST), reason (None when OK), level-0 inliers,
    keyframe (why the frame became one, or None) and the keyframe edges it was tracked with."""
    return {"timestamp": result.timestamp, "state": result.state, "reason": result.reason,
            "inliers": result.inliers, "keyframe": result.keyframe,
            "edges_used": result.edges_used}


def initial_pose(seq: Source) -> np.ndarray:
    """T_world_cam of the first frame: the nearest ground-truth pose, else identity."""
    if len(seq) == 0 or seq.groundtruth is None or len(seq.timestamps) == 0:
        return np.eye(4)
    pose7 = groundtruth_pose_at(seq, float(seq.timestamps[0]))
    return np.eye(4) if pose7 is None else poses7_to_matrices(np.asarray(pose7)[None])[0]


def run_sequence(
    seq: Source,
    config: Config,
    *,
    out: str | Path | None = None,
    progress: bool = True,
    max_frames: int | None = None,
    params: Params | None = None,
    started: float | None = None,
    on_frame: Callable[[FrameResult, np.ndarray, Frame, Odometry], None] | None = None,
    save_map: str | Path | None = None,
    map_file: str | Path | None = None,
) -> RunResult:
    """Track every associated frame of ``seq``; write the TUM trajectory to ``out`` line by
    line (flushed; renamed into place at the end). Returns the per-frame results.
    ``params``: learnt parameters for the tracker (``odometry.Odometry``; None: the config's).
    ``started``: the ``time.perf_counter()`` the start-up is counted from (None: this call;
    the CLI passes its own start). ``on_frame(result, rgb, frame, odometry)`` is called
    after each frame is concluded, with its rectified rgb and pre-processed ``Frame`` and
    the tracker in its state after the frame (e.g. ``viz.recording.RerunRecording``).
    ``save_map``: where the keyframe map goes at the end, once the trajectory is written
    (``Odometry.save_map``); ``map_file``: a saved map the run starts in (``Odometry``'s:
    refused before any frame where it does not fit). ValueError when ``max_frames`` is not
    positive (None: every frame) or ``save_map`` is given with the map off."""
    if max_frames is not None and max_frames < 1:
        raise ValueError(f"max_frames must be at least 1 (None: every frame), got {max_frames}")
    if save_map is not None and not config.map:
        raise ValueError("save_map needs the keyframe map: Config.map is off")
    started = time.perf_counter() if started is None else started
    odo = Odometry(config, seq.intrinsics, initial_pose=initial_pose(seq), params=params,
                   readout_s=camera_readout(seq), map_file=map_file)
    n = len(seq) if max_frames is None else min(len(seq), max_frames)
    run = RunResult(config=config, map_file=None if map_file is None else str(map_file))
    writer = TrajectoryWriter(out) if out is not None else None
    if progress:
        _announce_compile(seq, config, params)
    bar = _Bar(seq.name, n, odo, progress)
    try:
        _track_all(seq, odo, n, run, writer, started, on_frame, bar.advance)
        odo.finish()  # a loop found at the end still corrects the trajectory written
    except BaseException as exc:
        run.stopped_at = len(run.results)
        kept = ""
        if writer is not None:
            writer.abort()  # keeps the lines written so far in the .part file
            kept = f"; the {writer.count} poses done are in {writer.part_path}"
        exc.add_note(f"{seq.name}: the run stopped at frame {run.stopped_at} of {n}{kept}")
        exc.run_result = run  # type: ignore[attr-defined]  # the partial RunResult
        raise
    finally:
        bar.close()
        odo.close()
        run.num_keyframes = odo.num_keyframes
        run.mapping_worker_ms = odo.mapping_worker_ms
        _take_map(run, odo)
    if writer is not None:
        if run.corrections:
            writer.rewrite(run.timestamps, matrices_to_poses7(run.poses))
        writer.close()
    if save_map is not None:  # after the trajectory is safe; every keyframe described
        odo.save_map(save_map)
    return run


class _Bar:
    """The run's progress bar, made after the first frame (its rate and ETA leave the
    compiling out), with the keyframe count."""

    def __init__(self, name: str, total: int, odo: Odometry, shown: bool) -> None:
        self.name, self.total, self.odo, self.shown = name, total, odo, shown
        self.bar = None

    def advance(self) -> None:
        """One more frame done."""
        if self.bar is None:
            self.bar = tqdm(total=self.total, initial=1, desc=self.name, unit="frame",
                            disable=not self.shown, leave=False)
        else:
            self.bar.update(1)
        self.bar.set_postfix(kf=self.odo.num_keyframes, refresh=False)

    def close(self) -> None:
        """Take the bar off the screen."""
        if self.bar is not None:
            self.bar.close()


def _track_all(seq: Source, odo: Odometry, n: int, run: RunResult,
               writer: TrajectoryWriter | None, started: float, on_frame, advance) -> None:
    """Track frames 0 to ``n`` - 1 of ``seq`` pipelined (module doc), recording each in
    ``run`` and ``writer`` as it is concluded."""
    config = odo.config
    ready = None  # (frame, timestamp, preprocess ms, rgb) decoded and pre-processed, not submitted
    lags = depth_lags(seq)  # each depth image's time after its colour image's (None: 0)
    t_prev = time.perf_counter()
    for i in range(n + 1):
        decode_s = 0.0
        if i < n:
            t0 = time.perf_counter()
            rgb, raw_depth = seq.decode_frame(i)
            decode_s = time.perf_counter() - t0
            run.decode_ms.append(decode_s * 1e3)
        # submit after decoding, so that the solve overlaps preprocessing only
        pending = odo.submit(*ready[:2], preprocess_ms=ready[2]) if ready else None
        shown, job, pre_s = (ready[3], ready[0]) if ready else None, None, 0.0
        if i < n:
            t1 = time.perf_counter()
            rgb, depth = seq.rectify_frame(rgb, raw_depth)
            job = start_preprocess(rgb, depth, config)
            pre_s = time.perf_counter() - t1
        result = odo.complete(pending) if pending is not None else None  # meanwhile: DT
        if job is not None:
            t2 = time.perf_counter()
            frame = job.finish()
            if lags is not None:
                frame = dataclasses.replace(frame, depth_lag_s=float(lags[i]))
            ready = (frame, float(seq.timestamps[i]),
                     (pre_s + time.perf_counter() - t2) * 1e3, rgb)
        if result is not None:
            _record(run, result, writer)
            now = time.perf_counter()
            run.frame_ms.append((now - t_prev - decode_s) * 1e3)
            if len(run.results) == 1:
                run.startup_s = now - started
                run.warm_up_s = (odo.warm_up_ms or math.nan) * 1e-3
            if on_frame is not None:  # not counted in the frame times
                on_frame(result, shown[0], shown[1], odo)
            t_prev = time.perf_counter() if on_frame is not None else now
            advance()


def _take_map(run: RunResult, odo: Odometry) -> None:
    """The map's statistics, and the poses as they are now (``Odometry.poses``: moved by the
    corrections) in the run's results, the online ones kept apart."""
    kmap = odo.keyframe_map
    if kmap is not None:
        run.map_keyframes, run.map_bytes, run.map_full_at = len(kmap), kmap.nbytes, kmap.full_at
    run.corrections = list(odo.corrections)
    run.loops = odo.loop_stats
    run.found_in_loaded = odo.found_in_loaded
    if not run.corrections:
        return
    run.online_poses = run.poses
    poses = odo.poses()
    run.results = [dataclasses.replace(r, pose=pose) for r, pose in
                   zip(run.results, poses, strict=False)] + run.results[len(poses):]


#: (image size, configuration, learnt params or not) whose compiling this process announced
_announced: set[tuple] = set()


def _announce_compile(seq: Source, config: Config, params: Params | None) -> None:
    """One line on stderr, before the first frame of the first run of a configuration and
    image size in this process: the first frame compiles the tracker's programs (or loads
    them from the on-disk cache), once per configuration and image size."""
    key = (getattr(seq, "width", None), getattr(seq, "height", None), config,
           params is None)
    if key in _announced:
        return
    _announced.add(key)
    folder = enable_cache()
    where = (f"or loads them from {folder} (1-3 s) where a run kept them" if folder is not None
             else "(the program cache is off: EDGEVO_CACHE_DIR is empty)")
    print(f"{seq.name}: the first frame compiles the tracker's programs for this "
          f"configuration and image size, once (15-40 s on a quiet 2-core CPU), {where}",
          file=sys.stderr, flush=True)
    changed = structural_fields(config)
    if changed:
        sets = ", ".join(f"{name}={getattr(config, name)}" for name in changed)
        more = (" (with selection=all, a keyframe whose edges need a slot count not met "
                "before, of 1024, 2048, 4096, ..., compiles its solves when it is made, "
                "10-20 s)"
                if config.selection == "all" else "")
        print(f"{seq.name}: {sets} changes the programs' structure: they compile for it even "
              f"where the defaults' are kept{more}", file=sys.stderr, flush=True)


def track_in_chunks(odo: Odometry, frames: list[Frame], timestamps: list[float], *,
                    size: int) -> list[FrameResult]:
    """Track pre-processed frames with the scan tracker (``chunk.track_chunk``): chunks of
    ``size`` frames (the last one padded by repetition) are tracked on the device against
    the current keyframe in one call each; the host then concludes them in order and, at the
    first frame that changes the state (a new keyframe, a loss, a recovery), drops the rest
    of the chunk and tracks it again from there. Gives the trajectory of
    ``odo.track_frame`` called frame by frame."""
    if len(frames) != len(timestamps):
        raise ValueError(f"{len(frames)} frames but {len(timestamps)} timestamps")
    results: list[FrameResult] = []
    i = 0
    while i < len(frames):
        if not odo.has_keyframe:
            results.append(odo.track_frame(frames[i], timestamps[i]))
            i += 1
            continue
        todo = frames[i:i + size]
        t_submit = time.perf_counter()
        out = to_host(dispatch_chunk(odo, todo, size, timestamps[i:i + size]))
        done = conclude_chunk(odo, todo, timestamps[i:i + size], out, t_submit=t_submit)
        results += done
        i += len(done)
    return results


def conclude_chunk(odo: Odometry, frames: list[Frame], timestamps: list[float], out, *,
                   t_submit: float | None = None) -> list[FrameResult]:
    """Conclude the solved frames of a chunk in order (``out``: the scan's host arrays, C
    leading, C >= len(frames)) with ``odo.accept``, up to and including the first frame that
    changes the state (a new keyframe, a loss, a recovery): the rest of the chunk was
    solved against a state that no longer holds. Returns the concluded frames' results."""
    results: list[FrameResult] = []
    for j, (frame, timestamp) in enumerate(zip(frames, timestamps, strict=True)):
        res = jax.tree.map(lambda a, j=j: a[j], out)
        result, plain = odo.accept(frame, timestamp, res, t_submit=t_submit)
        results.append(result)
        if not plain:
            break
    return results


def dispatch_chunk(odo: Odometry, frames: list[Frame], size: int,
                   timestamps: list[float]) -> TrackResult:
    """Dispatch the scan over ``frames`` at ``timestamps`` (at most ``size``, padded to it by
    repeating the last) against ``odo``'s current keyframe; returns device arrays (C
    leading)."""
    if not 0 < len(frames) <= size or len(timestamps) != len(frames):
        raise ValueError(f"a chunk takes 1 to {size} frames and their timestamps, got "
                         f"{len(frames)} frames and {len(timestamps)} timestamps")
    rates = odo.shutter_rates(timestamps, frames[0].shape[0])
    if rates is not None:  # padding frames repeat the last one's rate
        rates = np.concatenate([rates, np.repeat(rates[-1:], size - len(frames))])
    frames = list(frames) + [frames[-1]] * (size - len(frames))
    dist = tuple(aligned_stack([f.dist[lv] for f in frames])
                 for lv in range(len(frames[0].dist)))
    ng = stack_edge_maps([f.edge_map for f in frames])
    kf, A, B, intr, knobs = odo.solve_inputs()
    return track_chunk_jit(kf, dist, ng, A, B, intr, knobs, rates, config=odo.structure)


def _record(run: RunResult, result: FrameResult, writer: TrajectoryWriter | None) -> None:
    run.results.append(result)
    if writer is not None:
        writer.write(result.timestamp, matrices_to_poses7(result.pose[None])[0])


def summarise(run: FrameResults, seq: Source) -> dict:
    """A run's statistics (the CLI's ``--stats`` JSON; one row of ``edgevo batch``): counts
    of frames, keyframes, OK, lost and weak frames and their reasons, the second opinion's
    (``second_opinion``: frames checked, and those it made WEAK), the run's own fields
    (``RunResult``: timings; ``BatchRun``: its configuration's index), the configuration,
    and against the sequence's ground truth when it has one: ATE / RPE and the frames
    called OK while silently wrong (``silently_wrong``: indices; ``truth.silently_wrong``)."""
    results = run.results
    stats: dict = {
        "sequence": seq.name,
        "frames": len(results),
        "keyframes": run.num_keyframes,
        "ok": sum(r.state == OK for r in results),
        "lost": sum(r.state == LOST for r in results),
        "weak": sum(r.state == WEAK for r in results),
        "flags": dict(Counter(f"{r.state}: {r.reason}" for r in results if r.state != OK)),
        "second_opinion": {
            "checked": sum(r.depth_agreement is not None for r in results),
            "weak": sum(r.state == WEAK and r.reason is not None
                        and r.reason.startswith(DEPTH_DISAGREES) for r in results)},
        **run.summary_fields(),
        "config": dataclasses.asdict(run.config) if run.config is not None else None,
    }
    if seq.groundtruth is not None and len(run.results) < 3:
        stats["ground_truth_note"] = f"only {len(run.results)} frames tracked, ATE needs 3"
    if seq.groundtruth is not None and len(run.results) >= 3:
        gt_t, gt_p = seq.groundtruth
        est = matrices_to_poses7(run.poses)
        try:
            stats["ate_rmse_m"] = ate((gt_t, gt_p), (run.timestamps, est))["rmse"]
            r = rpe_per_second((gt_t, gt_p), (run.timestamps, est))
            stats["rpe_rmse_m_per_s"] = r["trans_rmse_m_per_s"]
            stats["rpe_rmse_deg_per_s"] = r["rot_rmse_deg_per_s"]
            stats["silently_wrong"] = silently_wrong(
                run.poses, [r.state for r in results], groundtruth_at(seq, run.timestamps))
            stats["silently_wrong_bounds"] = {"m": DIVERGED_TRANS_M, "deg": DIVERGED_ROT_DEG}
        except ValueError as err:  # e.g. no timestamps in common with the ground truth
            stats["ground_truth_note"] = str(err)
    return stats


def _describe(values) -> dict:
    v = np.asarray(values, np.float64)
    if v.size == 0:
        return {"median": float("nan"), "mean": float("nan"), "p90": float("nan")}
    return {"median": float(np.median(v)), "mean": float(v.mean()),
            "p90": float(np.percentile(v, 90))}
