"""scripts/learn_weights.py end to end on the bundled fr1/xyz clip: a few pairs (or windows),
one or two adam steps; the JSON holds finite numbers (held-out ATE of full runs included) and
the loss-curve PNG is written. Their cost is compilation (the smooth mode's gradient, the
tracker's programs), not the frames."""

from __future__ import annotations

import json
import math

import pytest
from conftest import load_script

from edgevo_jax.cli import BUNDLED_CLIP

pytest.importorskip("optax", reason="optax is needed to fit Params (pip install 'optax>=0.2')")
pytest.importorskip("matplotlib", reason="matplotlib draws the loss curve")

#: one pyramid level (``--set`` arguments): every level runs the same code, and the smooth
#: gradient's program of three took most of these tests' time to compile
ONE_LEVEL = ["--set", "iterations=10", "--set", "huber_delta=1", "--set", "max_residual=5"]


def _numbers(obj):
    if isinstance(obj, dict):
        for v in obj.values():
            yield from _numbers(v)
    elif isinstance(obj, list):
        for v in obj:
            yield from _numbers(v)
    elif obj is None or (isinstance(obj, (int, float)) and not isinstance(obj, bool)):
        yield obj  # None: a NaN or inf that json_safe wrote as null


def test_learn_weights_runs_on_the_bundled_clip(tmp_path, capsys):
    out_json, out_png = tmp_path / "log.json", tmp_path / "loss.png"
    weights_png = tmp_path / "weights.png"
    rc = load_script("learn_weights").main([
        str(BUNDLED_CLIP), "--train", "0:5", "--test", "5:10", "--gaps", "1,2",
        "--num-edges", "64", "--steps", "2", "--batch", "4", "--timing-reps", "1",
        "--control-runs", "1",
        # the held-out runs without the window: the tracker's programs alone to compile; one
        # pyramid level (the script's path is the same; 150 -> 85 s here)
        "--set", "mapping=false", *ONE_LEVEL, "--gn-steps", "3",
        "--out-json", str(out_json), "--out-png", str(out_png),
        "--out-weights-png", str(weights_png),
    ])
    assert rc == 0
    for png in (out_png, weights_png):
        assert png.is_file() and png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    report = json.loads(out_json.read_text())
    a, b = report["settings"]["test_frames"]  # 5:9 (the clip has 9 frames)
    for which in ("default", "fitted"):  # full tracker runs over the held-out frames only
        run = report["ate"][which]
        assert run["frames"] == b - a == 4 and run["ate_rmse_m"] > 0
        assert "rpe_rmse_m_per_s" in run  # null here: 0.1 s of frames, RPE is over 1 s
    (control,) = report["ate"]["control"]["runs"]
    assert control["frames"] == 4 and control["ate_rmse_m"] > 0
    assert report["settings"]["loss_kind"] == "pairs"
    assert report["settings"]["overrides"] == ["mapping=false", *ONE_LEVEL[1::2]]
    assert report["pairs"]["train"] > 0 and report["pairs"]["test"] > 0
    assert len(report["loss_curve"]["minibatch"]) == 2
    assert len(report["loss_curve"]["all_training_pairs"]) == 3
    for which in ("default", "fitted"):
        for split in ("train", "test"):
            rpe = report["rpe"][which][split]
            assert rpe["t_mean_mm"] >= 0 and rpe["r_mean_deg"] >= 0
    numbers = list(_numbers({k: report[k] for k in ("rpe", "loss_curve", "fitted_params",
                                                    "timing")}))
    numbers += [report["ate"][w]["ate_rmse_m"] for w in ("default", "fitted")]
    assert numbers and all(x is not None and math.isfinite(x) for x in numbers)
    assert report["timing"]["value_and_grad_warm_s"] > 0
    curves = report["weights"]  # the learnt weight against each input, all six
    assert len(curves) == 6 and all(len(c["weight"]) == len(c["feature"]) > 1
                                    for c in curves.values())
    assert all(0 < w < 2 for c in curves.values() for w in c["weight"])
    assert "value_and_grad over 4 pairs" in capsys.readouterr().out


@pytest.mark.slow
def test_learn_weights_window_loss(tmp_path, capsys):
    """--loss window: windows of 3 frames tracked against a keyframe; finite losses."""
    out_json = tmp_path / "log.json"
    rc = load_script("learn_weights").main([
        str(BUNDLED_CLIP), "--train", "0:5", "--test", "5:10", "--gaps", "1",
        "--loss", "window", "--window", "3", "--num-edges", "64", "--steps", "1",
        "--batch", "2", "--timing-reps", "1", "--no-ate",
        *ONE_LEVEL, "--gn-steps", "3", "--out-json", str(out_json),
        "--out-png", str(tmp_path / "loss.png"), "--out-weights-png", str(tmp_path / "w.png"),
    ])
    assert rc == 0
    report = json.loads(out_json.read_text())
    assert report["training_items"] == {"kind": "windows", "count": 2}
    curve = report["loss_curve"]["all_training_windows"]
    assert len(curve) == 2 and all(math.isfinite(x) and x > 0 for x in curve)
    assert report["ate"] == {"skipped": "--no-ate"}
    assert "value_and_grad over 2 windows" in capsys.readouterr().out


def test_learn_weights_bad_override(tmp_path, capsys):
    rc = load_script("learn_weights").main([str(BUNDLED_CLIP), "--set", "no_such_key=1",
                                            "--out-json", str(tmp_path / "x.json")])
    assert rc == 2 and "unknown config key 'no_such_key'" in capsys.readouterr().err
    assert not (tmp_path / "x.json").exists()


def test_learn_weights_missing_sequence(tmp_path, capsys):
    rc = load_script("learn_weights").main([str(tmp_path / "nowhere"), "--out-json",
                              str(tmp_path / "x.json"), "--out-png", str(tmp_path / "x.png")])
    assert rc == 2 and "sequence folder not found" in capsys.readouterr().err
    assert not (tmp_path / "x.json").exists()
