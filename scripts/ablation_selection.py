"""Edge-selection ablation: accuracy and speed of spg / greedy / random / all per edge budget.

Usage::

    python scripts/ablation_selection.py [SEQ_DIR ...] [--out-dir docs/ablation]
        [--max-frames N] [--seeds 0,1,2] [--num-edges 128,256,512,1024]
        [--modes spg,greedy,random,all]

Default sequences: the shared TUM clips in ``../shared/data/tum`` (next to the repository).

What is run: for each sequence, ``selection=all`` once (every culled edge; deterministic, so
no seeds and no budget), and every stochastic mode (``spg``: stochastic partition greedy,
``greedy``: stochastic greedy without partitions, ``random``: a uniform subset) for every
edge budget (``Config.num_edges``) and every seed (``Config.seed``), each through
``edgevo_jax.runs.run.run_sequence`` (the pipelined runner, no progress bar) and ``summarise``.
All other settings are the ``Config`` defaults. The seed rounds are the outer loop, so a
drift in machine load spreads over every configuration instead of hitting one.

What is measured, per run:

- ATE RMSE (m; TUM's ``evaluate_ate``, rigid alignment to the ground truth);
- warm time per frame (ms; median over frames from the third on: frame 0 only becomes the
  keyframe, frame 1 compiles), wall time with PNG decoding excluded and undistortion,
  preprocessing, selection and solve included. It depends on the machine and on its load:
  compare configurations within one invocation, not across machines or days;
- edges used (mean number of keyframe edges the solve used per frame), edge-selection time
  per keyframe (ms, median over the keyframes after the first, whose selection may include
  compiling the selection program; null with a single keyframe), keyframes and lost frames.

Compiled XLA programs are kept on disk like the CLI does (``EDGEVO_CACHE_DIR``, default
``~/.cache/edgevo_jax``; empty string: off), so that runs which differ only in the seed
do not compile again; compilation never enters the warm times, only ``startup_s``.

Aggregates over seeds, per (sequence, mode, budget): mean and std (ddof 1; null for one
run) of the ATE, median of the per-run median times, mean of the edges used, median of the
per-run median selection times.

Outputs (in ``--out-dir``): ``ablation.json`` (every run, the aggregates, the command line,
date and machine information, the load average before and after; NaN written as null),
``ablation_<sequence>.png`` (``edgevo_jax.viz.plot_ablation``: EdgeVO Fig. 6 and Fig. 1d),
and for the first sequence ``selection_<sequence>.png`` (Fig. 5): the culled candidates of
frame 0 and the edges spg, greedy and random pick from them at the default budget (prior
motion = identity, seed 0), with a spread measure of each (occupied 32 px cells, mean
distance to the nearest other selected edge) in the JSON. One line per run goes to stderr as
it finishes, the final markdown table to stdout.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import math
import shlex
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from edgevo_jax import enable_batch_exact
from edgevo_jax.config import SELECTIONS, Config
from edgevo_jax.datasets.tum import SHARED_CLIPS as DEFAULT_CLIPS
from edgevo_jax.datasets.tum import SHARED_TUM, TumSequence, load_sequence
from edgevo_jax.frontend.selection import candidates, select
from edgevo_jax.image.preprocess import preprocess, to_gray
from edgevo_jax.programs import enable_cache
from edgevo_jax.provenance import load_average, machine_info
from edgevo_jax.reports import fmt, int_list, write_json
from edgevo_jax.reports import markdown_table as md_table
from edgevo_jax.runs.measure import finite_stats
from edgevo_jax.runs.run import run_sequence, summarise
from edgevo_jax.viz import plot_ablation, plot_selection_overlay

REPO_ROOT = Path(__file__).resolve().parents[1]
STOCHASTIC = ("spg", "greedy", "random")
MODE_ORDER = ("spg", "greedy", "random", "all")
SPREAD_CELL = 32  # px: cell size of the spread measure of the selection figure


def _fmt(value: float | None, spec: str) -> str:
    return fmt(value, spec, missing="-")


# ---------------------------------------------------------------------------- arguments


def _mode_list(text: str) -> list[str]:
    modes = [s.strip() for s in text.split(",") if s.strip()]
    bad = [m for m in modes if m not in SELECTIONS]
    if bad or not modes:
        raise argparse.ArgumentTypeError(
            f"unknown selection mode(s) {', '.join(bad) or '(none)'}; "
            f"choose from {', '.join(SELECTIONS)}")
    return list(dict.fromkeys(modes))


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        description="Edge-selection ablation (spg / greedy / random / all) on TUM RGB-D clips.")
    p.add_argument("sequences", nargs="*", type=Path, metavar="SEQ_DIR",
                   help=f"TUM sequence folders (default: the clips in {SHARED_TUM})")
    p.add_argument("--out-dir", type=Path, default=Path("docs/ablation"),
                   help="folder for ablation.json and the PNGs (default: docs/ablation)")
    p.add_argument("--max-frames", type=int, default=None,
                   help="use at most this many frames per sequence (default: all)")
    p.add_argument("--seeds", type=int_list, default=[0, 1, 2],
                   help="seeds for the stochastic modes, 0,1,2 or 0-2 (default: 0,1,2)")
    p.add_argument("--num-edges", type=int_list, default=[128, 256, 512, 1024],
                   help="comma-separated edge budgets (default: 128,256,512,1024)")
    p.add_argument("--modes", type=_mode_list, default=list(MODE_ORDER),
                   help="comma-separated selection modes (default: spg,greedy,random,all)")
    return p


def default_sequences() -> list[Path]:
    """The shared clips; SystemExit with the expected location when the folder is absent."""
    if not SHARED_TUM.is_dir():
        raise SystemExit(
            f"error: no sequences given and the shared TUM clips folder {SHARED_TUM} does not "
            "exist; pass TUM sequence folders (SEQ_DIR ...)")
    found = [SHARED_TUM / name for name in DEFAULT_CLIPS if (SHARED_TUM / name).is_dir()]
    if not found:
        raise SystemExit(f"error: none of {', '.join(DEFAULT_CLIPS)} found in {SHARED_TUM}; "
                         "pass TUM sequence folders (SEQ_DIR ...)")
    return found


# ---------------------------------------------------------------------------- runs


def plan(modes: Sequence[str], num_edges: Sequence[int], seeds: Sequence[int]
         ) -> list[tuple[str, int | None, int]]:
    """(mode, budget or None for ``all``, seed) of every run, in run order: ``all`` first
    (once), then one round per seed over every budget and stochastic mode."""
    runs: list[tuple[str, int | None, int]] = []
    if "all" in modes:
        runs.append(("all", None, seeds[0]))
    for seed in seeds:
        for n in num_edges:
            for mode in MODE_ORDER:
                if mode in modes and mode in STOCHASTIC:
                    runs.append((mode, n, seed))
    return runs


def config_for(mode: str, num_edges: int | None, seed: int) -> Config:
    """The default Config with this selection mode, budget (kept for ``all``) and seed."""
    cfg = Config().replace(selection=mode, seed=seed)
    return cfg if num_edges is None else cfg.replace(num_edges=num_edges)


def one_run(seq: TumSequence, mode: str, num_edges: int | None, seed: int,
            max_frames: int | None) -> dict[str, Any]:
    """Track ``seq`` with one configuration; the run's row."""
    cfg = config_for(mode, num_edges, seed)
    t0 = time.perf_counter()
    run = run_sequence(seq, cfg, progress=False, max_frames=max_frames)
    wall_s = time.perf_counter() - t0
    s = summarise(run, seq)
    # the first keyframe's selection compiles the selection program: leave it out
    select_ms = [r.select_ms for r in run.results if r.select_ms is not None]
    return {
        "sequence": seq.name,
        "selection": mode,
        "num_edges": num_edges,
        "seed": seed,
        "frames": s["frames"],
        "keyframes": s["keyframes"],
        "lost": s["lost"],
        "ate_rmse_m": s.get("ate_rmse_m", math.nan),
        "rpe_rmse_m_per_s": s.get("rpe_rmse_m_per_s", math.nan),
        "ms_per_frame_median": s["ms_per_frame"]["median"],
        "ms_per_frame_p90": s["ms_per_frame"]["p90"],
        "preprocess_ms_median": s["preprocess_ms"]["median"],
        "solve_wait_ms_median": s["solve_wait_ms"]["median"],
        "select_ms_median": finite_stats(select_ms[1:])["median"],
        "select_ms_first": select_ms[0] if select_ms else math.nan,
        "edges_used_mean": s["edges_used_mean"],
        "startup_s": s["startup_s"],
        "wall_s": wall_s,
        **({"ground_truth_note": s["ground_truth_note"]} if "ground_truth_note" in s else {}),
    }


def aggregate(rows: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """One record per (sequence, mode, budget): statistics over its seeds (see module doc)."""
    groups: dict[tuple[str, str, int | None], list[dict[str, Any]]] = {}
    for r in rows:
        groups.setdefault((r["sequence"], r["selection"], r["num_edges"]), []).append(r)
    out = []
    for (seq, mode, n), rs in groups.items():
        ate = finite_stats([r["ate_rmse_m"] for r in rs])
        over = {k: finite_stats([r[k] for r in rs]) for k in (
            "edges_used_mean", "ms_per_frame_median", "select_ms_median", "keyframes")}
        out.append({
            "sequence": seq,
            "selection": mode,
            "num_edges": n,
            "runs": len(rs),
            "seeds": [r["seed"] for r in rs],
            "edges_used_mean": over["edges_used_mean"]["mean"],
            "ms_per_frame_median": over["ms_per_frame_median"]["median"],
            "ate_rmse_m_mean": ate["mean"],
            "ate_rmse_m_std": ate["std"],
            "ate_rmse_m_min": ate["min"],
            "ate_rmse_m_max": ate["max"],
            "select_ms_median": over["select_ms_median"]["median"],
            "keyframes_mean": over["keyframes"]["mean"],
            "lost_total": int(sum(r["lost"] for r in rs)),
        })
    seq_rank = {seq: i for i, seq in enumerate(dict.fromkeys(r["sequence"] for r in rows))}
    # sequences in run order, then spg, greedy, random, all, budgets ascending
    return sorted(out, key=lambda r: (seq_rank[r["sequence"]], MODE_ORDER.index(r["selection"]),
                                      -1 if r["num_edges"] is None else r["num_edges"]))


def _progress_line(k: int, total: int, row: dict[str, Any]) -> str:
    budget = "all" if row["num_edges"] is None else row["num_edges"]
    return (f"[{k}/{total}] {row['sequence']} {row['selection']:>6} n={budget!s:>5} "
            f"seed={row['seed']}: ATE {_fmt(row['ate_rmse_m'] * 1e3, '7.2f')} mm, "
            f"{_fmt(row['ms_per_frame_median'], '6.1f')} ms/frame, "
            f"edges {_fmt(row['edges_used_mean'], '6.0f')}, "
            f"select {_fmt(row['select_ms_median'], '6.1f')} ms, kf {row['keyframes']}, "
            f"lost {row['lost']} ({row['wall_s']:.1f} s)")


def markdown_table(records: Sequence[dict[str, Any]]) -> str:
    """The aggregates as a markdown table (ATE in mm, times in ms)."""
    rows = []
    for r in records:
        std = _fmt(r["ate_rmse_m_std"] * 1e3, ".2f")
        rows.append([
            r["sequence"], r["selection"], "-" if r["num_edges"] is None else str(r["num_edges"]),
            _fmt(r["edges_used_mean"], ".0f"),
            _fmt(r["ate_rmse_m_mean"] * 1e3, ".2f") + ("" if std == "-" else f" ± {std}"),
            _fmt(r["ms_per_frame_median"], ".1f"), _fmt(r["select_ms_median"], ".1f"),
            _fmt(r["keyframes_mean"], ".1f"), str(r["runs"])])
    return md_table(("sequence", "selection", "budget", "edges used", "ATE mm (mean ± std)",
                     "ms / frame", "select ms", "keyframes", "runs"), rows, align="llrrrrrrr")


# ---------------------------------------------------------------------------- Fig. 5


def spread(uv: np.ndarray, width: int, height: int, cell: int = SPREAD_CELL) -> dict[str, Any]:
    """How spread out points uv (2, N) are: occupied ``cell`` px cells (count and fraction
    of all cells) and the mean distance (px) from each point to its nearest other point."""
    n = uv.shape[1]
    cols, rows = -(-width // cell), -(-height // cell)
    if n == 0:
        return {"points": 0, "cells_occupied": 0, "cells_total": cols * rows,
                "cells_fraction": 0.0, "nn_distance_px_mean": math.nan}
    cu = np.clip(np.round(uv[0]).astype(int) // cell, 0, cols - 1)
    cv = np.clip(np.round(uv[1]).astype(int) // cell, 0, rows - 1)
    occupied = int(np.unique(cv * cols + cu).size)
    nn = math.nan
    if 1 < n <= 20000:
        # blockwise brute force: N x N distances in chunks of rows
        best = np.full(n, np.inf)
        for lo in range(0, n, 512):
            d = np.hypot(uv[0, lo:lo + 512, None] - uv[0, None],
                         uv[1, lo:lo + 512, None] - uv[1, None])
            d[np.arange(d.shape[0]), np.arange(lo, lo + d.shape[0])] = np.inf
            best[lo:lo + 512] = d.min(axis=1)
        nn = float(best.mean())
    return {"points": n, "cells_occupied": occupied, "cells_total": cols * rows,
            "cells_fraction": occupied / (cols * rows), "nn_distance_px_mean": nn}


def selection_figure(seq: TumSequence, modes: Sequence[str], path: Path) -> dict[str, Any]:
    """Fig. 5: frame 0's culled candidates and the edges each mode picks (default budget,
    T_prior = identity, seed 0). Returns the figure's description with the spread of each."""
    cfg = Config()
    rgb, depth = seq.load_frame(0)
    frame = preprocess(rgb, depth, cfg)
    cands = candidates(frame, cfg)
    h, w = frame.shape
    selections: dict[str, np.ndarray] = {"candidates (culled)": cands.uv}
    for mode in modes:
        idx = select(cands, cfg.replace(selection=mode), T_prior=np.eye(4),
                     intr=seq.intrinsics, width=w, height=h, seed=0)
        selections[mode] = cands.uv[:, idx]
    out = plot_selection_overlay(
        to_gray(rgb), selections, path,
        title=f"{seq.name}, frame 0: edges selected at num_edges={cfg.num_edges} "
              "(prior motion identity, seed 0)")
    return {
        "path": out.name,
        "sequence": seq.name,
        "frame": 0,
        "num_edges": cfg.num_edges,
        "seed": 0,
        "spread_cell_px": SPREAD_CELL,
        "spread": {name: spread(uv, w, h) for name, uv in selections.items()},
    }


# ---------------------------------------------------------------------------- main




def main(argv: list[str] | None = None) -> int:
    """Run the ablation; returns the exit status."""
    enable_batch_exact()  # the CLI's arithmetic: trajectories as `edgevo run` gives them
    from_cli = argv is None
    argv = sys.argv[1:] if argv is None else list(argv)
    args = _parser().parse_args(argv)
    if args.max_frames is not None and args.max_frames < 3:
        raise SystemExit("error: --max-frames must be at least 3 (ATE needs 3 frames)")
    if any(n < 1 for n in args.num_edges):
        raise SystemExit("error: --num-edges must be positive")
    seq_dirs = args.sequences or default_sequences()
    for d in seq_dirs:
        if not d.is_dir():
            raise SystemExit(f"error: sequence folder not found: {d}")
    out_dir: Path = args.out_dir
    out_dir.mkdir(parents=True, exist_ok=True)

    cache_dir = enable_cache()
    started = datetime.datetime.now(datetime.UTC)
    load_before = load_average()
    runs = plan(args.modes, args.num_edges, args.seeds)
    total = len(runs) * len(seq_dirs)
    print(f"{len(seq_dirs)} sequence(s) x {len(runs)} runs; modes {','.join(args.modes)}, "
          f"budgets {args.num_edges}, seeds {args.seeds}, max frames {args.max_frames}",
          file=sys.stderr, flush=True)
    rows: list[dict[str, Any]] = []
    figures: dict[str, Any] = {}
    k = 0
    for i, d in enumerate(seq_dirs):
        seq = load_sequence(d)
        if i == 0:
            fig_modes = [m for m in STOCHASTIC if m in args.modes] or list(STOCHASTIC)
            figures["selection"] = selection_figure(
                seq, fig_modes, out_dir / f"selection_{seq.name}.png")
            print(f"wrote {out_dir / figures['selection']['path']}", file=sys.stderr,
                  flush=True)
        for mode, n, seed in runs:
            k += 1
            row = one_run(seq, mode, n, seed, args.max_frames)
            rows.append(row)
            print(_progress_line(k, total, row), file=sys.stderr, flush=True)
        records = [r for r in aggregate(rows) if r["sequence"] == seq.name]
        png = plot_ablation(records, out_dir / f"ablation_{seq.name}.png")
        figures.setdefault("ablation", []).append(png.name)
        print(f"wrote {png}", file=sys.stderr, flush=True)

    aggregates = aggregate(rows)
    report = {
        "command": shlex.join([sys.executable, *(sys.argv if from_cli else [__file__, *argv])]),
        "argv": list(argv),
        "date": started.isoformat(timespec="seconds"),
        "duration_s": (datetime.datetime.now(datetime.UTC) - started).total_seconds(),
        "machine": machine_info(("matplotlib",)),
        "load_average_before": load_before,
        "load_average_after": load_average(),
        "compilation_cache_dir": None if cache_dir is None else str(cache_dir),
        "settings": {"sequences": [str(d) for d in seq_dirs], "modes": args.modes,
                     "num_edges": args.num_edges, "seeds": args.seeds,
                     "max_frames": args.max_frames,
                     "config_defaults": dataclasses.asdict(Config())},
        "notes": "ms_per_frame: warm median (frames 3..), PNG decoding excluded, depends on "
                 "machine load: compare runs within one invocation. ATE in metres. "
                 "ate_rmse_m_std: std over seeds (ddof 1), null for a single run.",
        "aggregates": aggregates,
        "runs": rows,
        "figures": figures,
    }
    write_json(out_dir / "ablation.json", report)
    print(f"wrote {out_dir / 'ablation.json'}", file=sys.stderr, flush=True)
    print(markdown_table(aggregates))
    return 0


if __name__ == "__main__":
    sys.exit(main())
