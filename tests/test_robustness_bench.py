"""scripts/robustness_bench.py: the aggregation over seeds, and one tiny real sweep on the
bundled clip (the silently-diverged-frame test: tests/pipeline/test_measure.py)."""

from __future__ import annotations

import json
import math
from pathlib import Path
from types import ModuleType
from typing import Any

import pytest
from conftest import load_script

from edgevo_jax.cli import BUNDLED_CLIP


@pytest.fixture(scope="module")
def rb() -> ModuleType:
    """The script as a module."""
    return load_script("robustness_bench")


def test_aggregate_over_seeds(rb: ModuleType) -> None:
    def run(seed: int | None, ate: float, method: str = "edgevo") -> dict[str, Any]:
        return {"sequence": "s", "method": method, "step": 2, "seed": seed, "frames": 10,
                "ate_rmse_m": ate, "rpe_m_per_s": math.nan, "rpe_deg_per_s": math.nan,
                "diverged": seed or 0, "weak": 1, "lost": 0, "median_ms": 5.0,
                "mean_ms": 6.0}

    rows = rb.aggregate([run(0, 0.01), run(1, 0.02), run(2, 0.03), run(None, 0.1, "cv2_rgb"),
                         {"sequence": "s", "method": "o3d_color", "step": 2, "missing": "x"}])
    assert [(r["method"], r["runs"]) for r in rows] == [("edgevo", 3), ("cv2_rgb", 1)]
    e = rows[0]
    assert e["ate_mean_m"] == pytest.approx(0.02) and e["ate_max_over_min"] == pytest.approx(3)
    assert (e["ate_min_m"], e["ate_max_m"], e["diverged_max"]) == (0.01, 0.03, 2)
    assert math.isnan(e["rpe_m_per_s_mean"]) and e["seeds"] == [0, 1, 2]


# --------------------------------------------------------------------------------------------
# a tiny real sweep: the bundled 9-frame clip, steps 1 and 2, one seed, cv2_rgb if it can run


def _cv2_odometry_missing() -> str | None:
    try:
        import cv2
    except ImportError as err:
        return f"cannot import cv2: {err}"
    return None if hasattr(cv2, "Odometry") else f"OpenCV {cv2.__version__} has no cv2.Odometry"


@pytest.fixture(scope="module")
def sweep(rb: ModuleType, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    out = tmp_path_factory.mktemp("robustness")
    peers = "" if _cv2_odometry_missing() else "cv2_rgb"
    argv = [str(BUNDLED_CLIP), "--steps", "1,2", "--seeds", "0", "--peers", peers,
            "--warmup-frames", "0", "--out-json", str(out / "r.json"),
            "--out-md", str(out / "r.md"), "--out-png", str(out / "r.png")]
    assert rb.main(argv) == 0
    return {"json": json.loads((out / "r.json").read_text()), "out": out}


RUN_FIELDS = ("ate_rmse_m", "rpe_m_per_s", "rpe_deg_per_s", "frames", "ok", "weak", "lost",
              "diverged", "diverged_frames", "mean_ms", "median_ms")


def _check_runs(runs: list[dict[str, Any]], method: str) -> None:
    assert sorted(r["step"] for r in runs if r["method"] == method) == [1, 2]
    for r in (r for r in runs if r["method"] == method):
        assert all(k in r for k in RUN_FIELDS), sorted(set(RUN_FIELDS) - set(r))
        assert math.isfinite(r["ate_rmse_m"]) and r["ate_rmse_m"] < 0.05
        assert r["frames"] == {1: 9, 2: 5}[r["step"]]
        assert r["ok"] + r["weak"] + r["lost"] == r["frames"]
        assert r["diverged"] == len(r["diverged_frames"])
        assert r["rpe_m_per_s"] is None and "1 s" in r["accuracy_note"]  # a 0.3 s clip
        assert r["median_ms"] > 0


@pytest.mark.slow
def test_sweep_edgevo_rows(sweep: dict[str, Any]) -> None:
    result = sweep["json"]
    _check_runs(result["runs"], "edgevo")
    assert all(r["seed"] == 0 for r in result["runs"] if r["method"] == "edgevo")
    rows = [r for r in result["aggregates"] if r["method"] == "edgevo"]
    assert [r["step"] for r in rows] == [1, 2]
    assert all(r["ate_max_over_min"] == 1.0 and r["runs"] == 1 for r in rows)
    assert "robustness_bench.py" in result["command"] and "--steps 1,2" in result["command"]
    assert result["machine"]["cpu_count"] >= 1 and result["thresholds"]["diverged_trans_m"]
    md = (sweep["out"] / "r.md").read_text()
    assert "| rgbd_dataset_freiburg1_xyz_first10 | edgevo | 2 | 5 | 1 |" in md


@pytest.mark.slow
def test_sweep_peer_rows(sweep: dict[str, Any]) -> None:
    missing = _cv2_odometry_missing()
    if missing:
        pytest.skip(f"cv2_rgb peer not run: {missing}")
    _check_runs(sweep["json"]["runs"], "cv2_rgb")
    assert all(r["seed"] is None for r in sweep["json"]["runs"] if r["method"] == "cv2_rgb")


@pytest.mark.slow
def test_sweep_plot(sweep: dict[str, Any]) -> None:
    pytest.importorskip("matplotlib", reason="the plot is skipped without matplotlib")
    png = Path(sweep["out"] / "r.png")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
