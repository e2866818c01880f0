"""The tracker on real frames: known-motion recovery, one compilation, ATE bounds, the CLI."""

from __future__ import annotations

import json

import chex
import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
import pytest

from edgevo_jax import Config, Odometry
from edgevo_jax.camera import CAMERAS
from edgevo_jax.cli import BUNDLED_CLIP, main
from edgevo_jax.datasets import load_sequence
from edgevo_jax.datasets.source import depth_lags
from edgevo_jax.frontend.align import track
from edgevo_jax.frontend.chunk import batch_of_one, track_next
from edgevo_jax.frontend.selection import keyframe_edges
from edgevo_jax.geometry import rotation_angle_np
from edgevo_jax.image.preprocess import frame_from_edges, preprocess
from edgevo_jax.runs.run import run_sequence, summarise
from edgevo_jax.tracking import effects as tracker_module


@pytest.fixture(scope="module")
def bundled():
    return load_sequence(BUNDLED_CLIP)


def warped_edge_frame(frame, T_c_k: np.ndarray, intr, config):
    """The current frame seen after motion T_c_k: the keyframe's edge pixels with depth,
    forward-warped and rounded to pixels, with their gradients."""
    h, w = frame.shape
    ok = frame.edge_depth > 0
    uv, z = frame.edge_uv[ok].astype(np.float64), frame.edge_depth[ok].astype(np.float64)
    p = np.stack([(uv[:, 0] - intr.cx) / intr.fx * z, (uv[:, 1] - intr.cy) / intr.fy * z, z])
    q = T_c_k[:3, :3] @ p + T_c_k[:3, 3:]
    u = np.round(intr.fx * q[0] / q[2] + intr.cx).astype(int)
    v = np.round(intr.fy * q[1] / q[2] + intr.cy).astype(int)
    inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
    edges = np.zeros((h, w), np.uint8)
    gx, gy = np.zeros((h, w), np.float32), np.zeros((h, w), np.float32)
    edges[v[inside], u[inside]] = 255
    g = frame.edge_grad[ok][inside] * frame.edge_mag[ok][inside, None]
    gx[v[inside], u[inside]], gy[v[inside], u[inside]] = g[:, 0], g[:, 1]
    return frame_from_edges(edges, gx, gy, np.zeros((h, w), np.float32), config)


@pytest.mark.parametrize("twist", [
    [0.02, -0.01, 0.015, 0.01, -0.02, 0.015],   # 2.7 cm, 1.6 deg
    [-0.03, 0.0, -0.02, 0.0, 0.03, 0.0],        # 3.6 cm, 1.7 deg
])
def test_known_motion_is_recovered_on_a_real_frame(bundled, twist):
    config = Config()
    rgb, depth = bundled.load_frame(0)
    f0 = preprocess(rgb, depth, config)
    T_true = np.asarray(jaxlie.SE3.exp(jnp.asarray(twist)).as_matrix(), np.float64)
    f1 = warped_edge_frame(f0, T_true, bundled.intrinsics, config)
    edges = keyframe_edges(f0, config, seed=0, intr=bundled.intrinsics)
    kf = jax.tree.map(jnp.asarray, edges)
    res = track(kf, tuple(map(jnp.asarray, f1.dist)), jax.tree.map(jnp.asarray, f1.edge_map),
                jnp.eye(4, dtype=jnp.float32), bundled.intrinsics, config)
    err = np.linalg.inv(T_true) @ np.asarray(res.T_c_k, np.float64)
    assert np.linalg.norm(err[:3, 3]) < 2e-3, err  # metres
    assert np.degrees(rotation_angle_np(err)) < 0.1
    assert int(res.inliers) > 0.8 * int(np.sum(kf.valid))


def test_tracker_compiles_once_and_tracks_the_bundled_clip(bundled, monkeypatch):
    """Fixed shapes: the per-frame solve is traced once for the whole run (a second trace
    raises); ATE on real fr1 frames under 6 mm."""
    guarded = batch_of_one(chex.assert_max_traces(track_next, n=1))
    monkeypatch.setattr(tracker_module, "track_next_jit", guarded)
    run = run_sequence(bundled, Config(), progress=False)
    stats = summarise(run, bundled)
    assert stats["frames"] == len(bundled) and stats["lost"] == 0
    assert stats["ate_rmse_m"] < 0.006
    assert np.all(np.isfinite(run.poses))


def test_a_depth_time_offset_moves_the_keyframes_edge_depths(monkeypatch):
    """A camera stating a depth time offset: each frame carries its depth image's true time
    after its colour image's (``datasets.depth_lags``; +-15 ms on this clip), and a keyframe
    made after the first takes its edge depths at the colour time; without the lags the
    first keyframe (no velocity yet) is the same and the second is not."""
    seq = load_sequence(BUNDLED_CLIP, camera=CAMERAS["fr1"].camera._replace(
        depth_time_offset_s=-0.002))

    def keyframes() -> tuple[dict[int, np.ndarray], list[float]]:
        rho, lags = {}, []

        def record(result, rgb, frame, odo):
            lags.append(frame.depth_lag_s)
            rho.setdefault(odo.state.keyframe.id, np.asarray(odo.state.keyframe.edges.rho))

        run_sequence(seq, Config(), progress=False, on_frame=record)
        return rho, lags

    rho, lags = keyframes()
    np.testing.assert_array_equal(lags, depth_lags(seq))
    assert np.abs(np.asarray(lags)).min() > 0.01
    monkeypatch.setattr("edgevo_jax.runs.run.depth_lags", lambda seq: None)
    plain, plain_lags = keyframes()
    assert not any(plain_lags) and set(rho) == set(plain) and len(rho) >= 2
    np.testing.assert_array_equal(rho[0], plain[0])
    assert np.abs(rho[1] - plain[1]).max() > 1e-3


def test_first_pose_comes_from_the_ground_truth(bundled):
    run = run_sequence(bundled, Config(), progress=False, max_frames=1)
    gt_t, gt_p = bundled.groundtruth
    i = int(np.argmin(np.abs(gt_t - bundled.timestamps[0])))
    np.testing.assert_allclose(run.poses[0][:3, 3], gt_p[i, :3])


def test_the_compiling_is_announced_once_and_kept_out_of_the_bar(bundled, capsys):
    """With progress, one line before the first frame of a configuration and image size
    says it compiles (once per process); the bar starts at the second frame, so its rate
    counts tracked frames only; without progress nothing is printed."""
    config = Config(seed=123)  # a configuration no other test of this process announced
    run_sequence(bundled, config, progress=True, max_frames=3)
    err = capsys.readouterr().err
    assert err.count("the first frame compiles the tracker's programs") == 1, err
    assert "1/3" in err and "0/3" not in err  # the bar was made after the first frame
    run_sequence(bundled, config, progress=True, max_frames=3)
    assert "compiles" not in capsys.readouterr().err
    run_sequence(bundled, config.replace(seed=124), progress=False, max_frames=2)
    assert capsys.readouterr().err == ""


def test_a_structural_setting_is_named_before_compiling(bundled, capsys):
    """The compile line names the settings that change the programs' structure (those that
    take the run off the defaults' programs), and only those: not the traced numbers, not a
    field without effect beside them. Nothing is compiled to say it."""
    from edgevo_jax.derive import program_structure, structural_fields
    from edgevo_jax.runs.run import _announce_compile

    config = Config(selection="all", num_edges=256, huber_delta=(2.0, 2.0, 2.0), seed=7)
    assert structural_fields(config) == ["selection"]
    assert program_structure(config.replace(num_edges=128)) == program_structure(config)
    assert structural_fields(Config(num_edges=256, iterations=(5, 5, 5))) == ["num_edges"]
    two_levels = Config(iterations=(5, 5), huber_delta=(1.0, 1.0), max_residual=(5.0, 5.0))
    assert structural_fields(two_levels) == ["iterations", "huber_delta", "max_residual"]
    assert structural_fields(Config(mapping=False, readout_s=0.0)) == ["readout_s", "mapping"]
    assert structural_fields(Config(depth_weight=3.0, eta=0.5, seed=2)) == []
    _announce_compile(bundled, config, None)
    err = capsys.readouterr().err
    assert "selection=all changes the programs' structure" in err
    assert "num_edges" not in err and "huber" not in err
    _announce_compile(bundled, Config(seed=99), None)
    assert "structure" not in capsys.readouterr().err


def test_streaming_api_rejects_time_going_back(bundled):
    odo = Odometry(Config(), bundled.intrinsics)
    rgb, depth = bundled.load_frame(0)
    first = odo.track(rgb, depth, 10.0)
    assert first.state == "OK" and first.keyframe == "first"
    np.testing.assert_array_equal(first.pose, np.eye(4))
    with pytest.raises(ValueError, match="does not increase"):
        odo.track(rgb, depth, 10.0)
    with pytest.raises(ValueError, match="depth_lag_s must be finite"):
        odo.track(rgb, depth, 11.0, depth_lag_s=float("nan"))
    assert odo.track(rgb, depth, 11.0, depth_lag_s=-0.015).state in ("OK", "WEAK")


def test_cli_run_writes_trajectory_and_stats(tmp_path, capsys):
    out, stats_path = tmp_path / "t.txt", tmp_path / "s.json"
    assert main(["run", "--out", str(out), "--stats", str(stats_path), "--no-progress"]) == 0
    stats = json.loads(stats_path.read_text())
    for key in ("frames", "keyframes", "lost", "startup_s", "warm_up_s", "ms_per_frame",
                "ate_rmse_m", "rpe_rmse_m_per_s"):
        assert key in stats
    assert set(stats["ms_per_frame"]) == {"median", "mean", "p90"}
    assert stats["rpe_rmse_m_per_s"] is None  # the clip is shorter than RPE's 1 s delta
    lines = out.read_text().splitlines()
    assert len(lines) == stats["frames"] == 9
    assert all(len(line.split()) == 8 for line in lines)
    per_frame = stats["per_frame"]  # one record per trajectory line, in order
    assert [f"{r['timestamp']:.6f}" for r in per_frame] == [line.split()[0] for line in lines]
    assert {r["state"] for r in per_frame} <= {"OK", "WEAK", "LOST"}
    assert per_frame[0]["keyframe"] == "first" and per_frame[0]["inliers"] == 0
    assert sum(r["keyframe"] is not None for r in per_frame) == stats["keyframes"]
    assert all(r["inliers"] > 0 for r in per_frame[1:] if r["state"] == "OK")
    assert "ATE RMSE" in capsys.readouterr().out
    gt = BUNDLED_CLIP / "groundtruth.txt"
    assert main(["eval", str(gt), str(out), "--json"]) == 0
    ev = json.loads(capsys.readouterr().out)
    assert ev["ate"]["rmse"] == pytest.approx(stats["ate_rmse_m"], abs=1e-6)


def test_cli_reports_bad_input_clearly(tmp_path, capsys):
    assert main(["run", str(tmp_path / "nope"), "--no-progress"]) == 2
    assert "nope" in capsys.readouterr().err
    assert main(["run", "--set", "bogus=1", "--no-progress"]) == 2
    assert "unknown config key 'bogus'" in capsys.readouterr().err


def test_config_overrides_parse_by_field_type():
    c = Config().with_overrides(["max_edges=512", "huber_delta=2,2,3", "eta=0.5"])
    assert c.max_edges == 512 and c.huber_delta == (2.0, 2.0, 3.0) and c.eta == 0.5
    with pytest.raises(ValueError, match="one value per level"):
        Config().with_overrides(["huber_delta=1,2"])


@pytest.mark.parametrize("clip,frames,bound", [
    ("rgbd_dataset_freiburg3_teddy_first200", 200, 0.02),
    ("rgbd_dataset_freiburg1_desk_clip9", None, 0.006),
])
def test_real_sequences_under_ate_bound(shared_clip, clip, frames, bound):
    seq = load_sequence(shared_clip(clip))
    run = run_sequence(seq, Config(), progress=False, max_frames=frames)
    stats = summarise(run, seq)
    assert stats["lost"] == 0
    assert stats["ate_rmse_m"] < bound, stats


def test_pipelined_runner_equals_synchronous_tracking(bundled):
    """Overlapping preprocessing with the solve changes timing only, never the trajectory."""
    run = run_sequence(bundled, Config(), progress=False)
    odo = Odometry(Config(), bundled.intrinsics, initial_pose=run.poses[0],
                   readout_s=bundled.readout_s)
    for i, expected in enumerate(run.results):
        got = odo.track(*bundled.load_frame(i), bundled.timestamps[i])
        np.testing.assert_array_equal(got.pose, expected.pose)
        assert got.keyframe == expected.keyframe


def test_finish_takes_what_is_pending_and_moves_no_frame_a_refinement_moved(bundled):
    """``Odometry.finish`` (a run's end): the window's refinements on their way are taken
    (none dropped), the frames keep their poses (a refinement moves no frame reported), and
    tracking goes on after it; a frame in flight is refused."""
    seq = bundled
    with Odometry(Config(mapping_lag=50), seq.intrinsics) as odo:
        reported = [odo.track(*seq.load_frame(i), seq.timestamps[i]).pose for i in range(6)]
        handed = odo.num_keyframes - len(odo.refinements)
        assert handed >= 1  # refinements still on their way at a lag of 50 frames
        odo.finish()
        assert odo.num_keyframes - len(odo.refinements) == 0
        np.testing.assert_array_equal(odo.poses(), np.stack(reported))
        odo.track(*seq.load_frame(6), seq.timestamps[6])
        pending = odo.submit(preprocess(*seq.load_frame(7), odo.config), seq.timestamps[7])
        with pytest.raises(RuntimeError, match="in flight"):
            odo.finish()
        odo.complete(pending)
