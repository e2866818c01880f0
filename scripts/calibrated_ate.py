"""Does a calibration pay? Track a sequence with several cameras over seeds and frame rates
and compare the ATE.

Usage::

    python scripts/calibrated_ate.py SEQ --camera NAME=SPEC [--camera NAME=SPEC ...]
                                     [--seeds 0,1,2,3,4] [--frame-steps 1,2,3]
                                     [--max-frames N] [--out-json FILE]

SPEC: ``folder`` (the camera the folder gives: its calibration.txt, else its name), a preset
name (``fr1``, ...), or a file for ``--calibration`` (fx fy cx cy [k...] or a camera
file, .toml). Each camera tracks the sequence (the first ``--max-frames`` frames' span at
each frame step) with the default Config and each seed. Prints the mean ATE (mm) per camera
and frame step with its spread over seeds, and the ratio to the first camera; writes JSON.
"""

from __future__ import annotations

import argparse
import shlex
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from edgevo_jax import Config, enable_batch_exact
from edgevo_jax.camera import CAMERAS
from edgevo_jax.datasets.tum import read_calibration
from edgevo_jax.pipeline.measure import accuracy, load_clip
from edgevo_jax.pipeline.run import run_sequence
from edgevo_jax.provenance import machine_info
from edgevo_jax.reports import int_list, write_json


def camera_of(spec: str):
    """``load_sequence``'s camera for a SPEC (module doc); None: the folder's own."""
    if spec == "folder":
        return None
    if spec in CAMERAS:
        return spec
    return read_calibration(Path(spec))


def main(argv: Sequence[str] | None = None) -> int:
    """Track with each camera, seed and frame step; print and write the table."""
    argv = list(sys.argv[1:] if argv is None else argv)
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("sequence", type=Path)
    p.add_argument("--camera", action="append", required=True, metavar="NAME=SPEC")
    p.add_argument("--seeds", type=int_list, default=[0, 1, 2, 3, 4])
    p.add_argument("--frame-steps", type=int_list, default=[1])
    p.add_argument("--max-frames", type=int, default=None)
    p.add_argument("--out-json", type=Path, default=Path("calibrated_ate.json"))
    args = p.parse_args(argv)
    enable_batch_exact()
    cameras = dict(c.split("=", 1) for c in args.camera)
    rows: dict[str, dict[str, list[float]]] = {}
    for name, spec in cameras.items():
        camera = camera_of(spec)
        for step in args.frame_steps:
            seq = load_clip(args.sequence, frame_step=step, max_frames=args.max_frames,
                            camera=camera)
            ates = []
            for seed in args.seeds:
                run = run_sequence(seq, Config(seed=seed), progress=False)
                ates.append(accuracy(seq.groundtruth, run.timestamps, run.poses)["ate_rmse_m"])
            rows.setdefault(name, {})[str(step)] = ates
            print(f"{name:12s} every {step}: ATE mm " + " ".join(f"{1e3 * a:.1f}" for a in ates)
                  + f"  mean {1e3 * np.mean(ates):.2f}", flush=True)
    first = next(iter(rows))
    print(f"\ncamera       step  mean ATE mm (min-max over seeds {args.seeds})  / {first}")
    for name, by_step in rows.items():
        for step, ates in by_step.items():
            ratio = np.mean(ates) / np.mean(rows[first][step])
            print(f"{name:12s} {step:>4s}  {1e3 * np.mean(ates):6.2f} ({1e3 * min(ates):.1f}-"
                  f"{1e3 * max(ates):.1f})  {ratio:.3f}")
    write_json(args.out_json, {
        "command": shlex.join(["python", "scripts/calibrated_ate.py", *argv]),
        "machine": machine_info(), "sequence": str(args.sequence), "cameras": cameras,
        "seeds": args.seeds, "ate_m": rows})
    print(f"wrote {args.out_json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
