"""Plots of edge selection and of the selection ablation (matplotlib, optional).

matplotlib is an optional dependency (``pip install edgevo_jax[viz]``) and is imported only
inside the functions. Figures are drawn on matplotlib's Agg canvas directly (no pyplot, no
global backend switch, no display needed); each function writes one PNG and returns its path.

- :func:`plot_selection_overlay`: selected edges over the gray image, one panel per selection
  (EdgeVO Fig. 5: partition greedy spreads the edges, plain greedy clusters them).
- :func:`plot_ablation`: edges used vs ATE (EdgeVO Fig. 6) and time per frame vs ATE
  (Fig. 1d), from the records that ``scripts/ablation_selection.py`` aggregates.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["ABLATION_KEYS", "plot_ablation", "plot_selection_overlay"]

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

# one colour and marker per selection mode, stable across figures
_STYLE = {
    "spg": ("tab:blue", "o", "spg (partition greedy)"),
    "greedy": ("tab:orange", "s", "greedy (no partitions)"),
    "random": ("tab:green", "^", "random"),
    "all": ("tab:red", "*", "all culled edges"),
}
_MODE_ORDER = ("spg", "greedy", "random", "all")
_DPI = 120


def _figure(figsize: tuple[float, float], **kwargs: Any) -> Any:
    """A matplotlib Figure on an Agg canvas; a clear ImportError when matplotlib is missing."""
    try:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
    except ImportError as err:  # pragma: no cover - exercised only without matplotlib
        raise ImportError(
            "edgevo_jax.viz needs matplotlib: pip install edgevo_jax[viz] "
            "(or pip install 'matplotlib>=3.7')"
        ) from err
    fig = Figure(figsize=figsize, **kwargs)
    FigureCanvasAgg(fig)
    return fig


def _save(fig: Any, path: str | os.PathLike[str]) -> Path:
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, format="png", dpi=_DPI)
    return out


def plot_selection_overlay(
    gray: np.ndarray,
    selections: Mapping[str, np.ndarray],
    path: str | os.PathLike[str],
    *,
    title: str | None = None,
) -> Path:
    """Draw each named selection of edge pixels over the gray image, one panel per name.

    gray: (H, W) image (any numeric dtype; shown with its own min/max); selections: name ->
    uv (2, N) pixel coordinates (u = column, v = row, origin at the centre of the top-left
    pixel); the panel title gives the name and N. Writes a PNG to ``path``; returns the path.
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
    fig = _figure((panel_w * n, panel_w * h / w + (0.9 if title else 0.5)),
                  layout="constrained")
    axes = fig.subplots(1, n, squeeze=False)[0]
    marker = max(1.0, 6.0 * 640.0 / max(w, 1)) / 2.0
    for ax, (name, uv) in zip(axes, pts.items(), strict=True):
        ax.imshow(img, cmap="gray", interpolation="nearest")
        colour = _STYLE.get(name, ("yellow",))[0]
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
    return _save(fig, path)


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


def plot_ablation(records: Sequence[Mapping[str, Any]], path: str | os.PathLike[str]) -> Path:
    """Selection ablation in two panels; writes a PNG to ``path`` and returns the path.

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
        mode_rank = _MODE_ORDER.index(key[1]) if key[1] in _MODE_ORDER else len(_MODE_ORDER)
        return sequences.index(key[0]), mode_rank, key[1]

    fig = _figure((13.0, 5.2), layout="constrained")
    ax_a, ax_b = fig.subplots(1, 2)
    linestyles = ("-", "--", ":", "-.")
    for key in sorted(groups, key=order):
        seq, mode = key
        colour, marker, label = _STYLE.get(mode, (None, "D", mode))
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
    return _save(fig, path)
