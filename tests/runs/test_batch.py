"""Batched evaluation: many configurations and sequences in one compiled program give each
run's own trajectory (to 1e-6 m), on one device and sharded over four."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from edgevo_jax import Config
from edgevo_jax.cli import BUNDLED_CLIP
from edgevo_jax.datasets import load_sequence
from edgevo_jax.runs import batch
from edgevo_jax.runs import configs as config_files
from edgevo_jax.runs.run import run_sequence, summarise

# numbers of the solve (vmapped), host-side settings and the edge budget (padded slots); the
# clip's rolling shutter and a global shutter (rate 0 beside the others' rates)
CONFIGS = [
    Config(),
    Config(huber_delta=(2.0, 2.0, 2.0), eta=0.5, readout_s=0.0),
    Config(num_edges=256, max_residual=(4.0, 4.0, 4.0), iterations=(6, 8, 10)),
]


@pytest.fixture(scope="module")
def bundled():
    return load_sequence(BUNDLED_CLIP)


def test_batch_equals_each_configuration_alone(bundled):
    result = batch.evaluate([bundled], CONFIGS, chunk=3, progress=False)
    assert [r.config_index for r in result.runs] == [0, 1, 2]
    assert result.calls >= 2  # keyframes cut the chunks
    poses = []
    for run in result.runs:
        alone = run_sequence(bundled, run.config, progress=False)
        assert len(run.results) == len(alone.results) == len(bundled)
        assert [r.keyframe for r in run.results] == [r.keyframe for r in alone.results]
        assert np.abs(run.poses[:, :3, 3] - alone.poses[:, :3, 3]).max() <= 1e-6
        poses.append(run.poses)
        stats = summarise(run, bundled)
        assert stats["ate_rmse_m"] < 0.01 and stats["lost"] == 0
    # the configurations do differ (a batch that ignored them would give one trajectory)
    assert np.abs(poses[0] - poses[1]).max() > 1e-5 and np.abs(poses[0] - poses[2]).max() > 1e-5


def test_batch_of_two_sequences(bundled, shared_clip):
    """The bundled clip and 40 frames of fr3_teddy (many keyframes), with two edge budgets:
    runs of different lengths, frame sources and slot counts."""
    teddy = load_sequence(shared_clip("rgbd_dataset_freiburg3_teddy_first200"))
    configs = [CONFIGS[0], CONFIGS[2]]
    result = batch.evaluate([bundled, teddy], configs, chunk=2, max_frames=40, progress=False)
    assert [(r.sequence, r.config_index) for r in result.runs] == [
        (bundled.name, 0), (bundled.name, 1), (teddy.name, 0), (teddy.name, 1)]
    for run, seq in zip(result.runs, [bundled, bundled, teddy, teddy], strict=True):
        alone = run_sequence(seq, run.config, progress=False, max_frames=40)
        assert len(run.results) == len(alone.results)
        assert np.abs(run.poses[:, :3, 3] - alone.poses[:, :3, 3]).max() <= 1e-6


def test_batch_rejects_what_it_cannot_batch(bundled):
    with pytest.raises(ValueError, match="same number of pyramid levels"):
        batch.evaluate([bundled], [Config(), Config(iterations=(10, 10), huber_delta=(1.0, 1.0),
                                                    max_residual=(5.0, 5.0))])
    with pytest.raises(ValueError, match="at least one sequence"):
        batch.evaluate([], [Config()])
    with pytest.raises(ValueError, match="chunk must be positive"):
        batch.evaluate([bundled], [Config()], chunk=0)


SHARDED = textwrap.dedent("""
    import json, sys
    import jax
    from edgevo_jax import Config, enable_batch_exact
    from edgevo_jax.runs import batch
    enable_batch_exact()  # before JAX starts: a run's arithmetic does not depend on the batch
    from edgevo_jax.cli import BUNDLED_CLIP
    from edgevo_jax.datasets import load_sequence
    seq = load_sequence(BUNDLED_CLIP)
    configs = [Config(huber_delta=(h, h, h)) for h in (0.5, 1.0, 1.5, 2.0)]
    four = batch.evaluate([seq], configs, chunk=3, progress=False)
    one = batch.evaluate([seq], configs, chunk=3, progress=False, devices=jax.devices()[:1])
    json.dump({"devices": four.devices, "four": [r.poses.tolist() for r in four.runs],
               "one": [r.poses.tolist() for r in one.runs]}, sys.stdout)
""")


def test_sharded_over_four_devices_equals_one_device():
    """XLA_FLAGS=--xla_force_host_platform_device_count=4: the runs axis is split over four
    CPU devices (NamedSharding); every run's trajectory equals the single-device one."""
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=4",
               JAX_PLATFORMS="cpu")
    out = subprocess.run([sys.executable, "-c", SHARDED], env=env, capture_output=True,
                         text=True, timeout=600, check=True)
    got = json.loads(out.stdout)
    assert len(got["devices"]) == 4
    four, one = np.array(got["four"]), np.array(got["one"])
    assert four.shape == one.shape and four.shape[0] == 4
    assert np.abs(four[..., :3, 3] - one[..., :3, 3]).max() <= 1e-6
    assert np.abs(four[0] - four[3]).max() > 1e-5  # the runs differ


def test_load_configs_grid_and_list(tmp_path):
    grid = tmp_path / "grid.json"
    grid.write_text(json.dumps({"base": {"eta": 0.5},
                                "grid": {"huber_delta": [[1, 1, 1], [2, 2, 2]],
                                         "num_edges": [256, 512]}}))
    configs = config_files.load_configs(grid)
    assert [(c.huber_delta[0], c.num_edges) for c in configs] == [
        (1.0, 256), (1.0, 512), (2.0, 256), (2.0, 512)]
    assert all(c.eta == 0.5 for c in configs)
    listed = tmp_path / "list.json"
    listed.write_text(json.dumps([{}, {"mapping": False, "seed": 3}]))
    a, b = config_files.load_configs(listed)
    assert a == Config() and not b.mapping and b.seed == 3
    assert config_files.changed_fields(b) == {"mapping": False, "seed": 3}
    assert config_files.changed_fields(b, base=a.replace(seed=3)) == {"mapping": False}
    assert config_files.configs_from_spec([{"eta": 0.7}])[0].eta == 0.7
    for bad, match in [("[1, 2]", "expected a non-empty list"), ("{", "not valid JSON"),
                       ('{"grid": {"eta": []}}', "non-empty lists"),
                       ('[{"nope": 1}]', "unknown config key")]:
        listed.write_text(bad)
        with pytest.raises(ValueError, match=match):
            config_files.load_configs(listed)


def test_cli_batch_writes_results_and_trajectories(tmp_path):
    from edgevo_jax.cli import main
    from edgevo_jax.io import read_trajectory

    configs = tmp_path / "c.json"
    configs.write_text(json.dumps([{}, {"eta": 0.5}]))
    out = tmp_path / "b.json"
    assert main(["batch", str(configs), "--out", str(out), "--traj-dir", str(tmp_path / "t"),
                 "--no-progress"]) == 0
    got = json.loads(out.read_text())
    assert [r["config_index"] for r in got["runs"]] == [0, 1]
    assert got["runs"][1]["changed"] == {"eta": 0.5}
    assert all(r["ate_rmse_m"] < 0.01 for r in got["runs"])
    t, poses = read_trajectory(got["runs"][0]["trajectory"])
    assert len(t) == got["runs"][0]["frames"] and np.all(np.isfinite(poses))
