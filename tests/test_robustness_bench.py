"""scripts/robustness_bench.py: the silently-diverged-frame test on synthetic trajectories,
the aggregation, and one tiny real sweep on the bundled clip."""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
import pytest
from conftest import load_script

from edgevo_jax.cli import BUNDLED_CLIP
from edgevo_jax.geometry import inverse_np


@pytest.fixture(scope="module")
def rb() -> ModuleType:
    """The script as a module, with scripts/bench.py importable as ``bench`` while it loads
    (as it is when the script runs: scripts/ is then sys.path[0])."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setitem(sys.modules, "bench", load_script("bench"))
        yield load_script("robustness_bench")


def _rot(axis: str, deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    i, j = {"x": (1, 2), "y": (2, 0), "z": (0, 1)}[axis]
    m = np.eye(4)
    m[i, i], m[i, j], m[j, i], m[j, j] = c, -s, s, c
    return m


def _trans(x: float, y: float, z: float) -> np.ndarray:
    m = np.eye(4)
    m[:3, 3] = (x, y, z)
    return m


def _groundtruth(n: int = 20) -> np.ndarray:
    """T_world_cam moving 1 cm and turning 0.5 deg about y per frame (well under the
    thresholds)."""
    step = _trans(0.01, 0.002, 0.0) @ _rot("y", 0.5)
    poses = [_trans(0.3, -0.1, 1.2) @ _rot("x", 10.0)]
    for _ in range(n - 1):
        poses.append(poses[-1] @ step)
    return np.stack(poses)


def _jump(poses: np.ndarray, i: int, local: np.ndarray) -> np.ndarray:
    """The trajectory jumping at frame i by ``local`` (in frame i's camera coordinates) and
    staying there: P_m = G_i local G_i^-1 G_m for m >= i, so only the motion i-1 -> i is
    off, by exactly ``local``."""
    out = poses.copy()
    out[i:] = poses[i] @ local @ inverse_np(poses[i]) @ poses[i:]
    return out


JUMP_T, JUMP_R = 12, 7  # frames with a 6 cm jump and a 4 deg turn


def _injected(gt: np.ndarray) -> np.ndarray:
    return _jump(_jump(gt, JUMP_T, _trans(0.0, 0.06, 0.0)), JUMP_R, _rot("z", 4.0))


def test_diverged_frames_flags_jumps_on_ok_frames(rb: ModuleType) -> None:
    gt = _groundtruth()
    assert rb.diverged_frames(gt, ["OK"] * len(gt), gt) == []
    assert rb.diverged_frames(_injected(gt), ["OK"] * len(gt), gt) == [JUMP_R, JUMP_T]
    # the motion errors are the injected ones
    trans, rot = rb.motion_errors(_injected(gt), gt)
    assert trans[JUMP_T - 1] == pytest.approx(0.06) and rot[JUMP_R - 1] == pytest.approx(4.0)
    # under the thresholds (4 cm, 2 deg): nothing
    small = _jump(_jump(gt, JUMP_T, _trans(0.04, 0.0, 0.0)), JUMP_R, _rot("x", 2.0))
    assert rb.diverged_frames(small, ["OK"] * len(gt), gt) == []


@pytest.mark.parametrize("flag", ["LOST", "WEAK"])
def test_diverged_frames_ignores_jumps_on_flagged_frames(rb: ModuleType, flag: str) -> None:
    gt = _groundtruth()
    states = ["OK"] * len(gt)
    states[JUMP_T] = states[JUMP_R] = flag
    assert rb.diverged_frames(_injected(gt), states, gt) == []
    # a flagged frame whose pose alone is off (a bad prediction while lost, then back on
    # track) blames neither itself nor the OK frame after it
    outlier = gt.copy()
    outlier[JUMP_T] = outlier[JUMP_T] @ _trans(0.2, 0.0, 0.0) @ _rot("y", 20.0)
    assert rb.diverged_frames(outlier, states, gt) == []
    assert rb.diverged_frames(outlier, ["OK"] * len(gt), gt) == [JUMP_T, JUMP_T + 1]


def test_diverged_frames_skips_frames_without_groundtruth(rb: ModuleType) -> None:
    gt = _groundtruth()
    partial = gt.copy()
    partial[JUMP_T] = np.nan
    assert rb.diverged_frames(_injected(gt), ["OK"] * len(gt), partial) == [JUMP_R]
    with pytest.raises(ValueError, match="states"):
        rb.diverged_frames(gt, ["OK"] * 3, gt)


def test_parse_int_list(rb: ModuleType) -> None:
    assert rb.parse_int_list("0-4") == [0, 1, 2, 3, 4]
    assert rb.parse_int_list("0,1,2") == [0, 1, 2]
    assert rb.parse_int_list("1,2,3,5") == [1, 2, 3, 5]
    assert rb.parse_int_list("0-2,1,5") == [0, 1, 2, 5]
    for bad in ("", "a", "3-1", "1-x"):
        with pytest.raises(ValueError):
            rb.parse_int_list(bad)


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
