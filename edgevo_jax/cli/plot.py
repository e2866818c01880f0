"""``edgevo plot``: one figure as a PNG (trajectory, frame, selection, configs; the
figures themselves are ``edgevo_jax.viz``'s)."""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

from ..datasets import BUNDLED_CLIP
from ..io import check_output
from ._common import _read


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Add ``edgevo plot`` and its figures' options to the subcommands ``sub``."""
    plot = sub.add_parser("plot", help="draw a figure as a PNG (needs matplotlib)",
                          description="Draw one figure as a PNG (needs matplotlib: "
                                      "pip install 'edgevo_jax[viz]').")
    kinds = plot.add_subparsers(dest="figure", required=True)

    def common(p: argparse.ArgumentParser, default_out: str) -> None:
        p.add_argument("--out", type=Path, default=Path(default_out),
                       help=f"PNG file to write (default: {default_out})")
        p.add_argument("--dpi", type=float, default=100.0,
                       help="pixels per inch of the PNG (default: 100)")

    def frame_args(p: argparse.ArgumentParser) -> None:
        p.add_argument("sequence", nargs="?", type=Path, default=None,
                       help="TUM sequence folder (default: the bundled fr1_xyz clip)")
        p.add_argument("--index", type=int, default=0,
                       help="frame index among the associated rgb-depth pairs (default: 0)")
        p.add_argument("--set", dest="overrides", action="append", default=[],
                       metavar="KEY=VALUE", help="override a Config field (repeatable)")

    tr = kinds.add_parser("trajectory", help="estimate vs ground truth, coloured by error")
    tr.add_argument("groundtruth", type=Path, help="ground-truth trajectory (TUM format)")
    tr.add_argument("estimate", type=Path, help="estimated trajectory (TUM format)")
    tr.add_argument("--plane", default="xy",
                    help="axes of the top view, two of x, y, z (default: xy)")
    tr.add_argument("--title", default=None, help="title (default: the estimate's file name)")
    common(tr, "trajectory.png")

    fr = kinds.add_parser("frame", help="gray image, Canny edges, distance-field pyramid")
    frame_args(fr)
    common(fr, "frame.png")

    se = kinds.add_parser("selection", help="edges selected by each mode over the image")
    frame_args(se)
    se.add_argument("--modes", default="spg,greedy",
                    help="comma-separated selection modes, one panel each (default: "
                         "spg,greedy; also random, all)")
    se.add_argument("--no-candidates", action="store_true",
                    help="leave out the panel of all culled candidate edges")
    common(se, "selection.png")

    co = kinds.add_parser(
        "configs", help="accuracy vs time and edges used across configurations",
        description="Accuracy vs time per frame, and edges used vs accuracy, across "
                    "configurations, from the selection ablation's JSON (docs/ablation), "
                    "scripts/bench.py JSON, or `edgevo run --stats` JSON files.")
    co.add_argument("results", type=Path, nargs="+",
                    help="ablation.json, bench.json or run-statistics JSON file(s)")
    common(co, "configs.png")

    mp = kinds.add_parser("map", help="a saved keyframe map's edges from above and the side")
    mp.add_argument("file", type=Path, help="a map file written by --save-map")
    mp.add_argument("--planes", default="xy,xz",
                    help="axes of each panel, two of x, y, z each (default: xy,xz)")
    mp.add_argument("--title", default=None, help="title (default: its size)")
    mp.add_argument("--max-depth", type=float, default=None, metavar="M",
                    help="only edges nearer than M metres to their keyframe's camera")
    common(mp, "map.png")


def command(args: argparse.Namespace) -> int:
    """``edgevo plot FIGURE``: draw the figure, print where it went."""
    from .. import viz

    try:
        viz.require_matplotlib()
    except ImportError as err:
        print(f"edgevo: error: {err}", file=sys.stderr)
        return 2
    if not (args.dpi > 0 and math.isfinite(args.dpi)):
        raise ValueError(f"--dpi must be positive, got {args.dpi}")
    check_output(args.out, what="--out", make_folders=True)  # before anything is drawn
    out = {"trajectory": _plot_trajectory, "frame": _plot_frame,
           "selection": _plot_selection, "configs": _plot_configs,
           "map": _plot_map}[args.figure](args)
    print(f"wrote {out}")
    return 0


def _plot_trajectory(args: argparse.Namespace) -> Path:
    from ..viz import plot_trajectory

    gt_t, gt_p = _read(args.groundtruth, "ground-truth")
    est_t, est_p = _read(args.estimate, "estimated")
    return plot_trajectory(gt_t, gt_p, est_t, est_p, args.out, plane=args.plane,
                           title=args.title or args.estimate.name, dpi=args.dpi)


def _load_frame(args: argparse.Namespace):
    """(sequence, config, rgb, depth, frame) of ``args.index`` of ``args.sequence``."""
    from ..config import Config
    from ..datasets.tum import load_sequence
    from ..image.preprocess import preprocess

    config = Config().with_overrides(args.overrides)
    seq = load_sequence(args.sequence if args.sequence is not None else BUNDLED_CLIP)
    if not -len(seq) <= args.index < len(seq):
        raise ValueError(f"--index {args.index} out of range: {seq.name} has {len(seq)} "
                         "associated frames")
    rgb, depth = seq.load_frame(args.index)
    return seq, config, rgb, depth, preprocess(rgb, depth, config)


def _plot_frame(args: argparse.Namespace) -> Path:
    from ..image.preprocess import to_gray
    from ..viz import plot_frame

    seq, config, rgb, _, frame = _load_frame(args)
    title = (f"{seq.name}, frame {args.index}: Canny {config.canny_low:g}/{config.canny_high:g}"
             f", {len(frame.dist)}-level distance-field pyramid")
    return plot_frame(to_gray(rgb), frame, args.out, title=title, dpi=args.dpi)


def _plot_selection(args: argparse.Namespace) -> Path:
    import numpy as np

    from ..config import SELECTIONS
    from ..frontend.selection import candidates, select
    from ..image.preprocess import to_gray
    from ..viz import plot_selection_overlay

    modes = list(dict.fromkeys(m.strip() for m in args.modes.split(",") if m.strip()))
    bad = [m for m in modes if m not in SELECTIONS]
    if bad or not modes:
        raise ValueError(f"--modes: unknown selection mode(s) {', '.join(bad) or '(none)'}; "
                         f"choose from {', '.join(SELECTIONS)}")
    seq, config, rgb, _, frame = _load_frame(args)
    cands = candidates(frame, config)
    h, w = frame.shape
    panels = {} if args.no_candidates else {"candidates (culled)": cands.uv}
    for mode in modes:
        idx = select(cands, config.replace(selection=mode), T_prior=np.eye(4),
                     intr=seq.intrinsics, width=w, height=h, seed=config.seed)
        panels[mode] = cands.uv[:, idx]
    title = (f"{seq.name}, frame {args.index}: edges selected at num_edges={config.num_edges} "
             f"(prior motion identity, seed {config.seed})")
    return plot_selection_overlay(to_gray(rgb), panels, args.out, title=title, dpi=args.dpi)


def _plot_configs(args: argparse.Namespace) -> Path:
    from ..viz import plot_ablation, plot_benchmark, read_results

    kind, records = read_results(args.results)
    if kind == "bench":
        return plot_benchmark(records, args.out, dpi=args.dpi)
    return plot_ablation(records, args.out, dpi=args.dpi)


def _plot_map(args: argparse.Namespace) -> Path:
    from ..map.export import map_cloud
    from ..viz.map import plot_map

    planes = tuple(p.strip() for p in args.planes.split(",") if p.strip())
    return plot_map(map_cloud(args.file, max_depth=args.max_depth), args.out, planes=planes,
                    title=args.title, dpi=args.dpi)
