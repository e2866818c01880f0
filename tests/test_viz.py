"""edgevo_jax.viz: the plots write real PNGs from small synthetic inputs (fast, no tracking)."""

from __future__ import annotations

import json
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


# ---------------------------------------------------------------------------- new figures


def pixels(path: Path) -> np.ndarray:
    """The PNG's RGB pixels as floats in [0, 1], (H, W, 3)."""
    from matplotlib.image import imread

    return np.asarray(imread(path))[..., :3]


def assert_png(path: Path, size: tuple[int, int]) -> np.ndarray:
    """The PNG at ``path`` is ``size`` (width, height) pixels and is not blank."""
    assert png_size(path) == size
    img = pixels(path)
    ink = np.mean(np.any(img < 0.9, axis=-1))  # share of pixels that are not (near) white
    assert ink > 0.02, f"{path} is nearly blank ({ink:.3%} non-white pixels)"
    assert img.std() > 0.05
    return img


def synthetic_trajectories(seed: int = 0) -> tuple[np.ndarray, ...]:
    """Ground truth (100 Hz, a circle) and a 30 Hz estimate in another world frame + noise."""
    rng = np.random.default_rng(seed)
    gt_t = 100.0 + np.arange(300) * 0.01
    ang = gt_t - gt_t[0]
    gt_p = np.zeros((gt_t.size, 7))
    gt_p[:, 0], gt_p[:, 1], gt_p[:, 2] = np.cos(ang), np.sin(ang), 0.1 * ang
    gt_p[:, 6] = 1.0
    est_t = gt_t[::3] + 0.004
    c, s = math.cos(0.7), math.sin(0.7)
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    est_xyz = (rot @ gt_p[::3, :3].T).T + np.array([0.3, -2.0, 0.5])
    est_xyz += rng.normal(scale=0.01, size=est_xyz.shape)
    est_p = np.concatenate([est_xyz, gt_p[::3, 3:]], axis=1)
    return gt_t, gt_p, est_t, est_p


def test_align_trajectory_matches_ate() -> None:
    from edgevo_jax.metrics import ate
    from edgevo_jax.viz import align_trajectory

    gt_t, gt_p, est_t, est_p = synthetic_trajectories()
    al = align_trajectory(gt_t, gt_p, est_t, est_p)
    assert al.error.shape == (est_t.size,) and al.est_xyz.shape == (3, est_t.size)
    assert al.rmse == pytest.approx(ate((gt_t, gt_p), (est_t, est_p))["rmse"], rel=1e-12)
    assert 0.005 < al.rmse < 0.03  # the 1 cm noise, not the 2 m frame offset
    np.testing.assert_allclose(al.est_xyz[:, 0], gt_p[0, :3], atol=0.05)


def test_plot_trajectory_writes_png(tmp_path: Path) -> None:
    from edgevo_jax.viz import plot_trajectory

    out = plot_trajectory(*synthetic_trajectories(), tmp_path / "t.png", dpi=50, title="syn")
    img = assert_png(out, (600, 300))  # 12 x 6 inches at 50 dpi
    # the error colour bar (plasma) puts saturated colours on the figure
    sat = img.max(axis=-1) - img.min(axis=-1)
    assert np.mean(sat > 0.5) > 0.002


def test_plot_trajectory_rejects_bad_input(tmp_path: Path) -> None:
    from edgevo_jax.viz import plot_trajectory

    gt_t, gt_p, est_t, est_p = synthetic_trajectories()
    with pytest.raises(ValueError, match="plane"):
        plot_trajectory(gt_t, gt_p, est_t, est_p, tmp_path / "a.png", plane="xx")
    with pytest.raises(ValueError, match="at least 3 associated poses"):
        plot_trajectory(gt_t, gt_p, est_t + 50.0, est_p, tmp_path / "b.png")
    assert not list(tmp_path.iterdir())


def test_plot_frame_writes_png(tmp_path: Path) -> None:
    from edgevo_jax.config import Config
    from edgevo_jax.image.preprocess import preprocess, to_gray
    from edgevo_jax.viz import plot_frame

    rgb = np.full((96, 128, 3), 40, np.uint8)
    rgb[20:70, 30:90] = 220  # one bright rectangle: four straight edges
    frame = preprocess(rgb, np.ones((96, 128), np.float32), Config())
    assert frame.num_edges > 100
    out = plot_frame(to_gray(rgb), frame, tmp_path / "f.png", title="rect", dpi=40)
    w, h = 3 * 4.6 * 40, (2 * 4.6 * 96 / 128 + 1.2) * 40
    assert_png(out, (round(w), round(h)))
    with pytest.raises(ValueError, match="level 0"):
        plot_frame(to_gray(rgb)[:50], frame, tmp_path / "g.png")


def bench_json(tmp_path: Path) -> Path:
    rows = [
        {"method": "edgevo", "kind": "edgevo", "sequence": "clip", "ate_rmse_m": 0.004,
         "warm_median_ms": 20.0},
        {"method": "edgevo_all", "kind": "edgevo", "sequence": "clip", "ate_rmse_m": 0.0045,
         "warm_median_ms": 45.0},
        {"method": "cv2_rgb", "kind": "peer", "sequence": "clip", "ate_rmse_m": 0.02,
         "warm_median_ms": 600.0},
        {"method": "o3d_color", "sequence": "clip", "missing": "cannot import open3d"},
        {"method": "cv2_rgbd", "kind": "peer", "sequence": "clip", "ate_rmse_m": None,
         "warm_median_ms": 80.0},
    ]
    path = tmp_path / "bench.json"
    path.write_text(json.dumps({"machine": {}, "settings": {}, "results": rows}))
    return path


def stats_json(tmp_path: Path, name: str, selection: str, num_edges: int, seed: int,
               ate_m: float) -> Path:
    stats = {"sequence": "clip", "frames": 9, "ms_per_frame": {"median": 20.0 + seed,
                                                               "mean": 21.0, "p90": 25.0},
             "edges_used_mean": float(num_edges), "ate_rmse_m": ate_m,
             "config": {"selection": selection, "num_edges": num_edges, "seed": seed}}
    path = tmp_path / name
    path.write_text(json.dumps(stats))
    return path


def test_read_results_formats(tmp_path: Path) -> None:
    from edgevo_jax.viz import read_results

    kind, rows = read_results([bench_json(tmp_path)])
    assert kind == "bench" and len(rows) == 5
    a = stats_json(tmp_path, "a.json", "spg", 256, 0, 0.004)
    b = stats_json(tmp_path, "b.json", "spg", 256, 1, 0.006)
    c = stats_json(tmp_path, "c.json", "all", 512, 0, 0.005)
    kind, recs = read_results([a, b, c])
    assert kind == "ablation"
    spg = next(r for r in recs if r["selection"] == "spg")
    assert spg["runs"] == 2 and spg["num_edges"] == 256
    assert spg["ate_rmse_m_mean"] == pytest.approx(0.005)
    assert spg["ate_rmse_m_std"] == pytest.approx(math.sqrt(2) * 0.001)
    assert spg["ms_per_frame_median"] == pytest.approx(20.5)
    full = next(r for r in recs if r["selection"] == "all")
    assert full["num_edges"] is None and full["ate_rmse_m_std"] is None
    assert all(k in r for r in recs for k in ABLATION_KEYS)
    with pytest.raises(ValueError, match="cannot be mixed"):
        read_results([a, bench_json(tmp_path)])


def test_read_results_real_ablation_json() -> None:
    from edgevo_jax.viz import read_results

    path = Path(__file__).resolve().parents[1] / "docs" / "ablation" / "ablation.json"
    if not path.is_file():
        pytest.skip(f"{path} not found")
    kind, recs = read_results([path])
    assert kind == "ablation" and recs
    assert all(k in r for r in recs for k in ABLATION_KEYS)


def test_plot_benchmark_writes_png_and_rejects_empty(tmp_path: Path) -> None:
    from edgevo_jax.viz import plot_benchmark, read_results

    _, rows = read_results([bench_json(tmp_path)])
    assert_png(plot_benchmark(rows, tmp_path / "b.png", dpi=50), (450, 275))
    with pytest.raises(ValueError, match="no row has both"):
        plot_benchmark([r for r in rows if r["method"] in ("o3d_color", "cv2_rgbd")],
                       tmp_path / "c.png")
    with pytest.raises(ValueError, match="lacks key"):
        plot_benchmark([{"method": "x", "sequence": "s", "ate_rmse_m": 0.1}], tmp_path / "d.png")


# ---------------------------------------------------------------------------- the CLI


def cli(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    from edgevo_jax.cli import main

    rc = main(argv)
    captured = capsys.readouterr()
    return rc, captured.out, captured.err


def write_tum(path: Path, t: np.ndarray, poses7: np.ndarray) -> Path:
    from edgevo_jax.io import write_trajectory

    write_trajectory(path, t, poses7)
    return path


def test_cli_plot_trajectory(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    gt_t, gt_p, est_t, est_p = synthetic_trajectories()
    gt = write_tum(tmp_path / "gt.txt", gt_t, gt_p)
    est = write_tum(tmp_path / "est.txt", est_t, est_p)
    out = tmp_path / "figs" / "traj.png"
    rc, stdout, _ = cli(["plot", "trajectory", str(gt), str(est), "--out", str(out),
                         "--dpi", "40"], capsys)
    assert rc == 0 and str(out) in stdout
    assert_png(out, (480, 240))


def test_cli_plot_trajectory_missing_groundtruth(tmp_path: Path,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    _, _, est_t, est_p = synthetic_trajectories()
    est = write_tum(tmp_path / "est.txt", est_t, est_p)
    rc, _, err = cli(["plot", "trajectory", str(tmp_path / "nope.txt"), str(est),
                      "--out", str(tmp_path / "t.png")], capsys)
    assert rc == 2
    assert "ground-truth trajectory file not found" in err and "nope.txt" in err
    assert not (tmp_path / "t.png").exists()


def test_cli_plot_configs_bad_json(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "bad.json"
    bad.write_text('{"aggregates": [')
    rc, _, err = cli(["plot", "configs", str(bad), "--out", str(tmp_path / "c.png")], capsys)
    assert rc == 2 and "bad.json: not valid JSON" in err
    other = tmp_path / "other.json"
    other.write_text('{"hello": 1}')
    rc, _, err = cli(["plot", "configs", str(other), "--out", str(tmp_path / "c.png")], capsys)
    assert rc == 2 and "not a results file" in err and "'aggregates'" in err
    rc, _, err = cli(["plot", "configs", str(tmp_path / "absent.json")], capsys)
    assert rc == 2 and "results file not found" in err
    assert not (tmp_path / "c.png").exists()


def test_cli_plot_configs(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "bench.png"
    rc, _, _ = cli(["plot", "configs", str(bench_json(tmp_path)), "--out", str(out),
                    "--dpi", "50"], capsys)
    assert rc == 0
    assert_png(out, (450, 275))
    runs = [stats_json(tmp_path, f"s{k}.json", "spg", n, k, 0.004 + 1e-3 * k)
            for k, n in enumerate((128, 256, 512))]
    out = tmp_path / "stats.png"
    rc, _, _ = cli(["plot", "configs", *map(str, runs), "--out", str(out), "--dpi", "50"],
                   capsys)
    assert rc == 0
    assert_png(out, (650, 260))  # plot_ablation: 13 x 5.2 inches


def test_cli_plot_frame_bundled_clip(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "frame.png"
    rc, _, _ = cli(["plot", "frame", "--index", "1", "--out", str(out), "--dpi", "30"], capsys)
    assert rc == 0
    w, h = 3 * 4.6 * 30, (2 * 4.6 * 480 / 640 + 1.2) * 30
    assert_png(out, (round(w), round(h)))
    rc, _, err = cli(["plot", "frame", "--index", "99", "--out", str(out)], capsys)
    assert rc == 2 and "--index 99 out of range" in err


def test_cli_plot_selection_bundled_clip(tmp_path: Path,
                                        capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "sel.png"
    rc, _, _ = cli(["plot", "selection", "--modes", "spg,random", "--set", "num_edges=64",
                    "--set", "max_edges=2048", "--out", str(out), "--dpi", "30"], capsys)
    assert rc == 0
    w, h = png_size(out)
    assert w == round(3 * 4.8 * 30) and h > 100  # candidates, spg, random
    rc, _, err = cli(["plot", "selection", "--modes", "spg,best", "--out", str(out)], capsys)
    assert rc == 2 and "unknown selection mode(s) best" in err


def test_missing_matplotlib_is_named(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                     monkeypatch: pytest.MonkeyPatch) -> None:
    import sys

    from edgevo_jax.viz import require_matplotlib

    monkeypatch.setitem(sys.modules, "matplotlib", None)  # import matplotlib -> ImportError
    with pytest.raises(ImportError, match=r"pip install 'edgevo_jax\[viz\]'"):
        require_matplotlib()
    rc, _, err = cli(["plot", "configs", str(bench_json(tmp_path))], capsys)
    assert rc == 2 and "pip install 'edgevo_jax[viz]'" in err


def test_plot_frame_rates_writes_png(tmp_path: Path) -> None:
    """scripts/robustness_bench.py's figure: two panels per sequence, one line per method."""
    from edgevo_jax.viz import plot_frame_rates

    rows = [{"sequence": f"rgbd_dataset_{s}", "method": m, "step": k, "runs": n,
             "ate_mean_m": 0.01 * k, "ate_min_m": 0.008 * k, "ate_max_m": 0.012 * k,
             "diverged_mean": k - 1.0}
            for s in ("a", "b") for m, n in (("edgevo", 3), ("cv2_rgb", 1)) for k in (1, 2, 3)]
    w, h = png_size(plot_frame_rates(rows, tmp_path / "rates.png"))
    assert w > 1000 and h > 700  # 10 x 7.2 inches at 120 dpi


def test_learning_plots_write_pngs(tmp_path: Path) -> None:
    """scripts/learn_weights.py's figures: the loss per step and the weight per input."""
    from edgevo_jax.viz.learning import FEATURE_LABELS, plot_loss_curve, plot_weight_curves

    out = plot_loss_curve([0.5, 0.4, 0.45], [0.5, 0.44, 0.42, 0.41], tmp_path / "loss.png",
                          "synthetic", "pairs")
    assert png_size(out) == (400, 240)  # 5 x 3 inches at 80 dpi
    curves = {name: {"feature": [0.0, 0.5, 1.0], "weight": [0.9, 1.0, 1.1]}
              for name in FEATURE_LABELS}
    out = plot_weight_curves(curves, tmp_path / "weights.png", "synthetic")
    assert png_size(out) == (720, 400)
