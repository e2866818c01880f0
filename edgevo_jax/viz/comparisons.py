"""Figures that compare: selected edges per selection mode, the selection ablation, the
benchmark of methods, their accuracy against the frame rate, and the result files they
read."""

from __future__ import annotations

import json
import math
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:  # only for annotations: viz sits beside preprocess, not above it
    pass

from ._canvas import MODE_ORDER, STYLE, figure, save

#: Keys every record passed to :func:`plot_ablation` must have.
ABLATION_KEYS = (
    "sequence",
    "selection",
    "num_edges",
    "edges_used_mean",
    "ms_per_frame_median",
    "ate_rmse_m_mean",
    "ate_rmse_m_std",
)


def plot_selection_overlay(
    gray: np.ndarray,
    selections: Mapping[str, np.ndarray],
    path: str | os.PathLike[str],
    *,
    title: str | None = None,
    dpi: float | None = None,
) -> Path:
    """Draw each named selection of edge pixels over the gray image, one panel per name.

    gray: (H, W) image (any numeric dtype; shown with its own min/max); selections: name ->
    uv (2, N) pixel coordinates (u = column, v = row, origin at the centre of the top-left
    pixel); the panel title gives the name and N. Writes a PNG to ``path`` (``dpi``: pixels
    per inch, default 120; a panel is 4.8 inches wide); returns the path.
    """
    img = np.asarray(gray)
    if img.ndim != 2:
        raise ValueError(f"gray must be a 2-D (H, W) image, got shape {img.shape}")
    if not selections:
        raise ValueError("selections is empty: nothing to draw")
    pts = {}
    for name, uv in selections.items():
        a = np.asarray(uv, np.float64)
        if a.ndim != 2 or a.shape[0] != 2:
            raise ValueError(f"selection {name!r} must be uv (2, N) pixels, got shape {a.shape}")
        pts[name] = a
    h, w = img.shape
    n = len(pts)
    panel_w = 4.8
    fig = figure((panel_w * n, panel_w * h / w + (0.9 if title else 0.5)),
                  layout="constrained")
    axes = fig.subplots(1, n, squeeze=False)[0]
    marker = max(1.0, 6.0 * 640.0 / max(w, 1)) / 2.0
    for ax, (name, uv) in zip(axes, pts.items(), strict=True):
        ax.imshow(img, cmap="gray", interpolation="nearest")
        colour = STYLE.get(name, ("yellow",))[0]
        # dense sets (e.g. every candidate) as small dots, selections as larger ones
        size = marker ** 2 if uv.shape[1] <= 4096 else max(marker / 3.0, 0.5) ** 2
        ax.scatter(uv[0], uv[1], s=size, c=colour, marker="o", linewidths=0, alpha=0.9)
        ax.set_xlim(-0.5, w - 0.5)
        ax.set_ylim(h - 0.5, -0.5)
        ax.set_title(f"{name}: {uv.shape[1]} edges", fontsize=11)
        ax.set_xticks([])
        ax.set_yticks([])
    if title:
        fig.suptitle(title, fontsize=12)
    return save(fig, path, dpi)


def _check_records(records: Sequence[Mapping[str, Any]]) -> None:
    if not records:
        raise ValueError("plot_ablation needs at least one record")
    for i, rec in enumerate(records):
        missing = [k for k in ABLATION_KEYS if k not in rec]
        if missing:
            raise ValueError(
                f"plot_ablation: record {i} ({rec.get('selection', '?')!r}, "
                f"num_edges={rec.get('num_edges', '?')!r}) lacks key(s) {', '.join(missing)}; "
                f"every record needs {', '.join(ABLATION_KEYS)}"
            )


def _power_of_two_ticks(ax: Any) -> None:
    """Label a log x axis at the powers of two in its range, as plain integers."""
    from matplotlib.ticker import FixedLocator, NullFormatter, ScalarFormatter

    lo, hi = ax.get_xlim()
    if not (lo > 0 and hi > lo):
        return
    ticks = [2.0 ** k for k in range(math.ceil(math.log2(lo)), math.floor(math.log2(hi)) + 1)]
    if len(ticks) < 2:
        return
    ax.xaxis.set_major_locator(FixedLocator(ticks))
    ax.xaxis.set_major_formatter(ScalarFormatter())
    ax.xaxis.set_minor_formatter(NullFormatter())


def _num(value: Any) -> float:
    """A float, NaN for None (JSON null)."""
    return math.nan if value is None else float(value)


def plot_ablation(records: Sequence[Mapping[str, Any]], path: str | os.PathLike[str], *,
                  dpi: float | None = None) -> Path:
    """Selection ablation in two panels; writes a PNG to ``path`` (``dpi``: pixels per inch,
    default 120; the figure is 13 x 5.2 inches) and returns the path.

    (a) edges used per frame (x, log scale) vs ATE RMSE in mm (y), one line per selection mode
    over its edge budgets, error bars = std of the ATE over seeds (EdgeVO Fig. 6);
    (b) warm median time per frame in ms (x) vs ATE RMSE in mm (y), one marker per
    (mode, num_edges), labelled with the budget (EdgeVO Fig. 1d).

    Each record (one aggregate over seeds) needs the keys in :data:`ABLATION_KEYS`:
    ``ate_rmse_m_*`` in metres, ``ms_per_frame_median`` in ms, ``num_edges`` the budget (None
    for ``all``). None or NaN values are skipped (std: no error bar). Records of several
    sequences get one line per (sequence, mode). ValueError when a key is missing.
    """
    _check_records(records)
    sequences = list(dict.fromkeys(str(r["sequence"]) for r in records))
    groups: dict[tuple[str, str], list[Mapping[str, Any]]] = {}
    for r in records:
        groups.setdefault((str(r["sequence"]), str(r["selection"])), []).append(r)

    def order(key: tuple[str, str]) -> tuple[int, int, str]:
        mode_rank = MODE_ORDER.index(key[1]) if key[1] in MODE_ORDER else len(MODE_ORDER)
        return sequences.index(key[0]), mode_rank, key[1]

    fig = figure((13.0, 5.2), layout="constrained")
    ax_a, ax_b = fig.subplots(1, 2)
    linestyles = ("-", "--", ":", "-.")
    for key in sorted(groups, key=order):
        seq, mode = key
        colour, marker, label = STYLE.get(mode, (None, "D", mode))
        if len(sequences) > 1:
            label = f"{seq}: {label}"
        ls = linestyles[sequences.index(seq) % len(linestyles)]
        rows = sorted(groups[key], key=lambda r: _num(r["edges_used_mean"]))
        x = np.array([_num(r["edges_used_mean"]) for r in rows])
        y = np.array([_num(r["ate_rmse_m_mean"]) for r in rows]) * 1e3
        err = np.array([_num(r["ate_rmse_m_std"]) for r in rows]) * 1e3
        t = np.array([_num(r["ms_per_frame_median"]) for r in rows])
        ok = np.isfinite(x) & np.isfinite(y) & (x > 0)
        size = 14 if mode == "all" else 6
        if ok.any():
            yerr = np.where(np.isfinite(err[ok]), err[ok], 0.0)
            ax_a.errorbar(x[ok], y[ok], yerr=yerr, color=colour, marker=marker, markersize=size,
                          linestyle=ls, capsize=3, label=label)
        if mode == "all" and ok.any():  # the all-edges accuracy as a reference level
            ax_a.axhline(float(np.mean(y[ok])), color=colour, linestyle=":", alpha=0.6)
        ok_b = np.isfinite(t) & np.isfinite(y)
        if ok_b.any():
            face = colour if sequences.index(seq) == 0 else "none"  # open: later sequences
            ax_b.plot(t[ok_b], y[ok_b], color=colour, marker=marker, markersize=size,
                      markerfacecolor=face, linestyle="none", label=label)
            for r, ti, yi in zip(rows, t, y, strict=True):
                if np.isfinite(ti) and np.isfinite(yi):
                    budget = "all" if r["num_edges"] is None else str(r["num_edges"])
                    ax_b.annotate(budget, (ti, yi), textcoords="offset points", xytext=(5, 4),
                                  fontsize=8, color=colour)
    where = sequences[0] if len(sequences) == 1 else f"{len(sequences)} sequences"
    ax_a.set_xscale("log")
    _power_of_two_ticks(ax_a)
    ax_a.set_xlabel("edges used per frame (mean, log scale)")
    ax_a.set_ylabel("ATE RMSE (mm)")
    ax_a.set_title(f"(a) edges used vs accuracy, {where}\n(error bars: std over seeds)",
                   fontsize=11)
    ax_b.set_xlabel("time per frame (ms, warm median, decoding excluded)")
    ax_b.set_ylabel("ATE RMSE (mm)")
    ax_b.set_title(f"(b) time vs accuracy, {where}\n(labels: edge budget)", fontsize=11)
    for ax in (ax_a, ax_b):
        ax.grid(True, which="both", alpha=0.3)
        if ax.has_data():
            ax.legend(fontsize=9)
    return save(fig, path, dpi)


# ---------------------------------------------------------------------------- benchmarks

#: Keys every row passed to :func:`plot_benchmark` must have.
BENCH_KEYS = ("method", "sequence", "ate_rmse_m", "warm_median_ms")


def plot_benchmark(rows: Sequence[Mapping[str, Any]], path: str | os.PathLike[str], *,
                   dpi: float | None = None) -> Path:
    """Time per frame vs accuracy per method (EdgeVO Fig. 1d across methods and variants).

    rows: ``scripts/bench.py``'s ``results``, each with the keys in :data:`BENCH_KEYS`
    (``ate_rmse_m`` in metres, ``warm_median_ms`` the warm median wall time per frame in
    ms); rows marked ``missing`` or ``error`` and rows with null / NaN values are skipped.
    One marker per (method, sequence), labelled with the method; edgevo variants (``kind``
    ``edgevo``) are circles, peers squares; one colour per sequence. The time axis is
    logarithmic when the times span more than a factor of 8. Writes a PNG to ``path``
    (``dpi``: pixels per inch, default 120; 9 x 5.5 inches) and returns the path.
    ValueError when a row lacks a key or no row has both numbers.
    """
    if not rows:
        raise ValueError("plot_benchmark needs at least one row")
    usable = []
    for i, row in enumerate(rows):
        if "missing" in row or "error" in row:
            continue
        missing = [k for k in BENCH_KEYS if k not in row]
        if missing:
            raise ValueError(f"plot_benchmark: row {i} ({row.get('method', '?')!r}) lacks "
                             f"key(s) {', '.join(missing)}; every row needs "
                             f"{', '.join(BENCH_KEYS)}")
        x, y = _num(row["warm_median_ms"]), _num(row["ate_rmse_m"]) * 1e3
        if math.isfinite(x) and math.isfinite(y) and x > 0:
            usable.append((row, x, y))
    if not usable:
        raise ValueError("plot_benchmark: no row has both an ATE and a time per frame "
                         "(all missing, failed or null)")
    sequences = list(dict.fromkeys(str(r["sequence"]) for r, _, _ in usable))
    colours = [f"C{k % 10}" for k in range(len(sequences))]
    fig = figure((9.0, 5.5), layout="constrained")
    ax = fig.subplots()
    for seq, colour in zip(sequences, colours, strict=True):
        pts = [(r, x, y) for r, x, y in usable if str(r["sequence"]) == seq]
        for r, x, y in pts:
            marker = "o" if r.get("kind") == "edgevo" else "s"
            ax.plot(x, y, marker=marker, markersize=8, color=colour, linestyle="none")
            ax.annotate(str(r["method"]), (x, y), textcoords="offset points", xytext=(6, 4),
                        fontsize=9, color=colour)
        ax.plot([], [], marker="o", linestyle="none", color=colour, label=seq)
    xs = np.array([x for _, x, _ in usable])
    if xs.max() / xs.min() > 8:
        from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

        ax.set_xscale("log")  # labelled at 1, 2, 5 x 10^k as plain numbers
        ax.xaxis.set_major_locator(LogLocator(base=10.0, subs=(1.0, 2.0, 5.0)))
        ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
        ax.xaxis.set_minor_formatter(NullFormatter())
    ax.set_xlabel("time per frame (ms, warm median, decoding excluded)")
    ax.set_ylabel("ATE RMSE (mm)")
    ax.set_title("time vs accuracy per method (circles: edgevo_jax variants, squares: peers)",
                 fontsize=11)
    ax.grid(True, which="both", alpha=0.3)
    ax.margins(x=0.15, y=0.12)
    ax.legend(fontsize=9, title="sequence", title_fontsize=9)
    return save(fig, path, dpi)


def plot_frame_rates(rows: Sequence[Mapping[str, Any]], path: str | os.PathLike[str]) -> Path:
    """ATE (mean over seeds, min-max bars) and silently diverged frames per run against the
    frame step, one line per method, a row of two panels per sequence. ``rows``:
    ``scripts/robustness_bench.py``'s aggregates (``sequence``, ``method``, ``step``,
    ``runs``, ``ate_mean_m``, ``ate_min_m``, ``ate_max_m``, ``diverged_mean``). Writes a PNG
    to ``path`` and returns the path."""
    seqs = list(dict.fromkeys(r["sequence"] for r in rows))
    fig = figure((10, 3.6 * len(seqs)), layout="constrained")
    axes = fig.subplots(len(seqs), 2, squeeze=False)
    for (ax_ate, ax_div), seq in zip(axes, seqs, strict=True):
        mine = [r for r in rows if r["sequence"] == seq]
        for method in dict.fromkeys(r["method"] for r in mine):
            rs = sorted((r for r in mine if r["method"] == method), key=lambda r: r["step"])
            k = np.array([r["step"] for r in rs])
            mean = 1e3 * np.array([r["ate_mean_m"] for r in rs])
            lo = mean - 1e3 * np.array([r["ate_min_m"] for r in rs])
            hi = 1e3 * np.array([r["ate_max_m"] for r in rs]) - mean
            label = f"{method} ({rs[0]['runs']} seeds)" if rs[0]["runs"] > 1 else method
            ax_ate.errorbar(k, mean, yerr=[lo, hi], marker="o", capsize=3, label=label)
            ax_div.plot(k, [r["diverged_mean"] for r in rs], marker="o", label=method)
        ax_ate.set(xlabel="frame step k (every k-th frame)", ylabel="ATE RMSE (mm)",
                   yscale="log",
                   title=f"{seq.removeprefix('rgbd_dataset_')}: ATE (mean, min-max over seeds)")
        ax_div.set(xlabel="frame step k", ylabel="silently diverged frames per run",
                   title="OK frames off by > 5 cm or > 3 deg")
        for ax in (ax_ate, ax_div):
            ax.set_xticks(sorted({r["step"] for r in mine}))
            ax.grid(alpha=0.3)
        ax_ate.legend(fontsize=8)
    return save(fig, path)


# ---------------------------------------------------------------------------- result files


def _stats_records(runs: Sequence[Mapping[str, Any]]) -> list[dict[str, Any]]:
    """``edgevo run --stats`` dicts -> :data:`ABLATION_KEYS` records, one per (sequence,
    selection, budget), ATE mean and std (ddof 1; None for one run) over the runs (seeds)."""
    groups: dict[tuple[str, str, int | None], list[Mapping[str, Any]]] = {}
    for s in runs:
        cfg = s["config"]
        mode = str(cfg["selection"])
        budget = None if mode == "all" else int(cfg["num_edges"])
        groups.setdefault((str(s["sequence"]), mode, budget), []).append(s)
    out = []
    for (seq, mode, budget), rs in groups.items():
        ates = np.array([_num(r.get("ate_rmse_m")) for r in rs])
        ates = ates[np.isfinite(ates)]
        times = np.array([_num(r["ms_per_frame"]["median"]) for r in rs])
        edges = np.array([_num(r.get("edges_used_mean")) for r in rs])
        out.append({
            "sequence": seq, "selection": mode, "num_edges": budget, "runs": len(rs),
            "edges_used_mean": float(np.nanmean(edges)) if np.isfinite(edges).any() else None,
            "ms_per_frame_median": float(np.nanmedian(times)) if np.isfinite(times).any()
            else None,
            "ate_rmse_m_mean": float(ates.mean()) if ates.size else None,
            "ate_rmse_m_std": float(ates.std(ddof=1)) if ates.size > 1 else None,
        })
    return out


def read_results(paths: Sequence[str | os.PathLike[str]]) -> tuple[str, list[dict[str, Any]]]:
    """Read configuration results for :func:`plot_ablation` or :func:`plot_benchmark`.

    Each path is one of: the selection ablation's ``ablation.json`` (docs/ablation) (its
    ``aggregates``), ``scripts/bench.py``'s JSON (its ``results``), or ``edgevo run --stats``
    JSON (one run: several of them, e.g. one per seed and budget, are aggregated per
    (sequence, selection, num_edges)). Returns ``("ablation", records)`` (the records
    :func:`plot_ablation` takes; ablation and stats files may be mixed) or
    ``("bench", rows)``. FileNotFoundError for a missing file; ValueError naming the file
    for invalid JSON, an unknown layout, or bench files mixed with the others.
    """
    if not paths:
        raise ValueError("no result files given")
    ablation: list[dict[str, Any]] = []
    stats: list[Mapping[str, Any]] = []
    bench: list[dict[str, Any]] = []
    for p in map(Path, paths):
        if not p.is_file():
            raise FileNotFoundError(f"results file not found: {p}")
        try:
            data = json.loads(p.read_text(encoding="utf-8"))
        except (json.JSONDecodeError, UnicodeDecodeError) as err:
            raise ValueError(f"{p}: not valid JSON ({err})") from None
        if isinstance(data, dict) and isinstance(data.get("aggregates"), list):
            ablation.extend(dict(r) for r in data["aggregates"])
        elif isinstance(data, dict) and isinstance(data.get("results"), list):
            bench.extend(dict(r) for r in data["results"])
        elif (isinstance(data, dict) and isinstance(data.get("ms_per_frame"), dict)
              and isinstance(data.get("config"), dict) and "sequence" in data):
            stats.append(data)
        else:
            raise ValueError(
                f"{p}: not a results file: expected the selection ablation's JSON (key "
                "'aggregates'), scripts/bench.py JSON (key 'results') or `edgevo run --stats` "
                "JSON (keys 'sequence', 'ms_per_frame', 'config')")
    if bench and (ablation or stats):
        raise ValueError("bench.py results cannot be mixed with ablation or run statistics "
                         "in one figure: plot them separately")
    if bench:
        return "bench", bench
    return "ablation", ablation + _stats_records(stats)
