"""The batch's throughput by lane count: frames per second over all lanes of one
``evaluate`` call, on whatever device JAX runs on (CPU or GPU).

Usage::

    python scripts/bench_lanes.py SEQ_DIR [--frames 60] [--warmup-frames 30]
                                  [--lanes 16,64] [--out-json F]

The lanes are the 4 x 4 grid of ``bench_batch.py`` (Huber radius x edge budget), repeated
with selection seeds 0, 1, ... up to the lane count. Each lane count is first run on
``--warmup-frames`` frames (compilation and warm-up, reported apart), then timed over
``--frames`` frames; wall times include decoding and preprocessing.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import platform
import sys
import time
from pathlib import Path

from edgevo_jax import Config, enable_batch_exact, evaluate, load_sequence
from edgevo_jax.reports import int_list, write_json


def main(argv: list[str] | None = None) -> int:
    enable_batch_exact()  # the CLI's arithmetic, before any JAX computation
    import jax

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("sequence", type=Path)
    p.add_argument("--frames", type=int, default=60)
    p.add_argument("--warmup-frames", type=int, default=30)
    p.add_argument("--lanes", type=int_list, default=[16, 64])
    p.add_argument("--out-json", type=Path, default=Path("docs/bench/lanes.json"))
    args = p.parse_args(argv)
    seq = load_sequence(args.sequence)
    grid = [Config(huber_delta=(h, h, h), num_edges=k) for h in (0.5, 1.0, 1.5, 2.0)
            for k in (256, 384, 512, 640)]
    out = {"machine": platform.platform(), "cpu_count": os.cpu_count(), "jax": jax.__version__,
           "backend": jax.default_backend(), "devices": [str(d) for d in jax.devices()],
           "sequence": seq.name, "frames": args.frames, "runs": []}
    for lanes in args.lanes:
        configs = [dataclasses.replace(c, seed=s) for s in range(-(-lanes // len(grid)))
                   for c in grid][:lanes]
        t0 = time.perf_counter()
        evaluate([seq], configs, max_frames=args.warmup_frames, progress=False)
        warm = time.perf_counter() - t0
        t0 = time.perf_counter()
        result = evaluate([seq], configs, max_frames=args.frames, progress=False)
        wall = time.perf_counter() - t0
        n = sum(len(r.results) for r in result.runs)
        row = {"lanes": lanes, "lane_frames": n, "wall_s": wall, "fps": n / wall,
               "ms_per_frame_per_lane": wall / n * 1e3, "warm_up_and_compile_s": warm,
               "lost": sum(f.state == "LOST" for r in result.runs for f in r.results)}
        out["runs"].append(row)
        print(f"{lanes:3d} lanes: {row['fps']:.1f} frames/s ({row['ms_per_frame_per_lane']:.1f} "
              f"ms per frame per lane; warm-up and compilation {warm:.0f} s)", flush=True)
        write_json(args.out_json, out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
