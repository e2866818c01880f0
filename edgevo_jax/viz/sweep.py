"""The figure of a sweep's summary (``runs.sweep.write_summary(plot=plot_sweep)``)."""

from __future__ import annotations

from pathlib import Path

from ..runs.sweep import Sweep
from ._canvas import figure, save


def plot_sweep(sweep: Sweep, rows: list[dict], path: Path) -> Path:
    """ATE (mm) and ms per frame of every run against its frame step and setting, one
    colour per source, one marker per seed."""
    keys = list(dict.fromkeys((r["frame_step"], r["setting"]) for r in rows))
    sources = list(dict.fromkeys(r["sequence"] for r in rows))
    markers = "os^Dv<>P*X"
    fig = figure((max(6.0, 0.6 * len(keys) + 2), 6.5))
    ax_ate, ax_ms = fig.subplots(2, 1, sharex=True)
    for r in rows:
        x = keys.index((r["frame_step"], r["setting"]))
        x += 0.1 * (sources.index(r["sequence"]) - (len(sources) - 1) / 2)
        color = f"C{sources.index(r['sequence']) % 10}"
        marker = markers[sweep.seeds.index(r["seed"]) % len(markers)]
        if r["ate_rmse_m"] is not None:
            ax_ate.scatter(x, r["ate_rmse_m"] * 1e3, color=color, marker=marker, s=24)
        if r["ms_per_frame"] is not None:
            ax_ms.scatter(x, r["ms_per_frame"], color=color, marker=marker, s=24)
    for k, name in enumerate(sources):
        ax_ate.scatter([], [], color=f"C{k % 10}", label=name)
    ax_ate.legend(fontsize=7, loc="best")
    ax_ate.set_ylabel("ATE RMSE (mm)")
    ax_ms.set_ylabel("ms per frame (batch)")
    ax_ms.set_xticks(range(len(keys)))
    ax_ms.set_xticklabels([f"step {s}: {label}" for s, label in keys], rotation=30,
                          ha="right", fontsize=7)
    ax_ate.set_title(f"{sweep.path.name}: {len(rows)} runs (markers: seeds "
                     + ", ".join(f"{markers[i % len(markers)]} {s}"
                                 for i, s in enumerate(sweep.seeds)) + ")", fontsize=9)
    fig.tight_layout()
    return save(fig, path)
