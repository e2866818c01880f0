"""What a batch of configurations costs against one configuration, and whether each run
of the batch equals that configuration run alone.

Usage::

    python scripts/bench_batch.py [SEQ_DIR] [--configs grid.json] [--chunk N]
                                  [--max-frames N] [--warmup-frames N] [--check]
                                  [--out-json F] [--out-md F]

Default sequence: the shared fr3_teddy_first200 clip. Default configurations: a 4 x 4 grid
of the Huber radius (0.5, 1, 1.5, 2 px at every level) and the edge budget (256, 384, 512,
640), which includes the default Config; the grid exercises both the vmapped numbers of the
solve and the host-side selection.

In one process: both batches are first compiled on ``--warmup-frames`` frames (default 40:
enough keyframes to fill the local map's window and marginalise from it, so that the window's
programs compile there too; compilation is reported apart), then timed over the whole
clip: ``batch.evaluate`` with the default Config alone, with all configurations, and the
streaming runner (``runner.run_sequence``, the pipelined frame-by-frame driver) with the
default Config. Wall times include decoding and
preprocessing. ``--check`` also runs every configuration alone with ``run_sequence`` and
reports the largest position difference from its batch run (m).
"""

from __future__ import annotations

import argparse
import platform
import sys
import time
from pathlib import Path

import jax
import numpy as np

from edgevo_jax import Config, enable_batch_exact
from edgevo_jax.datasets import load_sequence
from edgevo_jax.reports import write_json, write_text
from edgevo_jax.runs import batch
from edgevo_jax.runs.run import run_sequence, summarise

DEFAULT_SEQ = (Path(__file__).resolve().parents[2] / "shared" / "data" / "tum"
               / "rgbd_dataset_freiburg3_teddy_first200")


def default_grid() -> list[Config]:
    """4 Huber radii x 4 edge budgets (the default Config among them)."""
    return [Config(huber_delta=(h, h, h), num_edges=k)
            for h in (0.5, 1.0, 1.5, 2.0) for k in (256, 384, 512, 640)]


def _timed(fn):
    t0 = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - t0


def main(argv: list[str] | None = None) -> int:
    enable_batch_exact()  # the CLI's arithmetic: trajectories as `edgevo run` gives them
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("sequence", nargs="?", type=Path, default=DEFAULT_SEQ)
    p.add_argument("--configs", type=Path, default=None, help="JSON (see edgevo batch)")
    p.add_argument("--chunk", type=int, default=2)
    p.add_argument("--max-frames", type=int, default=None)
    p.add_argument("--warmup-frames", type=int, default=40,
                   help="frames run first to compile (enough keyframes to fill the local "
                        "map's window and marginalise from it; teddy: ~13 keyframes)")
    p.add_argument("--check", action="store_true", help="compare every run with it alone")
    p.add_argument("--out-json", type=Path, default=Path("docs/bench/batch.json"))
    p.add_argument("--out-md", type=Path, default=Path("docs/bench/batch.md"))
    args = p.parse_args(argv)
    if not args.sequence.is_dir():
        print(f"bench_batch: no sequence at {args.sequence}", file=sys.stderr)
        return 2
    seq = load_sequence(args.sequence)
    configs = batch.load_configs(args.configs) if args.configs else default_grid()
    one = [Config()]
    kw = {"chunk": args.chunk, "max_frames": args.max_frames, "progress": False}
    warm = {**kw, "max_frames": args.warmup_frames}
    _, compile_one = _timed(lambda: batch.evaluate([seq], one, **warm))
    _, compile_all = _timed(lambda: batch.evaluate([seq], configs, **warm))
    # compiles the runner's step
    run_sequence(seq, Config(), progress=False, max_frames=args.warmup_frames)
    r_one, t_one = _timed(lambda: batch.evaluate([seq], one, **kw))
    r_all, t_all = _timed(lambda: batch.evaluate([seq], configs, **kw))
    _, t_stream = _timed(lambda: run_sequence(seq, Config(), progress=False,
                                              max_frames=args.max_frames))
    frames = len(r_one.runs[0].results)
    runs = []
    for run in r_all.runs:
        row = summarise(run, seq)
        row["changed"] = batch.changed_fields(run.config)
        if args.check:
            alone = run_sequence(seq, run.config, progress=False, max_frames=args.max_frames)
            row["max_diff_alone_m"] = float(np.abs(alone.poses[:, :3, 3]
                                                   - run.poses[:, :3, 3]).max())
        runs.append(row)
    out = {
        "sequence": seq.name, "frames": frames, "configurations": len(configs),
        "chunk": args.chunk, "devices": r_all.devices,
        "machine": {"platform": platform.platform(), "python": platform.python_version(),
                    "jax": jax.__version__, "backend": jax.default_backend()},
        "compile_s": {"one": compile_one, "all": compile_all},
        "wall_s": {"one_batch": t_one, "all_batch": t_all, "one_streaming_runner": t_stream},
        "ratio_all_to_one_batch": t_all / t_one,
        "ratio_all_to_one_streaming": t_all / t_stream,
        "device_calls": r_all.calls, "lane_frames_solved": r_all.solved,
        "runs": runs,
    }
    lines = [
        f"# Batch of {len(configs)} configurations on {seq.name} ({frames} frames)",
        "",
        f"chunk {args.chunk}, devices {', '.join(r_all.devices)}; wall times include decoding "
        "and preprocessing, compilation excluded (done first on "
        f"{args.warmup_frames} frames: {compile_one:.1f} s for one configuration, "
        f"{compile_all:.1f} s for all).",
        "",
        "| what | wall (s) | ms per frame per configuration |",
        "|---|---:|---:|",
        f"| 1 configuration, batch.evaluate | {t_one:.2f} | {t_one / frames * 1e3:.1f} |",
        f"| 1 configuration, streaming runner | {t_stream:.2f} | {t_stream / frames * 1e3:.1f} |",
        f"| {len(configs)} configurations, batch.evaluate | {t_all:.2f} | "
        f"{t_all / frames / len(configs) * 1e3:.1f} |",
        "",
        f"{len(configs)} configurations cost {t_all / t_one:.2f}x one configuration's batch and "
        f"{t_all / t_stream:.2f}x its streaming run.",
        "",
        "| config | changed | ATE (m) | keyframes | lost |"
        + (" max diff alone (m) |" if args.check else ""),
        "|---:|---|---:|---:|---:|" + ("---:|" if args.check else ""),
    ]
    for r in runs:
        lines.append(f"| {r['config_index']} | {r['changed'] or 'defaults'} | "
                     f"{r.get('ate_rmse_m', float('nan')):.4f} | {r['keyframes']} | {r['lost']} |"
                     + (f" {r['max_diff_alone_m']:.1e} |" if args.check else ""))
    text = "\n".join(lines) + "\n"
    print(text)
    write_json(args.out_json, out)
    write_text(args.out_md, text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
