"""The ``edgevo`` command: ``edgevo run`` tracks a TUM sequence, ``edgevo batch`` tracks many
sequences under many configurations at once, ``edgevo eval`` scores a trajectory,
``edgevo plot`` draws figures (trajectory, frame, selection, configs; see ``edgevo_jax.viz``)."""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

STARTED = time.perf_counter()  # the command's start (the start-up it reports counts from it)

from .camera import CAMERAS  # noqa: E402
from .datasets import BUNDLED_CLIP  # noqa: E402
from .datasets.source import DEPTH_TOPIC, INFO_TOPIC, RGB_TOPIC  # noqa: E402
from .io import json_safe  # noqa: E402

ALIGN_CHOICES = ("se3", "sim3", "origin", "none")  # metrics.ALIGNMENTS (not imported at start)
DELTA_UNIT_CHOICES = {"f": "frames", "s": "seconds", "m": "metres"}  # metrics.DELTA_UNITS


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="edgevo", description="Edge-based RGB-D visual odometry (EdgeVO) in JAX."
    )
    sub = p.add_subparsers(dest="command", required=True)
    run = sub.add_parser("run", help="track an RGB-D sequence and write its trajectory")
    run.add_argument("sequence", nargs="?", type=Path, default=None,
                     help="a TUM or ETH3D folder (its calibration.txt gives the camera), a "
                          "ROS1 or ROS2 bag (.bag, a folder with metadata.yaml, .db3, .mcap), "
                          "or realsense[:SERIAL] for a live camera (default: the bundled "
                          "fr1_xyz clip)")
    run.add_argument("--out", type=Path, default=None,
                     help="trajectory file (TUM format; default: <sequence>.traj.txt here)")
    run.add_argument("--stats", type=Path, default=None, help="write run statistics as JSON")
    run.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                     help="override a Config field (repeatable), e.g. --set max_edges=1024")
    run.add_argument("--max-frames", type=_positive_int, default=None, metavar="N",
                     help="stop after N frames (N >= 1)")
    run.add_argument("--depth-factor", type=_positive_float, default=5000.0,
                     help="depth PNG units per metre (TUM: 5000)")
    run.add_argument("--frame-step", type=_positive_int, default=1, metavar="K",
                     help="keep every K-th line of rgb.txt and depth.txt (1/K of the frame "
                          "rate)")
    cam = run.add_argument_group(
        "camera", "Default: a folder's calibration.txt, else the camera its name names "
        "(freiburg1/2/3 or fr1/2/3); a bag's camera_info; a RealSense's own. One of these "
        "options replaces it.").add_mutually_exclusive_group()
    cam.add_argument("--camera", choices=list(CAMERAS), default=None,
                     help="a preset: "
                          + "; ".join(f"{k}: {v.about}" for k, v in CAMERAS.items()))
    cam.add_argument("--calibration", type=Path, default=None, metavar="FILE",
                     help="a text file of 4 numbers, fx fy cx cy (ETH3D's calibration.txt), "
                          "or 9, fx fy cx cy k1 k2 p1 p2 k3 (OpenCV distortion of the raw "
                          "images, removed before tracking); a global shutter unless "
                          "--set readout_s=SECONDS")
    cam.add_argument("--intrinsics", type=float, nargs=4, default=None,
                     metavar=("FX", "FY", "CX", "CY"),
                     help="a pinhole camera of undistorted images with a global shutter (for "
                          "lens distortion use --calibration)")
    run.add_argument("--no-progress", action="store_true", help="no progress bar")
    run.add_argument("--rgb-topic", default=RGB_TOPIC, help=f"bags: rgb images ({RGB_TOPIC})")
    run.add_argument("--depth-topic", default=DEPTH_TOPIC,
                     help=f"bags: depth images, 32FC1 m or 16UC1 mm ({DEPTH_TOPIC})")
    run.add_argument("--info-topic", default=INFO_TOPIC,
                     help=f"bags: the camera's CameraInfo ({INFO_TOPIC})")
    run.add_argument("--groundtruth", type=Path, default=None,
                     help="bags and cameras: a TUM trajectory file to score against")
    run.add_argument("--rerun", type=Path, default=None, metavar="FILE.rrd",
                     help="record the run for the rerun viewer (pip install "
                          "'edgevo_jax[rerun]'); open it with `rerun FILE.rrd`")
    run.add_argument("--rerun-viewer", action="store_true",
                     help="show the run live in a rerun viewer (needs a display)")
    run.add_argument("--params", type=Path, default=None, metavar="JSON",
                     help="learnt parameters (Huber radii, eta, edge weighting, reobs_a): a "
                          "JSON of Params fields, or scripts/learn_weights.py's log")
    ba = sub.add_parser(
        "batch", help="a sweep: many sources, frame steps, seeds and settings, resumable, "
                      "over processes and hosts",
        description="Run a sweep file (TOML: sources, frame_steps, seeds, [base] and [grid] "
                    "of Config fields; see edgevo_jax.pipeline.sweep) into --out DIR: each "
                    "run's trajectory and JSON line as it finishes (a sweep started again "
                    "skips them), then summary.md / .csv / .png. --processes N runs it in N "
                    "local processes under jax.distributed; --coordinator, --num-processes "
                    "and --process-id (or --cluster, JAX's cluster detection, e.g. SLURM) "
                    "join processes on several hosts sharing DIR. A JSON file of "
                    "configurations with TUM folders runs the older one-process batch.")
    ba.add_argument("configs", type=Path, metavar="SWEEP",
                    help='a sweep file (.toml); or JSON: a list of Config overrides, or '
                         '{"base": {...}, "grid": {"field": [values]}}, with SEQUENCES')
    ba.add_argument("sequences", nargs="*", type=Path,
                    help="with a JSON file: TUM sequence folders (default: the bundled fr1_xyz "
                         "clip)")
    ba.add_argument("--out", type=Path, default=None,
                    help="the sweep's output folder (required with a sweep file); with a JSON "
                         "file the results JSON (default: batch.json)")
    ba.add_argument("--processes", type=_positive_int, default=1, metavar="N",
                    help="sweep: run in N processes on this host under jax.distributed "
                         "(coordinator on localhost; default 1)")
    ba.add_argument("--coordinator", default=None, metavar="HOST:PORT",
                    help="sweep: join a multi-process sweep whose process 0 listens at "
                         "HOST:PORT (with --num-processes and --process-id)")
    ba.add_argument("--num-processes", type=_positive_int, default=None, metavar="N",
                    help="sweep: the number of processes of the sweep, over all hosts")
    ba.add_argument("--process-id", type=int, default=None, metavar="I",
                    help="sweep: this process's index, 0 .. N-1 (0 writes the summary)")
    ba.add_argument("--cluster", action="store_true",
                    help="sweep: join the processes JAX's cluster detection finds (SLURM, "
                         "Open MPI, ...: jax.distributed.initialize())")
    ba.add_argument("--traj-dir", type=Path, default=None,
                    help="JSON batch: also write each run's trajectory here "
                         "(<sequence>.c<index>.txt)")
    ba.add_argument("--chunk", type=int, default=2,
                    help="JSON batch: frames per run per device call (a sweep file's chunk)")
    ba.add_argument("--max-frames", type=int, default=None,
                    help="JSON batch: frames per sequence (a sweep file's max_frames)")
    ba.add_argument("--no-progress", action="store_true", help="no progress bar")
    ev = sub.add_parser(
        "eval", help="ATE and RPE of a trajectory against ground truth (as evo computes them)",
        description="ATE (evo_ape's translation part) and RPE (evo_rpe's translation and "
                    "rotation angle) of an estimated trajectory against ground truth, both TUM "
                    "trajectory files (edgevo_jax.ate, edgevo_jax.rpe). evo's names: --align "
                    "se3 / sim3 / origin / none is -a / -as / --align_origin / no option; "
                    "--delta-unit f / m is evo's f / m (s, seconds, is not in evo; evo's d / r "
                    "are not offered); --t-max-diff, --t-offset, --all-pairs and --delta-tol "
                    "are evo's --t_max_diff, --t_offset, --all_pairs and --delta_tol.")
    ev.add_argument("groundtruth", type=Path, help="ground-truth trajectory (TUM format)")
    ev.add_argument("estimate", type=Path, help="estimated trajectory (TUM format)")
    ev.add_argument("--align", choices=ALIGN_CHOICES, default="se3",
                    help="how the estimate is aligned onto the ground truth: se3 rigid "
                         "(TUM's ATE; the default), sim3 with scale, origin (first poses made "
                         "equal), none; the RPE is aligned alike (only sim3 changes it)")
    ev.add_argument("--delta", type=float, default=1.0,
                    help="RPE: distance between the poses of a pair (default: 1)")
    ev.add_argument("--delta-unit", choices=tuple(DELTA_UNIT_CHOICES), default="f",
                    help="RPE: unit of --delta: f frames (default), s seconds, m metres of the "
                         "estimate's path")
    ev.add_argument("--all-pairs", action="store_true",
                    help="RPE: a pair from every pose, not consecutive pairs")
    ev.add_argument("--delta-tol", type=float, default=0.1,
                    help="RPE with s or m and --all-pairs: relative tolerance of a pair's "
                         "distance (default: 0.1)")
    ev.add_argument("--t-max-diff", type=float, default=0.02, metavar="S",
                    help="largest time difference of associated poses, seconds (default: 0.02,"
                         " TUM's; evo's is 0.01)")
    ev.add_argument("--t-offset", type=float, default=0.0, metavar="S",
                    help="seconds added to the estimate's timestamps (default: 0)")
    ev.add_argument("--json", action="store_true", help="print JSON")
    _add_plot_parser(sub)
    return p


def _add_plot_parser(sub: argparse._SubParsersAction) -> None:
    plot = sub.add_parser("plot", help="draw a figure as a PNG (needs matplotlib)",
                          description="Draw one figure as a PNG (needs matplotlib: "
                                      "pip install edgevo_jax[viz]).")
    kinds = plot.add_subparsers(dest="figure", required=True)

    def common(p: argparse.ArgumentParser, default_out: str) -> None:
        p.add_argument("--out", type=Path, default=Path(default_out),
                       help=f"PNG file to write (default: {default_out})")
        p.add_argument("--dpi", type=float, default=100.0,
                       help="pixels per inch of the PNG (default: 100)")

    def frame_args(p: argparse.ArgumentParser) -> None:
        p.add_argument("sequence", nargs="?", type=Path, default=None,
                       help="TUM sequence folder (default: the bundled fr1_xyz clip)")
        p.add_argument("--index", type=int, default=0,
                       help="frame index among the associated rgb-depth pairs (default: 0)")
        p.add_argument("--set", dest="overrides", action="append", default=[],
                       metavar="KEY=VALUE", help="override a Config field (repeatable)")

    tr = kinds.add_parser("trajectory", help="estimate vs ground truth, coloured by error")
    tr.add_argument("groundtruth", type=Path, help="ground-truth trajectory (TUM format)")
    tr.add_argument("estimate", type=Path, help="estimated trajectory (TUM format)")
    tr.add_argument("--plane", default="xy",
                    help="axes of the top view, two of x, y, z (default: xy)")
    tr.add_argument("--title", default=None, help="title (default: the estimate's file name)")
    common(tr, "trajectory.png")

    fr = kinds.add_parser("frame", help="gray image, Canny edges, distance-field pyramid")
    frame_args(fr)
    common(fr, "frame.png")

    se = kinds.add_parser("selection", help="edges selected by each mode over the image")
    frame_args(se)
    se.add_argument("--modes", default="spg,greedy",
                    help="comma-separated selection modes, one panel each (default: "
                         "spg,greedy; also random, all)")
    se.add_argument("--no-candidates", action="store_true",
                    help="leave out the panel of all culled candidate edges")
    common(se, "selection.png")

    co = kinds.add_parser(
        "configs", help="accuracy vs time and edges used across configurations",
        description="Accuracy vs time per frame, and edges used vs accuracy, across "
                    "configurations, from scripts/ablation_selection.py JSON, "
                    "scripts/bench.py JSON, or `edgevo run --stats` JSON files.")
    co.add_argument("results", type=Path, nargs="+",
                    help="ablation.json, bench.json or run-statistics JSON file(s)")
    common(co, "configs.png")


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``edgevo`` console script."""
    args = _parser().parse_args(argv)
    if args.command in ("run", "batch"):
        from .determinism import enable_batch_exact

        enable_batch_exact()  # a run's trajectory equals its trajectory in any batch
    try:
        if args.command == "run":
            return _run(args)
        if args.command == "plot":
            return _plot(args)
        if args.command == "batch":
            return _batch(args)
        return _eval(args)
    except (FileNotFoundError, ValueError, ImportError) as err:
        print(f"edgevo: error: {err}", file=sys.stderr)
        for note in getattr(err, "__notes__", []):  # where a run stopped, what it kept
            print(f"edgevo: {note}", file=sys.stderr)
        return 2


def _positive_int(text: str) -> int:
    """argparse type: an integer >= 1."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number >= 1, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {value}")
    return value


def _positive_float(text: str) -> float:
    """argparse type: a finite number > 0."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number > 0, got {text!r}") from None
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"must be a finite number > 0, got {text}")
    return value


def _camera(args: argparse.Namespace) -> dict:
    """``open_source``'s camera argument from ``--camera``, ``--calibration`` (``camera=``) or
    ``--intrinsics`` (``intrinsics=``); {} when none is given."""
    from .camera import Intrinsics
    from .datasets.tum import read_calibration

    if args.camera is not None:
        return {"camera": args.camera}
    if args.intrinsics is not None:
        try:
            return {"intrinsics": Intrinsics(*args.intrinsics).validate()}
        except ValueError as err:
            raise ValueError(f"--intrinsics {' '.join(f'{v:g}' for v in args.intrinsics)}: "
                             f"{err}") from None
    if args.calibration is None:
        return {}
    if not args.calibration.is_file():
        raise FileNotFoundError(f"--calibration file not found: {args.calibration}")
    try:
        return {"camera": read_calibration(args.calibration)}
    except ValueError as err:
        raise ValueError(f"--calibration {err}") from None


def _run(args: argparse.Namespace) -> int:
    from .config import Config
    from .datasets.source import SourceError, open_source
    from .pipeline.run import run_sequence, summarise

    config = Config().with_overrides(args.overrides)
    params = _read_params(args.params, config) if args.params is not None else None
    path = args.sequence if args.sequence is not None else BUNDLED_CLIP
    try:
        seq = open_source(
            path, **_camera(args), depth_factor=args.depth_factor,
            frame_step=args.frame_step, rgb_topic=args.rgb_topic, depth_topic=args.depth_topic,
            info_topic=args.info_topic, groundtruth=args.groundtruth, max_frames=args.max_frames)
    except SourceError as err:  # its remedy in the CLI's options
        raise ValueError(err.cli_message()) from None
    recording = None
    if args.rerun is not None or args.rerun_viewer:
        from .viz.recording import RerunRecording

        recording = RerunRecording(seq, path=args.rerun, spawn=args.rerun_viewer)
    out = args.out if args.out is not None else Path(f"{seq.name}.traj.txt")
    try:
        run = run_sequence(seq, config, out=out, progress=not args.no_progress,
                           max_frames=args.max_frames, params=params, started=STARTED,
                           on_frame=recording)
    except KeyboardInterrupt as err:
        notes = getattr(err, "__notes__", [])
        print("edgevo: interrupted" + (f"; {notes[0]}" if notes else ""), file=sys.stderr)
        return 130
    finally:
        if recording is not None:
            recording.close()
        if hasattr(seq, "close"):  # a bag's reader, a live camera
            seq.close()
    stats = summarise(run, seq)
    if args.stats is not None:
        args.stats.parent.mkdir(parents=True, exist_ok=True)
        args.stats.write_text(json.dumps(json_safe(stats), indent=2) + "\n")
    print(_summary_text(stats, out))
    if args.rerun is not None:
        print(f"rerun recording: {args.rerun} (open with `rerun {args.rerun}`)")
    return 0


def _read_params(path: Path, config):
    """Params from a JSON file: Params fields at the top level, or under "fitted_params"
    (``scripts/learn_weights.py``'s log)."""
    from .learn.params import params_from_dict

    try:
        values = json.loads(path.read_text())
    except FileNotFoundError:
        raise FileNotFoundError(f"--params file not found: {path}") from None
    except json.JSONDecodeError as err:
        raise ValueError(f"--params {path} is not JSON: {err}") from None
    if not isinstance(values, dict):
        raise ValueError(f"--params {path} must hold a JSON object")
    values = values.get("fitted_params", values)
    try:
        return params_from_dict(values, config)
    except (ValueError, TypeError) as err:
        raise ValueError(f"--params {path}: {err}") from None


def _batch(args: argparse.Namespace) -> int:
    if args.configs.suffix == ".toml":
        return _sweep(args)
    sweep_only = [o for o, v in (("--processes", args.processes != 1),
                                 ("--coordinator", args.coordinator is not None),
                                 ("--num-processes", args.num_processes is not None),
                                 ("--process-id", args.process_id is not None),
                                 ("--cluster", args.cluster)) if v]
    if sweep_only:
        raise ValueError(f"{', '.join(sweep_only)}: for a sweep file (.toml) only, not JSON "
                         "configurations")
    if args.out is None:
        args.out = Path("batch.json")
    from .datasets.tum import load_sequence
    from .io import matrices_to_poses7, write_trajectory
    from .pipeline import batch
    from .pipeline.run import summarise

    configs = batch.load_configs(args.configs)
    seqs = [load_sequence(p) for p in (args.sequences or [BUNDLED_CLIP])]
    result = batch.evaluate(seqs, configs, chunk=args.chunk, max_frames=args.max_frames,
                            progress=not args.no_progress)
    by_name = {s.name: s for s in seqs}
    rows = []
    for run in result.runs:
        row = summarise(run, by_name[run.sequence])
        row["changed"] = batch.changed_fields(run.config)
        if args.traj_dir is not None:
            args.traj_dir.mkdir(parents=True, exist_ok=True)
            path = args.traj_dir / f"{run.sequence}.c{run.config_index}.txt"
            write_trajectory(path, run.timestamps, matrices_to_poses7(run.poses))
            row["trajectory"] = str(path)
        rows.append(row)
    frames = sum(r["frames"] for r in rows)
    out = {"runs": rows, "wall_s": result.wall_s, "device_calls": result.calls,
           "frames": frames, "devices": result.devices}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(json_safe(out), indent=2) + "\n")
    for r in rows:
        ate = r.get("ate_rmse_m")
        print(f"{r['sequence']:<40} c{r['config_index']:<3} "
              f"ATE {'n/a' if ate is None else f'{ate:.4f} m':<9} frames {r['frames']:<5} "
              f"kf {r['keyframes']:<4} lost {r['lost']:<3} {r['changed'] or 'defaults'}")
    print(f"{len(rows)} runs, {frames} frames in {result.wall_s:.1f} s "
          f"({frames / result.wall_s:.0f} frames/s, compilation included) on "
          f"{len(result.devices)} device(s); results in {args.out}")
    return 0


def _sweep(args: argparse.Namespace) -> int:
    """``edgevo batch SWEEP.toml --out DIR``: this process's part of the sweep (its share
    of the runs, then, as process 0, the summary); with --processes N, start processes
    1 .. N-1 first."""
    from .pipeline import processes as procs
    from .pipeline import sweep as sw

    if args.sequences:
        raise ValueError("a sweep file names its sources itself: drop the SEQUENCES "
                         f"({' '.join(map(str, args.sequences))}) or list them in its sources")
    if args.out is None:
        raise ValueError("--out DIR is required with a sweep file (the folder its runs and "
                         "summary go to)")
    joined = [args.coordinator is not None, args.num_processes is not None,
              args.process_id is not None]
    if any(joined) and not all(joined):
        raise ValueError("--coordinator, --num-processes and --process-id go together")
    if sum([args.processes > 1, all(joined), args.cluster]) > 1:
        raise ValueError("choose one of --processes, --cluster and --coordinator / "
                         "--num-processes / --process-id")
    if all(joined) and not 0 <= args.process_id < args.num_processes:
        raise ValueError(f"--process-id must be 0 .. {args.num_processes - 1}, got "
                         f"{args.process_id}")
    plan = sw.load_sweep(args.configs)
    sw.open_sources(plan)  # every source opens before any process starts
    if args.out.exists() and not args.out.is_dir():
        raise ValueError(f"--out {args.out} is a file, not a folder")
    args.out.mkdir(parents=True, exist_ok=True)
    import jax

    from .programs import enable_cache

    children: list = []
    if args.processes > 1:
        coordinator = f"localhost:{procs.free_port()}"
        command = [sys.executable, "-m", "edgevo_jax.cli", "batch", str(args.configs),
                   "--out", str(args.out), "--no-progress"]
        children = procs.start_processes(command, args.processes, coordinator)
        jax.distributed.initialize(coordinator, args.processes, 0)
    elif all(joined):
        jax.distributed.initialize(args.coordinator, args.num_processes, args.process_id)
    elif args.cluster:
        jax.distributed.initialize()
    enable_cache()
    index, count = jax.process_index(), jax.process_count()
    tag = f"[process {index}/{count}] " if count > 1 else ""
    t0 = time.perf_counter()

    def done(record: dict) -> None:
        ate = record["ate_rmse_m"]
        print(f"{tag}{record['key']}: ATE {'n/a' if ate is None else f'{ate * 1e3:.2f} mm'}, "
              f"lost {record['lost']}", flush=True)

    try:
        from .viz.sweep import plot_sweep

        share, records = sw.run_sweep(plan, args.out, progress=not args.no_progress,
                                      check=procs.children_check(children), on_done=done,
                                      plot=plot_sweep)
    except KeyboardInterrupt:
        print(f"edgevo: {tag}interrupted; finished runs are in {args.out}: run the same "
              "command again to go on", file=sys.stderr)
        return 130
    except RuntimeError as err:
        print(f"edgevo: error: {tag}{err}", file=sys.stderr)
        return 1
    finally:
        if sys.exc_info()[0] is not None:  # given up on: the others stop too
            for child in children:
                if child.poll() is None:
                    child.kill()
    if count > 1:  # every process meets at the shutdown barrier; then children end
        jax.distributed.shutdown()
    for child in children:
        child.wait()
    print(f"{tag}{share.ran} runs tracked here, {share.skipped} already written, of "
          f"{share.owned} of this process; {len(records)} runs in all in "
          f"{time.perf_counter() - t0:.1f} s", flush=True)
    if index == 0:
        print(f"summary: {args.out / 'summary.md'} (and summary.csv, summary_settings.csv"
              f"{', summary.png' if (args.out / 'summary.png').exists() else ''})")
    return 0


def _summary_text(stats: dict, out: Path) -> str:
    ms = stats["ms_per_frame"]
    lines = [
        f"sequence      {stats['sequence']}",
        f"frames        {stats['frames']}  (keyframes {stats['keyframes']}, weak {stats['weak']}, "
        f"lost {stats['lost']})",
        f"start-up      {stats['startup_s']:.2f} s (command to first pose; compiling or "
        f"loading every program: {stats['warm_up_s']:.2f} s)",
        f"ms/frame      mean {ms['mean']:.1f}  median {ms['median']:.1f}  p90 {ms['p90']:.1f}"
        "  (every later frame, decoding excluded)",
    ]
    if "ate_rmse_m" in stats:
        lines.append(f"ATE RMSE      {stats['ate_rmse_m']:.4f} m")
        rpe = stats.get("rpe_rmse_m_per_s")
        lines.append("RPE RMSE      " + ("n/a (sequence shorter than 1 s)" if rpe is None
                                         or math.isnan(rpe) else f"{rpe:.4f} m/s"))
    else:
        lines.append("ATE           n/a (" + stats.get("ground_truth_note", "no ground truth")
                     + ")")
    lines.append(f"trajectory    {out}")
    return "\n".join(lines)


def _eval(args: argparse.Namespace) -> int:
    from .metrics import ate, rpe

    for option, value, low in (("--delta", args.delta, None), ("--t-max-diff", args.t_max_diff,
                               None), ("--delta-tol", args.delta_tol, 0.0)):
        if not (math.isfinite(value) and (value > 0 if low is None else value >= low)):
            raise ValueError(f"{option} must be {'positive' if low is None else '>= 0'} and "
                             f"finite, got {value:g}")
    if args.delta_unit == "f" and args.delta != int(args.delta):
        raise ValueError(f"--delta must be a whole number of frames with --delta-unit f, got "
                         f"{args.delta:g}")
    if not math.isfinite(args.t_offset):
        raise ValueError(f"--t-offset must be finite, got {args.t_offset:g}")
    gt, est = _read(args.groundtruth, "ground-truth"), _read(args.estimate, "estimated")
    unit = DELTA_UNIT_CHOICES[args.delta_unit]
    common = {"align": args.align, "max_diff": args.t_max_diff, "offset": args.t_offset}
    a = ate(gt, est, **common)
    r = rpe(gt, est, delta=args.delta, unit=unit, all_pairs=args.all_pairs,
            delta_tol=args.delta_tol, **common)
    if args.json:
        options = {"align": args.align, "delta": args.delta, "delta_unit": unit,
                   "all_pairs": args.all_pairs, "delta_tol": args.delta_tol,
                   "t_max_diff": args.t_max_diff, "t_offset": args.t_offset}
        print(json.dumps(json_safe({"ate": a, "rpe": r, "options": options})))
        return 0
    scale = f", scale {a['scale']:.6f}" if args.align == "sim3" else ""
    print(f"ATE ({args.align} alignment{scale}, {a['n']} pairs; m)")
    print("  " + _stat_line(a, ""))
    what = (f"delta = {args.delta:g} ({unit})" + (", all pairs" if args.all_pairs else "")
            + f", {r['n']} pairs")
    if r["n"]:
        print(f"RPE ({what}) translation, m")
        print("  " + _stat_line(r, ""))
        print("RPE rotation, deg")
        print("  " + _stat_line(r, "rot_"))
    else:
        print(f"RPE n/a (no pose pairs {args.delta:g} {unit} apart: the trajectory is shorter)")
    return 0


def _stat_line(stats: dict, prefix: str) -> str:
    return "  ".join(f"{k} {stats[prefix + k]:.6f}"
                     for k in ("rmse", "mean", "median", "std", "min", "max"))


def _plot(args: argparse.Namespace) -> int:
    from . import viz

    try:
        viz.require_matplotlib()
    except ImportError as err:
        print(f"edgevo: error: {err}", file=sys.stderr)
        return 2
    if not (args.dpi > 0 and math.isfinite(args.dpi)):
        raise ValueError(f"--dpi must be positive, got {args.dpi}")
    out = {"trajectory": _plot_trajectory, "frame": _plot_frame,
           "selection": _plot_selection, "configs": _plot_configs}[args.figure](args)
    print(f"wrote {out}")
    return 0


def _read(path: Path, what: str):
    from .io import read_trajectory

    if not path.is_file():
        raise FileNotFoundError(f"{what} trajectory file not found: {path}")
    return read_trajectory(path)


def _plot_trajectory(args: argparse.Namespace) -> Path:
    from .viz import plot_trajectory

    gt_t, gt_p = _read(args.groundtruth, "ground-truth")
    est_t, est_p = _read(args.estimate, "estimated")
    return plot_trajectory(gt_t, gt_p, est_t, est_p, args.out, plane=args.plane,
                           title=args.title or args.estimate.name, dpi=args.dpi)


def _load_frame(args: argparse.Namespace):
    """(sequence, config, rgb, depth, frame) of ``args.index`` of ``args.sequence``."""
    from .config import Config
    from .datasets.tum import load_sequence
    from .image.preprocess import preprocess

    config = Config().with_overrides(args.overrides)
    seq = load_sequence(args.sequence if args.sequence is not None else BUNDLED_CLIP)
    if not -len(seq) <= args.index < len(seq):
        raise ValueError(f"--index {args.index} out of range: {seq.name} has {len(seq)} "
                         "associated frames")
    rgb, depth = seq.load_frame(args.index)
    return seq, config, rgb, depth, preprocess(rgb, depth, config)


def _plot_frame(args: argparse.Namespace) -> Path:
    from .image.preprocess import to_gray
    from .viz import plot_frame

    seq, config, rgb, _, frame = _load_frame(args)
    title = (f"{seq.name}, frame {args.index}: Canny {config.canny_low:g}/{config.canny_high:g}"
             f", {len(frame.dist)}-level distance-field pyramid")
    return plot_frame(to_gray(rgb), frame, args.out, title=title, dpi=args.dpi)


def _plot_selection(args: argparse.Namespace) -> Path:
    import numpy as np

    from .config import SELECTIONS
    from .frontend.selection import candidates, select
    from .image.preprocess import to_gray
    from .viz import plot_selection_overlay

    modes = list(dict.fromkeys(m.strip() for m in args.modes.split(",") if m.strip()))
    bad = [m for m in modes if m not in SELECTIONS]
    if bad or not modes:
        raise ValueError(f"--modes: unknown selection mode(s) {', '.join(bad) or '(none)'}; "
                         f"choose from {', '.join(SELECTIONS)}")
    seq, config, rgb, _, frame = _load_frame(args)
    cands = candidates(frame, config)
    h, w = frame.shape
    panels = {} if args.no_candidates else {"candidates (culled)": cands.uv}
    for mode in modes:
        idx = select(cands, config.replace(selection=mode), T_prior=np.eye(4),
                     intr=seq.intrinsics, width=w, height=h, seed=config.seed)
        panels[mode] = cands.uv[:, idx]
    title = (f"{seq.name}, frame {args.index}: edges selected at num_edges={config.num_edges} "
             f"(prior motion identity, seed {config.seed})")
    return plot_selection_overlay(to_gray(rgb), panels, args.out, title=title, dpi=args.dpi)


def _plot_configs(args: argparse.Namespace) -> Path:
    from .viz import plot_ablation, plot_benchmark, read_results

    kind, records = read_results(args.results)
    if kind == "bench":
        return plot_benchmark(records, args.out, dpi=args.dpi)
    return plot_ablation(records, args.out, dpi=args.dpi)


if __name__ == "__main__":
    raise SystemExit(main())
