"""``edgevo eval``: ATE and RPE of a trajectory against ground truth, with evo's options
(``edgevo_jax.ate``, ``edgevo_jax.rpe``)."""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

from ..io import json_safe
from ._common import _read

ALIGN_CHOICES = ("se3", "sim3", "origin", "none")  # metrics.ALIGNMENTS (not imported at start)
DELTA_UNIT_CHOICES = {"f": "frames", "s": "seconds", "m": "metres"}  # metrics.DELTA_UNITS


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Add ``edgevo eval`` and its options to the subcommands ``sub``."""
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


def command(args: argparse.Namespace) -> int:
    """``edgevo eval``: check the options, print the ATE and RPE (as text or
    --json)."""
    from ..metrics import ate, rpe

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
    aligned = "no alignment" if args.align == "none" else f"{args.align} alignment"
    print(f"ATE ({aligned}{scale}, {a['n']} pairs; m)")
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

