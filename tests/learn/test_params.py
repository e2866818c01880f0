"""The tracker driven by learnt Params: defaults give the plain trajectory bit for bit; other
Params reach the solve (the same computation as the differentiable path's hard test) and the
edge selection; Params to and from JSON, and the CLI's --params."""

from __future__ import annotations

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from edgevo_jax import Config
from edgevo_jax.cli import BUNDLED_CLIP, main
from edgevo_jax.datasets import load_sequence
from edgevo_jax.derive import SolveStructure, solve_knobs, solve_structure
from edgevo_jax.frontend.align import track
from edgevo_jax.frontend.chunk import track_next_jit
from edgevo_jax.frontend.selection import KeyframeEdges, keyframe_edges
from edgevo_jax.image.preprocess import preprocess
from edgevo_jax.learn import track_differentiable
from edgevo_jax.learn.params import Params, params_from_dict, params_to_dict, solve_knobs_of
from edgevo_jax.runs.run import run_sequence

CONFIG = Config(num_edges=256)


def learnt(config: Config) -> Params:
    """Params away from the defaults in every part the tracker reads."""
    return Params.default(config)._replace(
        log_huber=jnp.log(jnp.array([1.5, 0.8, 1.2])), eta=jnp.asarray(0.5),
        reobs_a=jnp.asarray(130.0),
        weight_w2=jnp.array([0.4, -0.3, -0.8, 0.2, 0.5, -0.1, 0.3, -0.6]),
        weight_b2=jnp.asarray(0.1))


@pytest.fixture(scope="module")
def bundled():
    return load_sequence(BUNDLED_CLIP)


def test_default_params_give_the_plain_trajectory(bundled):
    """Params.default(config): the same knobs (no weighting model: the same program) and the
    same trajectory as no Params, bit for bit."""
    knobs, ref = solve_knobs_of(Params.default(CONFIG), CONFIG), solve_knobs(CONFIG)
    assert knobs.weighting is None
    assert solve_structure(CONFIG) == SolveStructure(CONFIG.num_levels)  # static, hashable
    assert hash(solve_structure(CONFIG)) == hash(solve_structure(CONFIG.replace(eta=0.5)))
    for a, b in zip(knobs, ref, strict=True):
        if a is not None:
            np.testing.assert_array_equal(a, b)
            assert np.asarray(a).dtype == np.asarray(b).dtype
    plain = run_sequence(bundled, CONFIG, progress=False)
    default = run_sequence(bundled, CONFIG, progress=False, params=Params.default(CONFIG))
    np.testing.assert_array_equal(default.poses, plain.poses)
    assert [r.keyframe for r in default.results] == [r.keyframe for r in plain.results]


@pytest.mark.slow
def test_learnt_params_drive_the_solve_and_the_selection(bundled):
    """The tracker's solve with learnt knobs is the differentiable path's hard-consistency
    computation with the same Params (float32); reobs_a changes the selected edges."""
    params = learnt(CONFIG)
    frame0 = preprocess(*bundled.load_frame(0), CONFIG)
    frame1 = preprocess(*bundled.load_frame(1), CONFIG)
    edges = keyframe_edges(frame0, CONFIG, seed=0, intr=bundled.intrinsics)
    kf = jax.tree.map(jnp.asarray, edges)
    moved = keyframe_edges(frame0, CONFIG, seed=0, intr=bundled.intrinsics,
                           reobs_a=float(params.reobs_a))  # (the run below compiles it too)
    assert not np.array_equal(edges.uv, moved.uv)
    assert kf.mag is not None and np.all(np.asarray(kf.mag)[np.asarray(kf.valid)]
                                         >= CONFIG.canny_high)
    dist = tuple(jnp.asarray(d) for d in frame1.dist)
    em = jax.tree.map(jnp.asarray, frame1.edge_map)
    eye = np.eye(4, dtype=np.float32)
    solve = jax.jit(track, static_argnames="config")
    diff = jax.jit(track_differentiable, static_argnames=("config", "consistency"))
    plain = solve(kf, dist, em, eye, bundled.intrinsics, solve_structure(CONFIG),
                  solve_knobs(CONFIG))
    default = Params.default(CONFIG)
    # one part at a time (together, float32 rounding differences of ~1e-8 can flip an LM
    # accept / reject and end ~1e-5 apart)
    for part in ("log_huber", "eta", "weight_w2", "weight_b2"):
        p = default._replace(**{part: getattr(params, part)})
        res = solve(kf, dist, em, eye, bundled.intrinsics, solve_structure(CONFIG),
                    solve_knobs_of(p, CONFIG))
        ref = diff(kf, dist, em, jnp.eye(4, dtype=jnp.float32), bundled.intrinsics, p, CONFIG,
                   consistency="hard")
        np.testing.assert_allclose(res.T_c_k, ref.T_c_k, atol=1e-7, err_msg=part)
        assert int(res.inliers) == int(ref.inliers), part
        assert float(res.cost) != float(plain.cost), part  # the part reaches the solve
        if part != "weight_b2":  # alone, a weight scale common to all edges: the same pose
            moved = np.max(np.abs(np.asarray(res.T_c_k) - np.asarray(plain.T_c_k)))
            assert float(moved) > 1e-6, part
    no_mag = kf._replace(mag=None)
    with pytest.raises(ValueError, match="KeyframeEdges.mag and .disc"):
        track_next_jit(no_mag, dist, em, eye, eye, bundled.intrinsics,
                       solve_knobs_of(params, CONFIG), config=solve_structure(CONFIG))
    assert isinstance(KeyframeEdges(*edges[:4]).mag, type(None))  # mag stays optional


def test_params_json_and_the_cli(tmp_path, capsys):
    """Params to JSON and back; ``edgevo run --params`` takes a learn_weights.py log and
    gives another trajectory than the plain run."""
    params = learnt(CONFIG)
    values = json.loads(json.dumps(params_to_dict(params)))
    back = params_from_dict(values, CONFIG)
    for a, b in zip(back, params, strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-7)
    partial = params_from_dict({"eta": 0.7}, CONFIG)
    assert float(partial.eta) == pytest.approx(0.7)
    np.testing.assert_array_equal(partial.log_huber, Params.default(CONFIG).log_huber)
    with pytest.raises(ValueError, match="log_huber"):
        params_from_dict({"log_huber": [0.0, 0.0]}, CONFIG)
    with pytest.raises(ValueError, match="pyramid levels"):
        solve_knobs_of(params, Config(iterations=(5, 5), huber_delta=(1.0, 1.0),
                                      max_residual=(5.0, 5.0)))
    log = tmp_path / "log.json"  # as scripts/learn_weights.py writes it
    log.write_text(json.dumps({"fitted_params": {**values, "huber_delta": [1.5, 0.8, 1.2]}}))
    out, ref = tmp_path / "traj.txt", tmp_path / "plain.txt"
    for path, extra in ((out, ["--params", str(log)]), (ref, [])):
        assert main(["run", *extra, "--set", "num_edges=256", "--max-frames", "3", "--out",
                     str(path), "--no-progress"]) == 0
    lines = out.read_text().splitlines()
    assert len(lines) == 3 and lines[1:] != ref.read_text().splitlines()[1:]
    bad = tmp_path / "bad.json"
    bad.write_text("[1, 2]")
    assert main(["run", "--params", str(bad), "--max-frames", "2", "--out",
                 str(tmp_path / "x.txt"), "--no-progress"]) == 2
    assert "must hold a JSON object" in capsys.readouterr().err


def test_params_that_lose_every_frame_write_finite_poses(bundled):
    """eta > 1: no match passes the consistency test, every frame after the first is lost
    (the bundled clip played back and forth, 40 frames). The run says so and its poses stay
    finite rotations (the constant-velocity guesses of lost frames in a row once grew into
    inf / NaN after ~25 frames), so its summary can be made."""
    from edgevo_jax.datasets import pingpong
    from edgevo_jax.runs.run import summarise
    from edgevo_jax.tracking.results import LOST

    params = Params.default(CONFIG)._replace(eta=jnp.asarray(1.5))
    seq = pingpong(bundled, 40)
    run = run_sequence(seq, CONFIG, progress=False, params=params)
    assert all(r.state == LOST for r in run.results[1:])
    poses = np.asarray(run.poses)
    assert np.all(np.isfinite(poses))
    R = poses[:, :3, :3]
    np.testing.assert_allclose(R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(3), R.shape),
                               atol=1e-6)
    stats = summarise(run, seq)
    assert stats["lost"] == len(run.results) - 1 == 39 and np.isfinite(stats["ate_rmse_m"])
