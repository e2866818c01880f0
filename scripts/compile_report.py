"""Every program a run compiles or loads, with its times and size.

Usage::

    python scripts/compile_report.py [SEQ_DIR] [--api] [--cache DIR] [--max-frames N]
        [--set key=value ...] [--out-json report.json]

Runs ``edgevo run`` on SEQ_DIR (default: the bundled clip) in this process, as the CLI
does (``--api``: through the public API instead, ``edgevo_jax.run(load_sequence(SEQ_DIR),
Config())``, with nothing set up beforehand). The on-disk program cache is a new empty
folder unless ``--cache DIR`` names one (a cache an earlier run filled: what a later process
loads). Start this script in a new process for each measurement: programs compiled earlier
in a process are not compiled again.

Per XLA program (one line each, in the order they finished; ``programs.CompileRecorder``):
its module name (``jit_`` and the edgevo program's name, or a JAX primitive run outside
edgevo's programs), the seconds
spent tracing it to a jaxpr, lowering it to StableHLO and compiling it (or loading it from
the cache: ``cached`` says which), and its size: the bytes of the compiled executable as the
cache stores it (0 when it was loaded). Totals at the end, with the run's start-up
(``RunResult.startup_s``: to the first pose) and warm-up (``warm_up_s``: the tracker's
compiling or loading of every program at its first keyframe), the wall time and the CPU time
of the whole run (on a shared machine the CPU time varies less). A mapping worker compiles
beside tracking, so the times of programs can overlap and their sum can exceed the wall time.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import jax

from edgevo_jax.programs import CompileRecorder


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("sequence", nargs="?", type=Path, default=None)
    ap.add_argument("--api", action="store_true", help="run through the public API")
    ap.add_argument("--cache", type=Path, default=None,
                    help="the program cache to use (default: a new empty folder)")
    ap.add_argument("--max-frames", type=int, default=None)
    ap.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE",
                    help="Config overrides (as `edgevo run --set`)")
    ap.add_argument("--out-json", type=Path, default=None)
    args = ap.parse_args(argv)

    started, cpu_started = time.perf_counter(), time.process_time()
    tmp = tempfile.TemporaryDirectory(prefix="edgevo_compile_report_")
    cache = args.cache if args.cache is not None else Path(tmp.name) / "cache"
    os.environ["EDGEVO_CACHE_DIR"] = str(cache)

    from edgevo_jax.cli import BUNDLED_CLIP

    # the folder JAX's compiled programs go to: EDGEVO_CACHE_DIR unless the user set one
    jax_dir = jax.config.jax_compilation_cache_dir
    recorder = CompileRecorder(Path(jax_dir) if jax_dir else cache)
    recorder.start()

    seq_path = args.sequence if args.sequence is not None else BUNDLED_CLIP
    if args.api:
        import edgevo_jax as e

        config = e.Config().with_overrides(args.set)
        seq = e.load_sequence(seq_path)
        run = e.run(seq, config, progress=False, max_frames=args.max_frames, started=started)
        run_stats = {"startup_s": run.startup_s, "warm_up_s": run.warm_up_s,
                     "frames": len(run.results)}
    else:
        from edgevo_jax import cli

        stats_path = Path(tmp.name) / "stats.json"
        cli_args = ["run", str(seq_path), "--no-progress", "--out",
                    str(Path(tmp.name) / "traj.txt"), "--stats", str(stats_path)]
        if args.max_frames is not None:
            cli_args += ["--max-frames", str(args.max_frames)]
        if args.set:
            cli_args += ["--set", *args.set]
        if cli.main(cli_args, started=started) != 0:
            return 1
        stats = json.loads(stats_path.read_text())
        run_stats = {k: stats[k] for k in ("startup_s", "warm_up_s", "frames")}
    wall_s, cpu_s = time.perf_counter() - started, time.process_time() - cpu_started
    recorder.stop()
    recorder.assign_sizes()
    rows = recorder.rows
    compiled = [r for r in rows if not r["cached"]]
    total = {
        "programs": len(rows),
        "compiled": len(compiled),
        "loaded": len(rows) - len(compiled),
        "trace_s": sum(r["trace_s"] for r in rows),
        "lower_s": sum(r["lower_s"] for r in rows),
        "compile_s": sum(r["compile_s"] for r in compiled),
        "load_s": sum(r["compile_s"] for r in rows if r["cached"]),
        "bytes": sum(r["bytes"] for r in rows),
        "wall_s": wall_s,
        "cpu_s": cpu_s,
        **run_stats,
    }
    print(f"{'program':<40} {'trace s':>8} {'lower s':>8} {'compile s':>9} {'cached':>6} "
          f"{'kB':>8}")
    for r in rows:
        print(f"{r['program'][:40]:<40} {r['trace_s']:8.3f} {r['lower_s']:8.3f} "
              f"{r['compile_s']:9.3f} {'yes' if r['cached'] else 'no':>6} "
              f"{r['bytes'] / 1e3:8.1f}")
    print(f"\n{total['programs']} programs: {total['compiled']} compiled "
          f"({total['compile_s']:.1f} s, {total['bytes'] / 1e6:.2f} MB), {total['loaded']} "
          f"loaded ({total['load_s']:.2f} s); tracing {total['trace_s']:.1f} s, lowering "
          f"{total['lower_s']:.1f} s")
    print(f"run: start-up {total['startup_s']:.2f} s (warm-up {total['warm_up_s']:.2f} s), "
          f"{total['frames']} frames, {wall_s:.1f} s in all, {cpu_s:.1f} s of CPU (cache {cache})")
    if args.out_json is not None:
        args.out_json.write_text(json.dumps({"sequence": str(seq_path), "api": args.api,
                                             "total": total, "programs": rows}, indent=1))
    tmp.cleanup()
    return 0


if __name__ == "__main__":
    sys.exit(main())
