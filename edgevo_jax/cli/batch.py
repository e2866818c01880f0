"""``edgevo batch``: a sweep file (TOML) run over processes and hosts into a resumable
output folder, or the older one-process batch of JSON configurations over TUM
folders."""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from ..datasets import BUNDLED_CLIP
from ..io import check_output, json_safe
from ._common import _positive_int


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Add ``edgevo batch`` and its options to the subcommands ``sub``."""
    ba = sub.add_parser(
        "batch", help="a sweep: many sources, frame steps, seeds and settings, resumable, "
                      "over processes and hosts",
        description="Run a sweep file (TOML: sources, frame_steps, seeds, [base] and [grid] "
                    "of Config fields; see edgevo_jax.runs.sweep) into --out DIR: each "
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


def command(args: argparse.Namespace) -> int:
    """``edgevo batch``: a sweep file goes to the sweep; JSON configurations run
    in this process and their results go to --out (batch.json)."""
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
    check_output(args.out, what="--out")  # before anything runs
    if args.traj_dir is not None:
        check_output(args.traj_dir, what="--traj-dir", folder=True)
    from ..datasets.tum import load_sequence
    from ..io import matrices_to_poses7, write_trajectory
    from ..runs import batch
    from ..runs.configs import changed_fields, load_configs
    from ..runs.run import summarise

    configs = load_configs(args.configs)
    seqs = [load_sequence(p) for p in (args.sequences or [BUNDLED_CLIP])]
    result = batch.evaluate(seqs, configs, chunk=args.chunk, max_frames=args.max_frames,
                            progress=not args.no_progress)
    by_name = {s.name: s for s in seqs}
    rows = []
    for run in result.runs:
        row = summarise(run, by_name[run.sequence])
        row["changed"] = changed_fields(run.config)
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
    from ..runs import sweep as sw

    joined = _check_sweep_args(args)
    check_output(args.out, what="--out", folder=True)  # before anything runs
    plan = sw.load_sweep(args.configs)
    sw.open_sources(plan)  # every source opens before any process starts
    args.out.mkdir(parents=True, exist_ok=True)
    import jax

    from ..programs import enable_cache

    children = _join_processes(args, joined)
    enable_cache()
    index, count = jax.process_index(), jax.process_count()
    tag = f"[process {index}/{count}] " if count > 1 else ""
    t0 = time.perf_counter()
    ran = _run_share(args, plan, children, tag)
    if isinstance(ran, int):
        return ran
    share, records = ran
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


def _check_sweep_args(args: argparse.Namespace) -> bool:
    """ValueError for options that do not go with a sweep file or with each other; whether
    this process joins a sweep by --coordinator, --num-processes and --process-id."""
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
    return all(joined)


def _join_processes(args: argparse.Namespace, joined: bool) -> list:
    """Start jax.distributed as the options say: with --processes N, processes 1 .. N-1
    started here (returned, to wait for) and this one as process 0; a process joining by
    --coordinator (``joined``) or by --cluster; nothing for one process."""
    import jax

    from ..runs import processes as procs

    children: list = []
    if args.processes > 1:
        coordinator = f"localhost:{procs.free_port()}"
        command = [sys.executable, "-m", "edgevo_jax.cli", "batch", str(args.configs),
                   "--out", str(args.out), "--no-progress"]
        children = procs.start_processes(command, args.processes, coordinator)
        jax.distributed.initialize(coordinator, args.processes, 0)
    elif joined:
        jax.distributed.initialize(args.coordinator, args.num_processes, args.process_id)
    elif args.cluster:
        jax.distributed.initialize()
    return children


def _run_share(args: argparse.Namespace, plan, children: list, tag: str) -> tuple | int:
    """Run this process's share of the sweep ``plan`` into --out, printing each run's line
    (prefixed by ``tag``) as it finishes: (share, records) of ``sweep.run_sweep``, or the
    exit code after an interruption (130) or a failed run (1); the children are killed
    when this process gives up."""
    from ..runs import processes as procs
    from ..runs import sweep as sw

    def done(record: dict) -> None:
        ate = record["ate_rmse_m"]
        print(f"{tag}{record['key']}: ATE {'n/a' if ate is None else f'{ate * 1e3:.2f} mm'}, "
              f"lost {record['lost']}", flush=True)

    try:
        from ..viz.sweep import plot_sweep

        return sw.run_sweep(plan, args.out, progress=not args.no_progress,
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
