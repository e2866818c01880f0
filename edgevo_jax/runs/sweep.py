"""Sweeps: many runs (sources x frame steps x seeds x a grid of ``Config`` fields) from one
TOML file, written run by run to an output folder, resumable, split over processes.

A sweep file::

    sources = ["data/rgbd_dataset_freiburg3_teddy",            # anything `edgevo run` takes
               {path = "walk.bag", groundtruth = "walk_gt.txt", camera = "freiburg1"}]
    frame_steps = [1, 2]      # keep every k-th frame (default [1])
    seeds = [0, 1]            # Config.seed of the runs (default: the base's seed)
    max_frames = 200          # frames per run (optional)
    chunk = 2                 # frames per run per device call (optional)

    [base]                    # Config fields of every run (optional)
    mapping = false

    [grid]                    # every combination of these values (optional)
    num_edges = [256, 512]
    huber_delta = [[1, 1, 1], [2, 2, 2]]

Paths are relative to the sweep file's folder. A source is a string (its path) or a table
with ``path`` and any of ``camera`` (a preset name or a calibration file), ``intrinsics``
([fx, fy, cx, cy]), ``depth_factor``, ``rgb_topic``, ``depth_topic``, ``info_topic`` and
``groundtruth`` (``datasets.source.open_source``'s arguments). A live camera cannot be swept
(every run must read the same frames): record it to a bag first.

Runs are ordered source, frame step, seed, setting (the grid's last field varying fastest)
and named by a stable key: the source folder's name, step, seed and a digest of the source
as written, the step, the run's whole ``Config`` and ``max_frames``. In the output folder:

- ``runs/<key>.txt``: each finished run's trajectory (TUM format), written at once;
- ``log/process-<i>.jsonl``: one JSON line per finished run of process i, appended with one
  write and fsync'd after its trajectory; a run whose line is there is never run again (a
  trailing partial line, from a kill, is not counted and is cut before the next append);
- at the end, by process 0: ``runs.jsonl`` (every run's line in sweep order), ``summary.md``,
  ``summary.csv`` (per run), ``summary_settings.csv`` (per frame step and setting, over
  sources and seeds) and ``summary.png`` (with matplotlib). The summary is a function of the
  runs' lines alone, so a resumed sweep ends with the summary of an uninterrupted one; the
  ``ms_per_frame`` columns (last in each table) are wall-clock times and differ between
  sweeps.

The file is read and checked by ``load_sweep`` (``pipeline.sweep_file``: the ``Sweep``, its
runs and their keys); this module opens its sources, runs them and writes the summary.

Within a process, runs that share an image size and a number of pyramid levels are tracked in
one ``batch.evaluate`` (vmapped lanes sharing each sequence's decoding and the compiled
programs). Under ``jax.distributed`` process i of N takes the runs i, i + N, ... of the
sweep (a function of the sweep file alone), skips those already written, and then waits for
the others' lines in the (shared) output folder; process 0 writes the summary.
"""

from __future__ import annotations

import csv
import dataclasses
import hashlib
import io
import itertools
import json
import math
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..datasets.source import Source, SourceError
from ..io import json_safe, matrices_to_poses7, write_trajectory
from .batch import BatchRun, evaluate
from .processes import failure_check, note_failure
from .run import summarise
from .sweep_file import (
    SOURCE_KEYS,
    SWEEP_KEYS,
    Sweep,
    SweepError,
    SweepRun,
    SweepSource,
    load_sweep,
)

__all__ = [
    "RUN_COLUMNS",
    "SETTING_COLUMNS",
    "SOURCE_KEYS",
    "SWEEP_KEYS",
    "Sweep",
    "SweepError",
    "SweepProgress",
    "SweepRun",
    "SweepSource",
    "load_sweep",
    "open_sources",
    "read_records",
    "run_record",
    "run_share",
    "run_sweep",
    "summary_markdown",
    "summary_tables",
    "wait_for_runs",
    "write_summary",
]


def open_sources(sweep: Sweep, needed: set[tuple[int, int]] | None = None
                 ) -> dict[tuple[int, int], Source]:
    """The sources of the (source index, frame step) pairs ``needed`` (default: all), opened
    with ``open_source``; SweepError naming the source for one that cannot be opened."""
    from ..camera import Intrinsics
    from ..datasets.source import open_source
    from ..datasets.tum import read_calibration

    needed = needed if needed is not None else {
        (s, k) for s in range(len(sweep.sources)) for k in sweep.frame_steps}
    out: dict[tuple[int, int], Source] = {}
    for s, step in sorted(needed):
        source = sweep.sources[s]
        options = dict(source.options)
        try:
            camera = options.get("camera")
            if isinstance(camera, str) and Path(camera).is_file():
                options["camera"] = read_calibration(camera)
            if "intrinsics" in options:
                options["intrinsics"] = Intrinsics(*options["intrinsics"]).validate()
            out[s, step] = open_source(source.path, frame_step=step, **options)
        except SourceError as err:
            raise SweepError(f"{sweep.path}: source {source.path}: {err}") from None
        except (ValueError, TypeError, OSError) as err:
            raise SweepError(f"{sweep.path}: source {source.path}: {err}") from None
    return out


def read_records(out: str | os.PathLike[str]) -> dict[str, dict]:
    """The finished runs' lines in ``out``'s logs by key: whole lines (ending in a newline)
    that parse and whose trajectory file exists; the first line of a key counts."""
    records: dict[str, dict] = {}
    for log in sorted((Path(out) / "log").glob("process-*.jsonl")):
        for line in log.read_bytes().split(b"\n")[:-1]:  # the last piece is partial or empty
            try:
                record = json.loads(line)
            except ValueError:
                continue
            if (isinstance(record, dict) and isinstance(record.get("key"), str)
                    and (Path(out) / "runs" / f"{record['key']}.txt").is_file()):
                records.setdefault(record["key"], record)
    return records


class _Log:
    """Process i's log: one line appended per run with a single write, then fsync; a partial
    last line (the process was killed mid-write) is cut first."""

    def __init__(self, out: Path, process: int) -> None:
        self.path = out / "log" / f"process-{process}.jsonl"
        self.path.parent.mkdir(parents=True, exist_ok=True)
        if self.path.exists():
            data = self.path.read_bytes()
            if data and not data.endswith(b"\n"):
                with self.path.open("r+b") as f:
                    f.truncate(data.rfind(b"\n") + 1)

    def append(self, record: dict) -> None:
        line = (json.dumps(json_safe(record), sort_keys=True) + "\n").encode()
        fd = os.open(self.path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
        try:
            os.write(fd, line)
            os.fsync(fd)
        finally:
            os.close(fd)


def run_record(sweep: Sweep, run: SweepRun, result: BatchRun, seq: Source,
               process: int) -> dict:
    """A finished run's JSON line: its key, source, step, seed and setting, ``summarise``'s
    counts, ATE and RPE (not the per-frame lists), the digest of its poses (float64
    T_world_cam matrices: equal digests are equal trajectories to the bit) and its batch's
    time per frame."""
    stats = summarise(result, seq)
    return {
        "key": run.key, "source": sweep.sources[run.source].path,
        "sequence": sweep.sources[run.source].label, "frame_step": run.frame_step,
        "seed": run.seed, "setting": sweep.setting_label(run.setting),
        "frames": stats["frames"], "keyframes": stats["keyframes"], "weak": stats["weak"],
        "lost": stats["lost"], "flags": stats["flags"],
        "ate_rmse_m": stats.get("ate_rmse_m"),
        "rpe_rmse_m_per_s": stats.get("rpe_rmse_m_per_s"),
        "rpe_rmse_deg_per_s": stats.get("rpe_rmse_deg_per_s"),
        "ground_truth_note": stats.get("ground_truth_note"),
        "poses_sha256": hashlib.sha256(np.ascontiguousarray(result.poses, np.float64)
                                       .tobytes()).hexdigest(),
        "trajectory": f"runs/{run.key}.txt", "ms_per_frame": result.batch_ms_per_frame,
        "process": process, "config": dataclasses.asdict(run.config),
    }


@dataclass
class SweepProgress:
    """What one process did: the runs it owns, those it found written and those it ran, and
    its wall time (s)."""

    owned: int
    skipped: int
    ran: int
    wall_s: float


def run_share(sweep: Sweep, out: str | os.PathLike[str], *, process: int = 0,
              processes: int = 1, progress: bool = True,
              on_done: Callable[[dict], None] | None = None) -> SweepProgress:
    """Track this process's share of the sweep (runs ``process::processes``) that is not yet
    written in ``out``, each batch of runs sharing an image size and pyramid levels in one
    ``batch.evaluate``; write each run (trajectory, then its log line) as soon as it
    finishes and call ``on_done(record)``."""
    t0 = time.perf_counter()
    out = Path(out)
    (out / "runs").mkdir(parents=True, exist_ok=True)
    done = read_records(out)
    owned = sweep.runs()[process::processes]
    todo = [r for r in owned if r.key not in done]
    log = _Log(out, process)
    seqs = open_sources(sweep, {(r.source, r.frame_step) for r in todo})
    groups: dict[tuple, list[SweepRun]] = {}
    for r in todo:
        seq = seqs[r.source, r.frame_step]
        groups.setdefault((seq.height, seq.width, r.config.num_levels), []).append(r)
    for members in groups.values():
        order = list(dict.fromkeys((r.source, r.frame_step) for r in members))
        batch_seqs = [seqs[k] for k in order]

        def finished(result: BatchRun, members=members, batch_seqs=batch_seqs,
                     order=order) -> None:
            run = members[result.config_index]
            seq = batch_seqs[order.index((run.source, run.frame_step))]
            write_trajectory(out / "runs" / f"{run.key}.txt", result.timestamps,
                             matrices_to_poses7(result.poses))
            record = run_record(sweep, run, result, seq, process)
            log.append(record)
            if on_done is not None:
                on_done(record)

        evaluate(batch_seqs, [r.config for r in members],
                 runs=[(order.index((r.source, r.frame_step)), j)
                       for j, r in enumerate(members)],
                 chunk=sweep.chunk, max_frames=sweep.max_frames, progress=progress,
                 on_run=finished)
    return SweepProgress(len(owned), len(owned) - len(todo), len(todo),
                         time.perf_counter() - t0)


def wait_for_runs(sweep: Sweep, out: str | os.PathLike[str], *,
                  check: Callable[[], None] | None = None, poll_s: float = 0.5,
                  timeout_s: float | None = None) -> dict[str, dict]:
    """Wait until every run of the sweep has its line in ``out``; returns them by key.
    ``check()`` is called at each poll (it raises to give up, e.g. when a process died)."""
    keys = [r.key for r in sweep.runs()]
    start = time.monotonic()
    while True:
        records = read_records(out)
        missing = [k for k in keys if k not in records]
        if not missing:
            return records
        if check is not None:
            check()
        if timeout_s is not None and time.monotonic() - start > timeout_s:
            raise TimeoutError(f"{len(missing)} runs of the sweep were not written within "
                               f"{timeout_s:g} s, e.g. {missing[0]}")
        time.sleep(poll_s)


RUN_COLUMNS = ("key", "sequence", "frame_step", "seed", "setting", "frames", "keyframes",
               "weak", "lost", "ate_rmse_m", "rpe_rmse_m_per_s", "rpe_rmse_deg_per_s",
               "ms_per_frame")
SETTING_COLUMNS = ("frame_step", "setting", "runs", "frames", "ate_rmse_m_mean",
                   "ate_rmse_m_max", "rpe_rmse_m_per_s_mean", "rpe_rmse_deg_per_s_mean",
                   "weak", "lost", "ms_per_frame_mean")


def summary_tables(sweep: Sweep, records: dict[str, dict]) -> tuple[list[dict], list[dict]]:
    """The per-run rows (sweep order) and the per-setting rows (frame step, then setting;
    means over sources and seeds, counts summed) of the summary; every run must have its
    record. ATE / RPE that could not be computed are None and left out of the means."""
    runs = sweep.runs()
    missing = [r.key for r in runs if r.key not in records]
    if missing:
        raise ValueError(f"{len(missing)} runs of {sweep.path} are not written yet, e.g. "
                         f"{missing[0]}")
    rows = [{c: records[r.key].get(c) for c in RUN_COLUMNS} for r in runs]
    settings = []
    for step, k in itertools.product(sweep.frame_steps, range(len(sweep.settings))):
        group = [records[r.key] for r in runs if r.frame_step == step and r.setting == k]

        def mean(col: str, group=group) -> float | None:
            v = [g[col] for g in group if g.get(col) is not None]
            return float(np.mean(v)) if v else None

        ates = [g["ate_rmse_m"] for g in group if g.get("ate_rmse_m") is not None]
        settings.append({
            "frame_step": step, "setting": sweep.setting_label(k), "runs": len(group),
            "frames": sum(g["frames"] for g in group), "ate_rmse_m_mean": mean("ate_rmse_m"),
            "ate_rmse_m_max": max(ates) if ates else None,
            "rpe_rmse_m_per_s_mean": mean("rpe_rmse_m_per_s"),
            "rpe_rmse_deg_per_s_mean": mean("rpe_rmse_deg_per_s"),
            "weak": sum(g["weak"] for g in group), "lost": sum(g["lost"] for g in group),
            "ms_per_frame_mean": mean("ms_per_frame")})
    return rows, settings


def _csv(rows: list[dict], columns: Sequence[str]) -> str:
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(columns)
    for row in rows:
        writer.writerow(["" if row[c] is None else repr(row[c]) if isinstance(row[c], float)
                         else row[c] for c in columns])
    return buf.getvalue()


def _num(value: float | None, scale: float = 1.0, digits: int = 2) -> str:
    return "n/a" if value is None or not math.isfinite(value) else f"{value * scale:.{digits}f}"


def summary_markdown(sweep: Sweep, rows: list[dict], settings: list[dict]) -> str:
    """The summary as markdown: per setting over sources and seeds, then per run."""
    lines = [
        f"# Sweep {sweep.path.name}: {len(rows)} runs", "",
        f"{len(sweep.sources)} sources x {len(sweep.frame_steps)} frame steps x "
        f"{len(sweep.seeds)} seeds x {len(sweep.settings)} settings"
        + (f", at most {sweep.max_frames} frames per run" if sweep.max_frames else "")
        + ". ATE and RPE: RMSE (mm, mm/s, deg/s); weak / lost: frames. ms/frame: the batch's "
        "wall time shared over its runs (compilation included), the one column that depends "
        "on the machine and on how the sweep was split and resumed.", "",
        "## Per setting (over sources and seeds)", "",
        "| step | setting | runs | ATE mean | ATE max | RPE mm/s | RPE deg/s | weak | lost "
        "| ms/frame |",
        "|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for s in settings:
        lines.append(
            f"| {s['frame_step']} | {s['setting']} | {s['runs']} | "
            f"{_num(s['ate_rmse_m_mean'], 1e3)} | {_num(s['ate_rmse_m_max'], 1e3)} | "
            f"{_num(s['rpe_rmse_m_per_s_mean'], 1e3)} | {_num(s['rpe_rmse_deg_per_s_mean'])} "
            f"| {s['weak']} | {s['lost']} | {_num(s['ms_per_frame_mean'], 1, 1)} |")
    lines += ["", "## Per run", "",
              "| sequence | step | seed | setting | frames | kf | ATE | RPE mm/s | RPE deg/s "
              "| weak | lost | ms/frame |",
              "|---|---:|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(
            f"| {r['sequence']} | {r['frame_step']} | {r['seed']} | {r['setting']} | "
            f"{r['frames']} | {r['keyframes']} | {_num(r['ate_rmse_m'], 1e3)} | "
            f"{_num(r['rpe_rmse_m_per_s'], 1e3)} | {_num(r['rpe_rmse_deg_per_s'])} | "
            f"{r['weak']} | {r['lost']} | {_num(r['ms_per_frame'], 1, 1)} |")
    return "\n".join(lines) + "\n"


def write_summary(sweep: Sweep, out: str | os.PathLike[str],
                  records: dict[str, dict] | None = None, *,
                  plot: Callable[[Sweep, list[dict], Path], Path] | None = None) -> list[Path]:
    """Write ``runs.jsonl``, ``summary.md``, ``summary.csv``, ``summary_settings.csv`` and,
    with ``plot`` (``viz.sweep.plot_sweep``, which needs matplotlib), ``summary.png`` from
    the runs' records (default: read from ``out``). Returns the files written."""
    out = Path(out)
    records = read_records(out) if records is None else records
    rows, settings = summary_tables(sweep, records)
    texts = {
        "runs.jsonl": "".join(json.dumps(json_safe(records[r.key]), sort_keys=True) + "\n"
                              for r in sweep.runs()),
        "summary.md": summary_markdown(sweep, rows, settings),
        "summary.csv": _csv(rows, RUN_COLUMNS),
        "summary_settings.csv": _csv(settings, SETTING_COLUMNS),
    }
    written = []
    for name, text in texts.items():
        tmp = out / f".{name}.tmp"
        tmp.write_text(text)
        os.replace(tmp, out / name)
        written.append(out / name)
    if plot is not None:
        try:
            written.append(plot(sweep, rows, out / "summary.png"))
        except ImportError:
            pass  # the plot needs matplotlib (pip install edgevo_jax[viz])
    return written


def run_sweep(sweep: Sweep, out: str | os.PathLike[str], *, progress: bool = True,
              check: Callable[[], None] | None = None,
              on_done: Callable[[dict], None] | None = None,
              plot: Callable[[Sweep, list[dict], Path], Path] | None = None,
              ) -> tuple[SweepProgress, dict]:
    """This process's part of a sweep: its share (``run_share``, by ``jax.process_index()``
    of ``jax.process_count()``), then wait for every run (``wait_for_runs`` with ``check``),
    then, under ``jax.distributed``, meet the other processes; process 0 then writes the
    summary (``write_summary``, with ``plot``). Returns this process's progress and every
    run's record."""
    import jax

    index, count = jax.process_index(), jax.process_count()
    note_failure(out, index, None)
    if count > 1:  # no process reads a note left by an earlier sweep
        from jax.experimental import multihost_utils

        multihost_utils.sync_global_devices("edgevo sweep: started")
    try:
        done = run_share(sweep, out, process=index, processes=count, progress=progress,
                         on_done=on_done)
        checks = [c for c in (check, failure_check(out) if count > 1 else None) if c]
        records = wait_for_runs(sweep, out, check=lambda: [c() for c in checks])
    except Exception as err:
        if count > 1:
            note_failure(out, index, err)
        raise
    if count > 1:
        multihost_utils.sync_global_devices("edgevo sweep: every run written")
    if index == 0:
        write_summary(sweep, out, records, plot=plot)
    return done, records
