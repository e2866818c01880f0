"""scripts/error_anatomy.py: its measures on known poses and one real run on the bundled
clip (every frame scored, the JSON written)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from conftest import load_script

from edgevo_jax.cli import BUNDLED_CLIP
from edgevo_jax.geometry import exp_np


@pytest.fixture(scope="module")
def anatomy():
    return load_script("error_anatomy")


def test_pose_error_is_the_relative_rotation_and_translation(anatomy):
    gt = exp_np(np.array([0.1, -0.2, 0.3, 0.05, 0.02, -0.1]))
    off = exp_np(np.array([0.0, 0.0, 0.0, 0.0, 0.0, math.radians(2.0)]))
    off[:3, 3] = [0.006, 0.0, -0.008]  # 1 cm
    deg, cm = anatomy.pose_error(gt @ off, gt)
    assert deg == pytest.approx(2.0, abs=1e-9)
    assert cm == pytest.approx(1.0, abs=1e-9)
    assert anatomy.pose_error(gt, gt) == pytest.approx((0.0, 0.0), abs=1e-6)


def test_spearman_ranks_and_skips_missing(anatomy):
    x = np.array([1.0, 2.0, 3.0, np.nan, 5.0])
    assert anatomy.spearman(x, x**3) == pytest.approx(1.0)
    assert anatomy.spearman(x, -x) == pytest.approx(-1.0)
    assert math.isnan(anatomy.spearman(x[:2], x[:2]))  # fewer than 3 pairs


def test_a_run_on_the_bundled_clip(anatomy, tmp_path):
    out = tmp_path / "a.json"
    assert anatomy.main([str(BUNDLED_CLIP), "--out-json", str(out),
                         "--out-png", str(tmp_path / "a.png")]) == 0
    data = json.loads(out.read_text())
    frames = data["frames"]
    assert len(frames) == 9 and data["summary"]["ate_rmse_m"] < 0.02  # 9 pairs associate
    # every frame after the first has its step error, a speed from the ground truth and
    # the rgb-depth offset of its pair (TUM lists pair within 20 ms)
    for f in frames[1:]:
        assert f["step_err_cm"] >= 0 and f["speed_deg_s"] >= 0
        assert abs(f["depth_offset_ms"]) <= 20
    assert frames[0]["drift_cm"] == pytest.approx(0.0, abs=1e-6)
    assert (tmp_path / "a.png").is_file()
