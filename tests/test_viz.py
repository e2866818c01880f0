"""edgevo_jax.viz: the plots write real PNGs from small synthetic inputs (fast, no tracking)."""

from __future__ import annotations

import math
import struct
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip(
    "matplotlib", reason="matplotlib not installed (pip install edgevo_jax[viz]): viz untested")

from edgevo_jax.viz import ABLATION_KEYS, plot_ablation, plot_selection_overlay  # noqa: E402

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def png_size(path: Path) -> tuple[int, int]:
    """(width, height) of a PNG, checking its signature and IHDR chunk."""
    data = path.read_bytes()
    assert len(data) > 1000, f"{path} is suspiciously small ({len(data)} bytes)"
    assert data[:8] == PNG_SIGNATURE, f"{path} is not a PNG"
    assert data[12:16] == b"IHDR"
    return struct.unpack(">II", data[16:24])


def records() -> list[dict]:
    rows = []
    for mode, ates in (("spg", (9.0, 8.0, 7.5)), ("greedy", (14.0, 11.0, 9.0)),
                       ("random", (10.0, 9.0, 8.0))):
        for n, ate_mm in zip((128, 256, 512), ates, strict=True):
            rows.append({"sequence": "synthetic", "selection": mode, "num_edges": n,
                         "edges_used_mean": float(n), "ms_per_frame_median": 10.0 + n / 64,
                         "ate_rmse_m_mean": ate_mm * 1e-3, "ate_rmse_m_std": 0.5e-3})
    # 'all' is one deterministic run: no budget and no std (null in the JSON)
    rows.append({"sequence": "synthetic", "selection": "all", "num_edges": None,
                 "edges_used_mean": 6000.0, "ms_per_frame_median": 25.0,
                 "ate_rmse_m_mean": 7.0e-3, "ate_rmse_m_std": None})
    return rows


def test_plot_selection_overlay_writes_png(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    gray = rng.integers(0, 256, (48, 64), dtype=np.uint8)
    sel = {"spg": rng.uniform(0, 63, (2, 40)), "greedy": rng.uniform(0, 20, (2, 40)),
           "random": np.zeros((2, 0))}
    out = plot_selection_overlay(gray, sel, tmp_path / "sub" / "sel.png", title="synthetic")
    assert out == tmp_path / "sub" / "sel.png"
    w, h = png_size(out)
    assert w > h > 100  # three panels side by side


def test_plot_selection_overlay_rejects_bad_points(tmp_path: Path) -> None:
    gray = np.zeros((8, 8), np.uint8)
    with pytest.raises(ValueError, match=r"uv \(2, N\)"):
        plot_selection_overlay(gray, {"spg": np.zeros((3, 4))}, tmp_path / "x.png")


def test_plot_ablation_writes_png(tmp_path: Path) -> None:
    out = plot_ablation(records(), tmp_path / "ablation.png")
    w, h = png_size(out)
    assert w > h > 200


def test_plot_ablation_several_sequences_and_nan(tmp_path: Path) -> None:
    rows = records()
    other = [{**r, "sequence": "other"} for r in rows]
    other[0]["ate_rmse_m_mean"] = math.nan  # a failed run is skipped, not fatal
    out = plot_ablation(rows + other, tmp_path / "two.png")
    png_size(out)


def test_plot_ablation_rejects_missing_key(tmp_path: Path) -> None:
    rows = records()
    del rows[2]["ms_per_frame_median"]
    with pytest.raises(ValueError, match="record 2 .*ms_per_frame_median"):
        plot_ablation(rows, tmp_path / "bad.png")
    assert not (tmp_path / "bad.png").exists()
    with pytest.raises(ValueError, match="at least one record"):
        plot_ablation([], tmp_path / "empty.png")
    assert "ate_rmse_m_std" in ABLATION_KEYS
