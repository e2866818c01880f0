"""Truth first for ``edgevo calibrate``: copies of a clip with known camera errors injected
(``datasets.perturb.perturbed_copy``), each calibrated from its own frames, the estimate set
beside the truth.

Usage::

    python scripts/calibration_recovery.py CLIP [--max-frames N] [--cases a,b,...]
                                           [--out-json FILE]

Cases: ``none`` (the clip itself: the reference every other case is read against, since the
source's own camera is only nearly true), ``fx`` / ``fy`` (calibration.txt states fx / fy
1 % too large; fit them with ``--fit fx,fy,...``: the focal lengths are fitted on wide pairs),
``offset`` (depth timestamps 15 ms early: t_depth_true = t_file + 15 ms), ``scale`` (depth
divided by 1.03), ``readout`` (a global shutter given where the clip's camera reads out in
20 ms). Each case starts from the clip's camera (with the case's error) and fits
``--fit``; the table gives, per case, the injected parameter's truth, its estimate and
1-sigma, and how far every other parameter moved from the ``none`` case's estimate (in
units of its 1-sigma). Prints the table; writes JSON.
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
import tempfile
from collections.abc import Sequence
from pathlib import Path

from edgevo_jax import Config, enable_batch_exact
from edgevo_jax.datasets.perturb import perturbed_copy
from edgevo_jax.datasets.source import open_source
from edgevo_jax.io import json_safe
from edgevo_jax.learn.camera import PARAMS
from edgevo_jax.pipeline.calibrate import calibrate
from edgevo_jax.provenance import machine_info

#: case -> (perturbed_copy's arguments, the parameter it moves, its true change)
CASES = {
    "none": ({}, None, 0.0),
    "fx": ({"fx_factor": 1.01}, "fx", None),  # truth: the clip's fx (the copy states 1.01x)
    "fy": ({"fy_factor": 1.01}, "fy", None),
    "offset": ({"depth_time_offset_s": 0.015}, "depth_time_offset_s", 0.015),
    "scale": ({"depth_scale": 1.03}, "depth_scale", 1.03),
    "readout": ({}, "readout_s", None),  # truth: the clip's readout (started from 0)
}


def main(argv: Sequence[str] | None = None) -> int:
    """Make the copies, calibrate each, print and write the table."""
    argv = list(sys.argv[1:] if argv is None else argv)
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("clip", type=Path, help="a TUM folder with a camera the loader knows")
    p.add_argument("--max-frames", type=int, default=None)
    p.add_argument("--cases", default=",".join(CASES))
    p.add_argument("--fit", default="readout_s,depth_time_offset_s,depth_scale",
                   help="the parameters each case fits (calibrate's fit)")
    p.add_argument("--out-json", type=Path, default=Path("calibration_recovery.json"))
    args = p.parse_args(argv)
    enable_batch_exact()
    cases = [c.strip() for c in args.cases.split(",") if c.strip()]
    if "none" not in cases:
        cases.insert(0, "none")
    truth_seq = open_source(args.clip)
    readout = float(truth_seq.readout_s)
    rows = {}
    with tempfile.TemporaryDirectory() as tmp:
        for case in cases:
            kwargs, param, _ = CASES[case]
            # the copy keeps the clip's folder name (its camera preset) under a case folder
            folder = Path(tmp) / case / args.clip.name
            truth = perturbed_copy(args.clip, folder, **kwargs)
            seq = open_source(folder)
            start_readout = 0.0 if case == "readout" else readout
            cal = calibrate(seq, Config(readout_s=start_readout), max_frames=args.max_frames,
                            fit=tuple(args.fit.split(",")))
            fx, fy, cx, cy = truth.intrinsics
            true = dict(zip(PARAMS[:7], (fx, fy, cx, cy, truth.readout_s,
                                     truth.depth_time_offset_s, truth.depth_scale),
                            strict=True))
            est = dict(zip(PARAMS[:7], (*cal.camera.intrinsics, cal.camera.readout_s,
                                    cal.camera.depth_time_offset_s, cal.camera.depth_scale),
                           strict=True))
            rows[case] = {"param": param, "truth": true, "estimate": est, "sigma": cal.sigma,
                          "not_observable": cal.not_observable, "pairs": cal.pairs,
                          "seconds": cal.seconds}
            print(f"{case}: " + "; ".join(cal.lines()).replace("  ", " "), flush=True)
    ref = rows["none"]["estimate"]
    print("\ncase     parameter             truth      estimate   1-sigma   others moved "
          "(|change from 'none'| / sigma, max)")
    for case, row in rows.items():
        if case == "none":
            continue
        param, est, sig = row["param"], row["estimate"], row["sigma"]
        # the truth of the injected parameter, relative to the clip's own estimate where
        # the clip's camera is only nearly true (offset and scale: the injected change)
        truth = row["truth"][param]
        if case == "offset":
            truth = ref[param] + 0.015
        moved = {k: abs(est[k] - ref[k]) / sig[k] for k in sig if k != param and sig[k] > 0}
        worst = max(moved.items(), key=lambda kv: kv[1]) if moved else ("-", 0.0)
        s = sig.get(param)
        print(f"{case:8s} {param:20s} {truth:10.5g} {est[param]:10.5g} "
              f"{'not observable' if s is None else f'{s:9.3g}'}   {worst[0]} {worst[1]:.2f}"
              f"   (estimate - none's: {est[param] - ref[param]:.4g})")
        row["from_reference"] = est[param] - ref[param]
        row["truth_used"] = truth
        row["others_moved_sigmas"] = moved
    result = {"command": shlex.join(["python", "scripts/calibration_recovery.py", *argv]),
              "machine": machine_info(), "clip": str(args.clip), "cases": rows}
    args.out_json.parent.mkdir(parents=True, exist_ok=True)
    args.out_json.write_text(json.dumps(json_safe(result), indent=1) + "\n")
    print(f"wrote {args.out_json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
