"""The time ``calibrate`` takes on N frames, compilation included: a clip played forward and
back to N frames (``datasets.pingpong``), calibrated in this process from its start.

Usage::

    EDGEVO_CACHE_DIR=DIR python scripts/bench_calibrate.py CLIP [--frames 300]
                                                           [--out-json FILE]

Run it twice with one new ``EDGEVO_CACHE_DIR``: the first run is cold (every program
compiled), the second warm (the tracker's programs loaded from DIR; the calibration's own
solve compiles each time). Prints the times; writes JSON.
"""

from __future__ import annotations

import argparse
import shlex
import sys
import time
from collections.abc import Sequence
from pathlib import Path

from edgevo_jax import Config, enable_batch_exact
from edgevo_jax.datasets.pingpong import pingpong
from edgevo_jax.datasets.tum import load_sequence
from edgevo_jax.pipeline.calibrate import calibrate
from edgevo_jax.provenance import machine_info
from edgevo_jax.reports import write_json


def main(argv: Sequence[str] | None = None) -> int:
    """Calibrate the clip played to ``--frames`` frames; print and write the times."""
    argv = list(sys.argv[1:] if argv is None else argv)
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("clip", type=Path)
    p.add_argument("--frames", type=int, default=300)
    p.add_argument("--out-json", type=Path, default=Path("bench_calibrate.json"))
    args = p.parse_args(argv)
    enable_batch_exact()
    t0 = time.perf_counter()
    seq = pingpong(load_sequence(args.clip), args.frames)
    cal = calibrate(seq, Config(), progress=True)
    total = time.perf_counter() - t0
    print("\n".join(cal.lines()))
    print(f"{args.frames} frames: {total:.1f} s in all (tracking {cal.seconds['tracking']:.1f} "
          f"s, pairs and solving {cal.seconds['solving']:.1f} s; rounds "
          f"{len(cal.source['tracked_with_readout_s'])})")
    write_json(args.out_json, {
        "command": shlex.join(["python", "scripts/bench_calibrate.py", *argv]),
        "machine": machine_info(), "clip": str(args.clip), "frames": args.frames,
        "seconds": total, "parts": cal.seconds, "readout_s": cal.camera.readout_s,
        "sigma": cal.sigma, "rounds": len(cal.source["tracked_with_readout_s"])})
    return 0


if __name__ == "__main__":
    sys.exit(main())
