"""Side-by-side benchmark of edgevo_jax and peer RGB-D odometry methods on TUM RGB-D clips.

Usage::

    python scripts/bench.py [SEQ_DIR ...] [--max-frames N] [--methods m1,m2,...]
                            [--edgevo NAME=key=value;key=value ...] [--pingpong N]
                            [--out-json bench.json] [--out-md bench.md]

Methods:

- ``edgevo`` (the default ``Config``), ``edgevo_all`` (``selection=all``), ``edgevo_nomap``
  (``mapping=false``: no local mapping) and any ``--edgevo`` variant, e.g.
  ``--edgevo "e256=num_edges=256"``: ``edgevo_jax.runs.run.run_sequence`` (keyframe-based,
  pipelined: the solve of frame i overlaps the preprocessing of frame i+1).
- ``cv2_rgb``, ``cv2_depth``, ``cv2_rgbd`` (OpenCV 5 ``cv2.Odometry``), ``o3d_color``,
  ``o3d_hybrid`` (Open3D ``compute_rgbd_odometry``): the peers of ``edgevo_jax.peers``
  (their calls and settings are described there), frame to frame from edgevo's first pose
  (``runner.initial_pose``: T_world_cam of frame 0 from the nearest ground-truth pose); a
  pair that fails counts as a lost frame and reuses the previous motion.

What is measured, per method and sequence, each in its own child process (``--one``), so
that the peak RSS is the method's own and a crashing peer cannot take the benchmark down:

- ATE RMSE (m; TUM's ``evaluate_ate``: rigid Horn alignment) and RPE (translation RMSE over
  1 s, m/s; null when the processed clip spans less than 1 s), from ``edgevo_jax.metrics``.
- Per-frame wall time (``time.perf_counter``), PNG decoding excluded and everything else
  included: for peers from ``seq.decode_frame``'s arrays to the pose (undistortion and depth
  scaling by ``seq.rectify_frame``, gray conversion, the library's frame objects, preparation
  and solve); for edgevo ``RunResult.frame_ms``, which has the same boundary (decoding
  excluded, ``rectify_frame`` and preprocessing included). Warm statistics skip the first
  two frames of every method (frame 0 sets up; frame 1 is the first pair).
  ``first_frame_ms``: edgevo's ``startup_s`` (to the first pose, with every program compiled
  before it: cold XLA compilation in a fresh process, no persistent cache), for peers the
  time of their first pair.
- ``compiled_mean_ms`` / ``compiled_median_ms`` come from a second
  run of the same frames in the same process, every program compiled, and
  ``repeat_identical`` says whether it gave the first run's poses exactly. Beside each
  median: the p90, the mean and the max (``warm_max_ms``, ``compiled_p90_ms``,
  ``compiled_max_ms``): users feel the mean and the worst frame, not the median.
- ``wall_s``: end to end, the method's whole run in its child process, from the tracker's
  construction to the last pose, PNG decoding included (for edgevo the first run, with its
  compilation; ``compiled_wall_s`` the second).
- ``peak_rss_mib``: ``ru_maxrss`` of the child at its end (edgevo: after its first run, before
  the compiled one). Every child imports edgevo_jax
  (and so JAX and OpenCV) to read the sequence; ``baseline_rss_mib`` is the peak after
  that, before the method's own library was imported and the method started.
- ``ratio_to_edgevo``: warm median / warm median of the default ``edgevo`` variant on the
  same sequence.
- For edgevo variants a per-stage profile (medians over warm frames): decode
  (``run.decode_ms``), preprocess (``FrameResult.preprocess_ms``), solve wait
  (``FrameResult.solve_ms``) and host other = frame - preprocess - solve wait (clipped at
  0). The solve runs while the next frame is preprocessed, so the stages do not add up to
  the frame time. Per keyframe (medians over keyframes, ``runner.summarise``): edge
  selection (``select_ms``) and local mapping (``mapping_ms``), with the share of frames
  that were keyframes: these make the p90 and the mean, not the median.

A peer whose library is absent (ImportError, or an OpenCV without ``cv2.Odometry``) is
reported as ``"missing": "<reason>"``; an unknown method name likewise. Results go to
``--out-json`` (with machine information; NaN written as null) and ``--out-md``; the
markdown table and the profile are printed to stdout, progress to stderr.

The data are the TUM RGB-D benchmark's (CC BY 4.0): J. Sturm, N. Engelhard, F. Endres,
W. Burgard, D. Cremers, "A Benchmark for the Evaluation of RGB-D SLAM Systems", IROS 2012.
"""

from __future__ import annotations

import argparse
import json
import math
import resource
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from edgevo_jax import enable_batch_exact
from edgevo_jax.datasets.tum import SHARED_CLIPS as DEFAULT_CLIPS
from edgevo_jax.datasets.tum import SHARED_TUM
from edgevo_jax.io import json_safe
from edgevo_jax.peers import PEERS, PeerMissing
from edgevo_jax.provenance import machine_info
from edgevo_jax.reports import fmt, write_json, write_text
from edgevo_jax.reports import markdown_table as md_table
from edgevo_jax.runs import measure
from edgevo_jax.runs.measure import WARMUP_FRAMES, frame_stats

DEFAULT_EDGEVO = "edgevo"
# the edgevo variants every run includes: selection off (all edges) and local mapping off
BUILTIN_VARIANTS = ("edgevo_all=selection=all", "edgevo_nomap=mapping=false")
PROFILE_NOTE = (
    "solve wait = FrameResult.solve_ms, from submitting frame k to its result; it runs while "
    "the host preprocesses frame k+1, so preprocess and solve overlap and the stages do not "
    "add up to the frame time; host other = frame - preprocess - solve wait, clipped at 0; "
    "selection and mapping: median ms per keyframe, on the keyframes (the share given), "
    "which they lengthen"
)


def parse_variant(spec: str) -> tuple[str, list[str]]:
    """``name=key=value;key=value`` -> (name, ["key=value", ...]), each override checked
    against ``edgevo_jax.Config`` (ValueError naming the variant for an unknown key)."""
    from edgevo_jax import Config

    if "=" not in spec:
        raise ValueError(f"--edgevo expects NAME=key=value;key=value, got {spec!r}")
    name, rest = (s.strip() for s in spec.split("=", 1))
    if not name:
        raise ValueError(f"--edgevo {spec!r}: empty variant name")
    if name in PEERS:
        raise ValueError(f"--edgevo {spec!r}: {name!r} is a peer's name")
    overrides = [s.strip() for s in rest.split(";") if s.strip()]
    try:
        Config().with_overrides(overrides)
    except (ValueError, TypeError) as err:
        raise ValueError(f"--edgevo {name}: {err}") from None
    return name, overrides


def _maxrss_mib() -> float:
    """Peak resident set size of this process so far (MiB; ru_maxrss is KiB on Linux)."""
    kib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return kib / (1024.0 * 1024.0) if sys.platform == "darwin" else kib / 1024.0


def accuracy(seq: Any, timestamps: np.ndarray, poses: np.ndarray) -> dict[str, Any]:
    """ATE RMSE (m) and RPE translation RMSE (m/s; NaN for clips under 1 s) of T_world_cam
    ``poses`` (N, 4, 4) against the sequence's ground truth (``measure.accuracy``)."""
    out = measure.accuracy(seq.groundtruth, timestamps, poses,
                           no_groundtruth="no groundtruth.txt")
    del out["rpe_deg_per_s"]
    return out


def _timing(prefix: str, stats: dict[str, float], keys: Sequence[str]) -> dict[str, float]:
    return {f"{prefix}_{k}_ms": stats[k] for k in keys}


def run_peer(method: str, seq: Any, max_frames: int | None = None) -> dict[str, Any]:
    """Track ``seq`` frame to frame with the peer ``method`` from edgevo's first pose
    (``measure.run_peer``); the result row, or ``{"missing": reason}``."""
    if method not in PEERS:
        return {"missing": f"unknown method {method!r} (peers: {', '.join(PEERS)}; edgevo "
                           "variants are named with --edgevo)"}
    baseline = _maxrss_mib()
    t0 = time.perf_counter()
    try:
        track = measure.run_peer(method, seq, max_frames=max_frames)
    except PeerMissing as err:
        return {"missing": str(err)}
    wall_s = time.perf_counter() - t0
    n = len(track.frame_ms)
    out: dict[str, Any] = {
        "kind": "peer",
        "api": track.description,
        "frames": n,
        "lost": track.lost,
        **accuracy(seq, np.asarray(seq.timestamps[:n], np.float64),
                   np.asarray(track.poses).reshape(-1, 4, 4)),
        "first_frame_ms": track.frame_ms[1] if n > 1 else math.nan,
        **_timing("warm", frame_stats(track.frame_ms), ("median", "p90", "mean", "max")),
        "wall_s": wall_s,
        "decode_median_ms": frame_stats(track.decode_ms)["median"],
        "baseline_rss_mib": baseline,
    }
    if track.failures:
        out["failures"] = track.failures
    return out


def _stat(stats: dict[str, Any], key: str) -> float:
    """The median of one of ``runner.summarise``'s per-keyframe timings (NaN if none)."""
    value = stats.get(key)
    return float(value["median"]) if isinstance(value, dict) and "median" in value else math.nan


def run_edgevo(overrides: Sequence[str], seq: Any, max_frames: int | None = None
               ) -> dict[str, Any]:
    """Track ``seq`` with edgevo_jax (``Config().with_overrides(overrides)``)."""
    from edgevo_jax import Config
    from edgevo_jax.runs.run import run_sequence, summarise

    config = Config().with_overrides(list(overrides))
    baseline = _maxrss_mib()
    t0 = time.perf_counter()
    run = run_sequence(seq, config, progress=False, max_frames=max_frames)
    wall_s = time.perf_counter() - t0
    peak = _maxrss_mib()  # the method's peak: before the compiled pass below
    # the same clip again in this process: every program is compiled now (the first pass
    # compiles the window's programs mid-run, which its mean includes)
    t0 = time.perf_counter()
    try:
        again = run_sequence(seq, config, progress=False, max_frames=max_frames)
    except Exception as err:  # the first run's numbers stand; say why the second is absent
        again, compiled_error = None, f"{type(err).__name__}: {err}"
    compiled_wall_s = time.perf_counter() - t0 if again is not None else math.nan
    compiled = frame_stats(again.frame_ms if again is not None else [])
    stats = summarise(run, seq)
    n = len(run.results)
    warm = frame_stats(run.frame_ms)
    pre = [r.preprocess_ms for r in run.results]
    solve = [r.solve_ms for r in run.results]
    # frame_ms[k] (the period in which frame k completes) holds the solve wait of frame k and
    # the preprocessing of frame k + 1 (none after the last frame).
    other = [max(0.0, run.frame_ms[k] - (pre[k + 1] if k + 1 < n else 0.0) - solve[k])
             for k in range(WARMUP_FRAMES, n)]
    return {
        "kind": "edgevo",
        "config_overrides": list(overrides),
        "frames": n,
        "lost": int(stats["lost"]),
        "keyframes": int(stats["keyframes"]),
        **accuracy(seq, run.timestamps, run.poses),
        "first_frame_ms": run.startup_s * 1e3,
        **_timing("warm", warm, ("median", "p90", "mean", "max")),
        "wall_s": wall_s,
        **_timing("compiled", compiled, ("median", "mean", "p90", "max")),
        "compiled_wall_s": compiled_wall_s,
        "repeat_identical": bool(np.array_equal(run.poses, again.poses))
        if again is not None else None,
        **({} if again is not None else {"compiled_error": compiled_error}),
        "peak_rss_mib": peak,
        "profile_ms": {
            "frame": warm["median"],
            "decode": frame_stats(run.decode_ms)["median"],
            "preprocess": frame_stats(pre)["median"],
            "solve_wait": frame_stats(solve)["median"],
            "host_other": frame_stats(other, skip=0)["median"],
            "selection_per_keyframe": _stat(stats, "select_ms"),
            "mapping_per_keyframe": _stat(stats, "mapping_ms"),
            "mapping_worker_per_keyframe": _stat(stats, "mapping_worker_ms"),
            "keyframe_share": int(stats["keyframes"]) / max(n, 1),
        },
        "baseline_rss_mib": baseline,
    }


def run_method(method: str, seq_dir: str | Path, max_frames: int | None = None,
               variants: dict[str, list[str]] | None = None,
               pingpong: int | None = None) -> dict[str, Any]:
    """Run one method on one sequence in this process: the result row (``missing`` set
    instead of the measurements when the method cannot run here). ``pingpong``: play the
    sequence forward and backward to that many frames (``datasets.pingpong``)."""
    from edgevo_jax.datasets import load_sequence
    from edgevo_jax.datasets import pingpong as play

    variants = {DEFAULT_EDGEVO: [], **(variants or {})}
    seq = load_sequence(seq_dir)
    if pingpong is not None:
        seq = play(seq, pingpong)
    row: dict[str, Any] = {"method": method, "sequence": seq.name, "path": str(seq_dir)}
    if method in variants:
        row.update(run_edgevo(variants[method], seq, max_frames))
    else:
        row.update(run_peer(method, seq, max_frames))
    return row


# --------------------------------------------------------------------------------------------
# the parent: one child per method and sequence, then tables and JSON


def run_child(method: str, seq_dir: Path, max_frames: int | None, variant_spec: str | None,
              timeout_s: float | None, pingpong: int | None = None) -> dict[str, Any]:
    """Run ``method`` on ``seq_dir`` in a child process (``--one``); a crash or a timeout
    becomes an ``error`` row."""
    cmd = [sys.executable, str(Path(__file__).resolve()), "--one", method, str(seq_dir)]
    if max_frames is not None:
        cmd += ["--max-frames", str(max_frames)]
    if pingpong is not None:
        cmd += ["--pingpong", str(pingpong)]
    if variant_spec is not None:
        cmd += ["--edgevo", variant_spec]
    base = {"method": method, "sequence": seq_dir.name, "path": str(seq_dir)}
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s,
                              check=False)
    except subprocess.TimeoutExpired:
        return {**base, "error": f"timed out after {timeout_s} s"}
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("{")]
    rc = proc.returncode
    status = f"killed by signal {-rc}" if rc < 0 else f"exited with status {rc}"
    if not lines:
        tail = " | ".join(proc.stderr.strip().splitlines()[-3:])
        return {**base, "error": f"child {status}: {tail}"}
    row = json.loads(lines[-1])
    if rc != 0:  # the result was complete, the child failed afterwards (at exit, say)
        row["child_exit"] = status
    return row


def add_ratios(rows: list[dict[str, Any]], reference: str = DEFAULT_EDGEVO) -> None:
    """Set ``ratio_to_edgevo`` = warm median / the reference method's warm median on the
    same sequence (NaN where either is unavailable)."""
    ref = {r["sequence"]: r.get("warm_median_ms", math.nan)
           for r in rows if r["method"] == reference}
    for r in rows:
        if "missing" in r or "error" in r:
            continue
        den = ref.get(r["sequence"], math.nan)
        num = r.get("warm_median_ms", math.nan)
        ok = den is not None and num is not None and den > 0
        r["ratio_to_edgevo"] = num / den if ok else math.nan


RESULT_HEAD = ("sequence", "method", "ATE RMSE (m)", "RPE (m/s)", "frames", "lost",
               "first frame (ms)", "warm median (ms)", "warm p90 (ms)", "warm mean (ms)",
               "compiled mean (ms)", "x edgevo", "warm max (ms)", "wall (s)",
               "peak RSS (MiB)", "note")
RESULT_CELLS = (("ate_rmse_m", ".4f"), ("rpe_m_per_s", ".4f"), ("frames", None),
                ("lost", None), ("first_frame_ms", ".0f"), ("warm_median_ms", ".1f"),
                ("warm_p90_ms", ".1f"), ("warm_mean_ms", ".1f"), ("compiled_mean_ms", ".1f"),
                ("ratio_to_edgevo", ".2f"), ("warm_max_ms", ".1f"), ("wall_s", ".2f"),
                ("peak_rss_mib", ".0f"))
PROFILE_HEAD = ("sequence", "variant", "frame", "decode", "preprocess", "solve wait",
                "host other", "selection / kf", "mapping / kf", "keyframes")


def markdown_table(rows: list[dict[str, Any]]) -> str:
    """The results as a markdown table, one row per method and sequence."""
    cells = []
    for r in rows:
        if "missing" in r or "error" in r:
            note = f"missing: {r['missing']}" if "missing" in r else f"error: {r['error']}"
            cells.append([r["sequence"], r["method"]] + ["-"] * 13 + [note.replace("|", "/")])
            continue
        note = "; ".join(filter(None, [
            "config: " + ";".join(r["config_overrides"]) if r.get("config_overrides") else "",
            r.get("accuracy_note", "")])).replace("|", "/")
        cells.append([r["sequence"], r["method"]] + [
            str(r.get(k, "")) if spec is None else fmt(r.get(k), spec)
            for k, spec in RESULT_CELLS] + [note])
    text = md_table(RESULT_HEAD, cells)
    base = [r["baseline_rss_mib"] for r in rows if r.get("baseline_rss_mib") is not None]
    if base:
        text += (f"\n\nPeak RSS is the whole child process's: each starts at ~"
                 f"{float(np.median(base)):.0f} MiB (edgevo_jax, JAX and OpenCV imported, "
                 "sequence loaded) before the method's library and frames (baseline_rss_mib).")
    return text


def profile_table(rows: list[dict[str, Any]]) -> str:
    """Per-stage medians of the edgevo variants (ms per warm frame)."""
    keys = ("frame", "decode", "preprocess", "solve_wait", "host_other",
            "selection_per_keyframe", "mapping_per_keyframe")
    cells = [[r["sequence"], r["method"]] + [fmt(p.get(k), ".1f") for k in keys]
             + [fmt(100 * p.get("keyframe_share", math.nan), ".0f") + " %"]
             for r in rows if (p := r.get("profile_ms")) is not None]
    return md_table(PROFILE_HEAD, cells) + f"\n\n{PROFILE_NOTE}."


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        description="Benchmark edgevo_jax against OpenCV / Open3D RGB-D odometry on TUM clips.")
    p.add_argument("sequences", nargs="*", type=Path, metavar="SEQ_DIR",
                   help=f"TUM sequence folders (default: the clips in {SHARED_TUM})")
    p.add_argument("--max-frames", type=int, default=None,
                   help="use at most this many frames per sequence")
    p.add_argument("--methods", default=None,
                   help="comma-separated methods (default: the edgevo variants and "
                        f"{','.join(PEERS)})")
    p.add_argument("--edgevo", action="append", default=[], metavar="NAME=key=v;key=v",
                   help="an extra edgevo variant (repeatable), e.g. 'edgevo_all=selection=all'")
    p.add_argument("--pingpong", type=int, default=None, metavar="N",
                   help="play each sequence forward and backward to N frames (memory, drift)")
    p.add_argument("--out-json", type=Path, default=Path("bench.json"))
    p.add_argument("--out-md", type=Path, default=Path("bench.md"))
    p.add_argument("--timeout", type=float, default=3600.0,
                   help="seconds allowed per method and sequence (default 3600)")
    p.add_argument("--one", metavar="METHOD", default=None, help=argparse.SUPPRESS)
    return p


def _child_main(args: argparse.Namespace, variants: dict[str, list[str]]) -> int:
    if len(args.sequences) != 1:
        raise ValueError("--one takes exactly one sequence")
    row = run_method(args.one, args.sequences[0], args.max_frames, variants, args.pingpong)
    row.setdefault("peak_rss_mib", _maxrss_mib())
    print(json.dumps(json_safe(row)), flush=True)
    return 0


def _progress(k: int, total: int, row: dict[str, Any], seconds: float) -> str:
    head = f"[{k}/{total}] {row['method']} on {row['sequence']}"
    if "missing" in row:
        return f"{head}: missing ({row['missing']})"
    if "error" in row:
        return f"{head}: ERROR {row['error']}"
    return (f"{head}: ATE {fmt(row.get('ate_rmse_m'), '.4f')} m, warm "
            f"{fmt(row.get('warm_median_ms'), '.1f')} ms/frame, lost {row.get('lost')}, "
            f"peak {fmt(row.get('peak_rss_mib'), '.0f')} MiB ({seconds:.1f} s)")


def _cv2_odometry() -> bool | None:
    """Whether this OpenCV has cv2.Odometry (None without OpenCV)."""
    try:
        import cv2
    except ImportError:
        return None
    return hasattr(cv2, "Odometry")


def main(argv: list[str] | None = None,
         progress: Callable[[str], None] | None = None) -> int:
    """Entry point: run the benchmark (or, with ``--one``, one method as a child)."""
    enable_batch_exact()  # the CLI's arithmetic: trajectories as `edgevo run` gives them
    args = _parser().parse_args(argv)
    say = progress or (lambda line: print(line, file=sys.stderr, flush=True))
    try:
        variant_specs = [*BUILTIN_VARIANTS, *args.edgevo]  # a user's spec replaces a builtin
        variants = {DEFAULT_EDGEVO: []} | dict(parse_variant(s) for s in variant_specs)
        if args.max_frames is not None and args.max_frames < 1:
            raise ValueError("--max-frames must be positive")
        if args.one is not None:
            return _child_main(args, variants)
        if args.sequences:
            seqs = list(args.sequences)
            absent = [s for s in seqs if not s.is_dir()]
            if absent:
                raise FileNotFoundError(f"sequence folder not found: {absent[0]}")
        else:
            seqs = [SHARED_TUM / name for name in DEFAULT_CLIPS]
            absent = [s for s in seqs if not s.is_dir()]
            if absent:
                raise FileNotFoundError(
                    f"default TUM clips not found ({absent[0]}); pass SEQ_DIR arguments")
    except (FileNotFoundError, ValueError) as err:
        print(f"bench.py: error: {err}", file=sys.stderr)
        return 2
    methods = ([m.strip() for m in args.methods.split(",") if m.strip()]
               if args.methods else [*variants, *PEERS])
    specs = dict(zip([parse_variant(s)[0] for s in variant_specs], variant_specs, strict=True))

    rows: list[dict[str, Any]] = []
    total, k = len(seqs) * len(methods), 0
    for seq_dir in seqs:
        for method in methods:
            k += 1
            t0 = time.perf_counter()
            row = run_child(method, seq_dir, args.max_frames, specs.get(method), args.timeout,
                            args.pingpong)
            rows.append(row)
            say(_progress(k, total, row, time.perf_counter() - t0))
    add_ratios(rows)

    md = markdown_table(rows)
    prof = profile_table(rows)
    report = {
        "machine": {**machine_info(("open3d",)), "opencv_odometry": _cv2_odometry()},
        "settings": {
            "max_frames": args.max_frames, "pingpong": args.pingpong, "methods": methods,
            "warmup_frames": WARMUP_FRAMES,
            "edgevo_variants": {m: variants[m] for m in methods if m in variants},
            "sequences": [str(s) for s in seqs],
            "timing": "per-frame wall time, PNG decoding excluded; warm = frames from the third",
            "profile_note": PROFILE_NOTE,
        },
        "results": rows,
    }
    write_json(args.out_json, report)
    write_text(args.out_md, f"{md}\n\nedgevo per-stage profile (median ms)\n\n{prof}\n")
    print(md)
    print("\nedgevo per-stage profile (median ms per warm frame)\n")
    print(prof)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

