"""The ``edgevo`` command: ``edgevo run`` tracks a TUM sequence, ``edgevo eval`` scores one."""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

from .io import json_safe

BUNDLED_CLIP = Path(__file__).resolve().parent / "data" / "rgbd_dataset_freiburg1_xyz_first10"


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="edgevo", description="Edge-based RGB-D visual odometry (EdgeVO) in JAX."
    )
    sub = p.add_subparsers(dest="command", required=True)
    run = sub.add_parser("run", help="track a TUM RGB-D sequence and write its trajectory")
    run.add_argument("sequence", nargs="?", type=Path, default=None,
                     help="TUM sequence folder (default: the bundled fr1_xyz clip)")
    run.add_argument("--out", type=Path, default=None,
                     help="trajectory file (TUM format; default: <sequence>.traj.txt here)")
    run.add_argument("--stats", type=Path, default=None, help="write run statistics as JSON")
    run.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                     help="override a Config field (repeatable), e.g. --set max_edges=1024")
    run.add_argument("--max-frames", type=int, default=None, help="stop after this many frames")
    run.add_argument("--depth-factor", type=float, default=5000.0,
                     help="depth PNG units per metre (TUM: 5000)")
    run.add_argument("--intrinsics", type=float, nargs=4, default=None,
                     metavar=("FX", "FY", "CX", "CY"),
                     help="override the camera (then no undistortion is applied)")
    run.add_argument("--no-progress", action="store_true", help="no progress bar")
    ev = sub.add_parser("eval", help="ATE and RPE of a trajectory against ground truth")
    ev.add_argument("groundtruth", type=Path)
    ev.add_argument("estimate", type=Path)
    ev.add_argument("--json", action="store_true", help="print JSON")
    return p


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``edgevo`` console script."""
    args = _parser().parse_args(argv)
    try:
        if args.command == "run":
            return _run(args)
        return _eval(args)
    except (FileNotFoundError, ValueError) as err:
        print(f"edgevo: error: {err}", file=sys.stderr)
        return 2


def _run(args: argparse.Namespace) -> int:
    from .camera import Intrinsics
    from .config import Config
    from .datasets.tum import load_sequence
    from .runner import enable_compilation_cache, run_sequence, summarise

    config = Config().with_overrides(args.overrides)
    enable_compilation_cache()
    path = args.sequence if args.sequence is not None else BUNDLED_CLIP
    kwargs = {"depth_factor": args.depth_factor}
    if args.intrinsics is not None:
        kwargs["intrinsics"] = Intrinsics(*args.intrinsics)
    seq = load_sequence(path, **kwargs)
    out = args.out if args.out is not None else Path(f"{seq.name}.traj.txt")
    try:
        run = run_sequence(seq, config, out=out, progress=not args.no_progress,
                           max_frames=args.max_frames)
    except KeyboardInterrupt:
        print(f"edgevo: interrupted; the frames done so far are in {out}.part", file=sys.stderr)
        return 130
    stats = summarise(run, seq)
    if args.stats is not None:
        args.stats.parent.mkdir(parents=True, exist_ok=True)
        args.stats.write_text(json.dumps(json_safe(stats), indent=2) + "\n")
    print(_summary_text(stats, out))
    return 0


def _summary_text(stats: dict, out: Path) -> str:
    ms = stats["ms_per_frame"]
    lines = [
        f"sequence      {stats['sequence']}",
        f"frames        {stats['frames']}  (keyframes {stats['keyframes']}, lost {stats['lost']})",
        f"compile       {stats['compile_s']:.2f} s (first tracked frame)",
        f"ms/frame      median {ms['median']:.1f}  mean {ms['mean']:.1f}  p90 {ms['p90']:.1f}"
        "  (warm, decoding excluded)",
    ]
    if "ate_rmse_m" in stats:
        lines.append(f"ATE RMSE      {stats['ate_rmse_m']:.4f} m")
        rpe = stats.get("rpe_rmse_m_per_s")
        lines.append("RPE RMSE      " + ("n/a (sequence shorter than 1 s)" if rpe is None
                                         or math.isnan(rpe) else f"{rpe:.4f} m/s"))
    else:
        lines.append("ATE           n/a (" + stats.get("ground_truth_note", "no groundtruth.txt")
                     + ")")
    lines.append(f"trajectory    {out}")
    return "\n".join(lines)


def _eval(args: argparse.Namespace) -> int:
    from .io import read_trajectory
    from .metrics import ate, rpe

    gt_t, gt_p = read_trajectory(args.groundtruth)
    est_t, est_p = read_trajectory(args.estimate)
    a = ate(gt_t, gt_p, est_t, est_p)
    r = rpe(gt_t, gt_p, est_t, est_p)
    result = {"ate_rmse_m": a["rmse"], "ate_pairs": a["n"], "rpe_rmse_m_per_s":
              r["trans_rmse_m_per_s"], "rpe_rmse_deg_per_s": r["rot_rmse_deg_per_s"],
              "rpe_pairs": r["n"]}
    if args.json:
        print(json.dumps(json_safe(result)))
    else:
        print(f"ATE RMSE  {a['rmse']:.6f} m  ({a['n']} pairs)")
        if r["n"]:
            print(f"RPE RMSE  {r['trans_rmse_m_per_s']:.6f} m/s  "
                  f"{r['rot_rmse_deg_per_s']:.4f} deg/s  ({r['n']} pairs, 1 s apart)")
        else:
            print("RPE       n/a (no pose pairs 1 s apart)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
