"""scripts/bench.py: one peer and edgevo on the bundled clip in-process, missing peers, tables
and JSON (the peers themselves: tests/test_peers.py)."""

from __future__ import annotations

import importlib.util
import json
import math
import sys
from pathlib import Path

import pytest

from edgevo_jax.cli import BUNDLED_CLIP

BENCH_PATH = Path(__file__).resolve().parents[1] / "scripts" / "bench.py"


@pytest.fixture(scope="module")
def bench():
    """The script as a module (imported from its path; not a package)."""
    spec = importlib.util.spec_from_file_location("edgevo_bench_script", BENCH_PATH)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    try:
        spec.loader.exec_module(module)
        yield module
    finally:
        sys.modules.pop(spec.name, None)


ROW_KEYS = {"method", "sequence", "path", "kind", "api", "frames", "lost", "ate_rmse_m",
            "rpe_m_per_s", "first_frame_ms", "warm_median_ms", "warm_p90_ms",
            "warm_mean_ms", "warm_max_ms", "wall_s", "baseline_rss_mib"}


def test_cv2_rgb_tracks_the_bundled_clip(bench):
    cv2 = pytest.importorskip("cv2")
    if not hasattr(cv2, "Odometry"):
        pytest.skip(f"OpenCV {cv2.__version__} has no cv2.Odometry (needs OpenCV 5)")
    row = bench.run_method("cv2_rgb", BUNDLED_CLIP, max_frames=5)
    assert "missing" not in row, row
    assert ROW_KEYS <= row.keys()
    assert row["method"] == "cv2_rgb" and row["frames"] == 5 and row["lost"] == 0
    assert math.isfinite(row["ate_rmse_m"]) and row["ate_rmse_m"] < 0.05
    assert math.isnan(row["rpe_m_per_s"])  # 5 frames span 0.13 s
    assert row["warm_median_ms"] > 0 and row["first_frame_ms"] > 0
    assert row["warm_median_ms"] <= row["warm_p90_ms"] <= row["warm_max_ms"]
    assert row["wall_s"] * 1e3 > row["first_frame_ms"] + row["warm_median_ms"]
    json.dumps(bench.json_safe(row), allow_nan=False)


def test_edgevo_row_has_a_compiled_pass_and_keeps_the_first_run_without_it(bench, monkeypatch):
    """The second (compiled) run repeats the first run's poses exactly; if it fails, the first
    run's numbers stay and the row says why the compiled ones are missing."""
    from edgevo_jax.runs import run as runner

    row = bench.run_method("edgevo", BUNDLED_CLIP, max_frames=4)
    assert row["repeat_identical"] is True and math.isfinite(row["compiled_mean_ms"])
    assert "compiled_error" not in row
    assert row["compiled_median_ms"] <= row["compiled_p90_ms"] <= row["compiled_max_ms"]
    assert row["wall_s"] > 0 and row["compiled_wall_s"] > 0

    real, calls = runner.run_sequence, []

    def second_run_fails(*args, **kwargs):
        calls.append(1)
        if len(calls) == 2:
            raise MemoryError("simulated")
        return real(*args, **kwargs)

    monkeypatch.setattr(runner, "run_sequence", second_run_fails)
    failed = bench.run_method("edgevo", BUNDLED_CLIP, max_frames=4)
    assert failed["ate_rmse_m"] == row["ate_rmse_m"] and failed["frames"] == row["frames"]
    assert failed["compiled_error"] == "MemoryError: simulated"
    assert failed["repeat_identical"] is None and math.isnan(failed["compiled_mean_ms"])


def test_unknown_peer_is_reported_missing(bench):
    row = bench.run_method("no_such_peer", BUNDLED_CLIP, max_frames=3)
    assert "unknown method 'no_such_peer'" in row["missing"]
    assert row["sequence"] == BUNDLED_CLIP.name


def test_missing_library_is_reported_missing(bench, monkeypatch):
    monkeypatch.setitem(sys.modules, "open3d", None)  # makes `import open3d` raise ImportError
    row = bench.run_method("o3d_color", BUNDLED_CLIP, max_frames=3)
    assert row["missing"].startswith("cannot import open3d"), row


def test_variants_are_checked(bench):
    assert bench.parse_variant("edgevo_fast=max_depth=4.0; min_inliers=20") == (
        "edgevo_fast", ["max_depth=4.0", "min_inliers=20"])
    with pytest.raises(ValueError, match="unknown config key 'no_such_key'"):
        bench.parse_variant("bad=no_such_key=1")
    with pytest.raises(ValueError, match="expects NAME"):
        bench.parse_variant("no_equals_sign")


def test_ratios_tables_and_json(bench):
    rows = [
        {"method": "edgevo", "sequence": "s", "warm_median_ms": 10.0, "ate_rmse_m": 0.01,
         "rpe_m_per_s": math.nan, "frames": 9, "lost": 0, "warm_mean_ms": 30.0,
         "compiled_mean_ms": 12.5,
         "profile_ms": {"frame": 10.0, "decode": 5.0, "preprocess": 8.0, "solve_wait": 9.0,
                        "host_other": 0.0}},
        {"method": "cv2_rgb", "sequence": "s", "warm_median_ms": 35.0, "ate_rmse_m": 0.02,
         "frames": 9, "lost": 1},
        {"method": "o3d_color", "sequence": "s", "missing": "cannot import open3d: x | y"},
    ]
    bench.add_ratios(rows)
    assert rows[0]["ratio_to_edgevo"] == 1.0 and rows[1]["ratio_to_edgevo"] == 3.5
    assert "ratio_to_edgevo" not in rows[2]
    md = bench.markdown_table(rows)
    assert "missing: cannot import open3d: x / y" in md and "| 3.50 |" in md
    assert "| 30.0 | 12.5 | 1.00 |" in md  # warm mean, compiled mean, ratio
    assert len({line.count("|") for line in md.splitlines()[:5]}) == 1  # columns line up
    assert len(md.splitlines()) == 5
    assert "solve wait" in bench.profile_table(rows)
    safe = bench.json_safe(rows)
    assert safe[0]["rpe_m_per_s"] is None
    json.dumps(safe, allow_nan=False)


def test_absent_default_clips_are_a_clear_error(bench, monkeypatch, tmp_path, capsys):
    monkeypatch.setattr(bench, "SHARED_TUM", tmp_path / "nowhere")
    assert bench.main(["--out-json", str(tmp_path / "b.json")]) == 2
    assert "default TUM clips not found" in capsys.readouterr().err
