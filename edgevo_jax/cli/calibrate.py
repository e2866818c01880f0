"""``edgevo calibrate``: estimate a camera from its own recording (no target, no ground
truth) and write it as a camera file that ``edgevo run --calibration`` takes."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from ..camera import CAMERAS
from ..io import check_output
from ._common import _positive_float, _positive_int


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Add ``edgevo calibrate`` and its options to the subcommands ``sub``."""
    p = sub.add_parser(
        "calibrate", help="estimate the camera (rolling-shutter readout, depth time offset) from a "
        "recording and write a camera file",
        description="Track the recording with the starting camera, then solve the camera "
        "jointly with the tracked poses on the tracker's own cost. Parameters the motion "
        "cannot reveal are reported as not observable and kept at their start. Writes a "
        "camera file (docs/camera_file.md) for `edgevo run --calibration`.")
    p.add_argument("sequence", type=Path,
                   help="a TUM or ETH3D folder (edgevo run's folder sources)")
    p.add_argument("--out", type=Path, default=Path("camera.toml"),
                   help="the camera file to write (default: camera.toml)")
    p.add_argument("--max-frames", type=_positive_int, default=300, metavar="N",
                   help="calibrate from the first N frames (default 300)")
    p.add_argument("--frame-step", type=_positive_int, default=1, metavar="K",
                   help="keep every K-th frame")
    p.add_argument("--depth-factor", type=_positive_float, default=5000.0,
                   help="depth PNG units per metre (TUM: 5000)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override a Config field of the tracking (repeatable); "
                        "readout_s=SECONDS sets the starting readout")
    p.add_argument("--fit", default=None, metavar="NAMES",
                   help="comma-separated parameters to estimate, of fx, fy, cx, cy, "
                        "readout_s, depth_time_offset_s (default: readout_s,"
                        "depth_time_offset_s; fx and fy are fitted on frames 5-15 deg apart, "
                        "opt-in: on the fr1 clip fx came out 4 %% off; depth_scale is never "
                        "observable from one RGB-D camera)")
    p.add_argument("--rounds", type=_positive_int, default=3, metavar="N",
                   help="at most N rounds of tracking and solving: another round tracks "
                        "again with the readout found while it moved by more than 2 ms "
                        "(default 3)")
    cam = p.add_argument_group(
        "starting camera", "as for edgevo run: a folder's calibration.txt or the camera its "
        "name names, or one of these").add_mutually_exclusive_group()
    cam.add_argument("--camera", choices=list(CAMERAS), default=None, help="a preset")
    cam.add_argument("--calibration", type=Path, default=None, metavar="FILE",
                     help="fx fy cx cy [k1 k2 p1 p2 k3], or a camera file FILE.toml")
    cam.add_argument("--intrinsics", type=float, nargs=4, default=None,
                     metavar=("FX", "FY", "CX", "CY"), help="a pinhole of undistorted images")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def command(args: argparse.Namespace) -> int:
    """``edgevo calibrate``: calibrate, print the estimates, write the camera file."""
    from ..config import Config
    from ..datasets.source import SourceError, open_source
    from ..runs.calibrate import DEFAULT_FIT, calibrate
    from .run import _camera

    check_output(args.out, what="--out")
    fit = DEFAULT_FIT if args.fit is None else tuple(s.strip() for s in args.fit.split(",")
                                                if s.strip())
    config = Config().with_overrides(args.overrides)
    try:
        seq = open_source(args.sequence, **_camera(args), depth_factor=args.depth_factor,
                          frame_step=args.frame_step, max_frames=args.max_frames)
    except SourceError as err:
        raise ValueError(err.cli_message()) from None
    t0 = time.perf_counter()
    print("edgevo calibrate: programs compile once per configuration (15-40 s here on a "
          "first run)", file=sys.stderr)
    result = calibrate(seq, config, max_frames=args.max_frames, fit=fit, rounds=args.rounds,
                       progress=not args.no_progress,
                       log=lambda s: print(f"edgevo calibrate: {s}", file=sys.stderr))
    result.write(args.out)
    print(f"camera of {seq.name} from {result.pairs} frame-keyframe pairs "
          f"({result.keyframes} keyframes); cost per pair {result.cost_before:.1f} -> "
          f"{result.cost_after:.1f}")
    print("\n".join(result.lines()))
    print(f"wrote {args.out} in {time.perf_counter() - t0:.0f} s (tracking "
          f"{result.seconds['tracking']:.0f} s, solving {result.seconds['solving']:.0f} s); "
          f"use it with: edgevo run {args.sequence} --calibration {args.out}")
    return 0
