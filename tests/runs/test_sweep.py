"""Sweeps (``edgevo batch SWEEP.toml``): two processes under jax.distributed give every
trajectory of one process to the bit and the same summary; a sweep killed with SIGKILL
resumes without running its finished runs again and ends with the same summary; a bad sweep
file is refused before anything runs."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from edgevo_jax.cli import BUNDLED_CLIP, main
from edgevo_jax.datasets import load_sequence
from edgevo_jax.runs import sweep

# 4 runs: frame steps 1 and 2 (9 and 5 frames: the step-2 runs finish first) x two edge
# budgets; the budgets differ in keyframe slots, so the runs are tracked in separate calls
SWEEP = f"""
sources = ["{BUNDLED_CLIP}"]
frame_steps = [1, 2]
seeds = [3]

[base]
recovery_features = false
mapping = false

[grid]
num_edges = [256, 512]
"""


def _cli(*args: str, cache: Path, **kw) -> subprocess.Popen:
    env = dict(os.environ, EDGEVO_CACHE_DIR=str(cache), JAX_PLATFORMS="cpu")
    return subprocess.Popen([sys.executable, "-m", "edgevo_jax.cli", "batch", *args,
                             "--no-progress"], env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, **kw)


def _accuracy(path: Path) -> list[list[str]]:
    """A summary CSV without its last column (ms per frame: wall-clock time)."""
    return [line.split(",")[:-1] for line in path.read_text().splitlines()]


def _lines(out: Path) -> list[dict]:
    return [json.loads(line) for log in sorted((out / "log").glob("*.jsonl"))
            for line in log.read_text().splitlines()]


@pytest.fixture(scope="module")
def cache(tmp_path_factory) -> Path:
    """One compilation cache for the sweeps run in subprocesses (each loads what an earlier
    one compiled)."""
    return tmp_path_factory.mktemp("cache")


@pytest.fixture(scope="module")
def single(tmp_path_factory) -> tuple[Path, Path]:
    """The sweep file and the output folder of the sweep run in this process, uninterrupted."""
    root = tmp_path_factory.mktemp("sweep")
    (root / "s.toml").write_text(SWEEP)
    assert main(["batch", str(root / "s.toml"), "--out", str(root / "one"),
                 "--no-progress"]) == 0
    return root / "s.toml", root / "one"


def _assert_same_sweep(a: Path, b: Path) -> None:
    """Every trajectory file and pose digest equal, the summaries equal but for ms/frame."""
    runs = sorted(p.name for p in (a / "runs").iterdir())
    assert len(runs) == 4 and runs == sorted(p.name for p in (b / "runs").iterdir())
    for name in runs:
        assert (a / "runs" / name).read_bytes() == (b / "runs" / name).read_bytes()
    digests = [[(r["key"], r["poses_sha256"]) for r in map(json.loads, (d / "runs.jsonl")
                                                           .read_text().splitlines())]
               for d in (a, b)]
    assert digests[0] == digests[1]
    for name in ("summary.csv", "summary_settings.csv"):
        assert _accuracy(a / name) == _accuracy(b / name)


def test_sweep_writes_runs_and_summary(single):
    toml, out = single
    records = [json.loads(line) for line in (out / "runs.jsonl").read_text().splitlines()]
    assert [(r["frame_step"], r["setting"]) for r in records] == [
        (1, "num_edges=256"), (1, "num_edges=512"), (2, "num_edges=256"), (2, "num_edges=512")]
    n = [len(load_sequence(BUNDLED_CLIP, frame_step=k)) for k in (1, 2)]
    assert [r["frames"] for r in records] == [n[0], n[0], n[1], n[1]]
    assert all(r["seed"] == 3 and r["config"]["seed"] == 3 and r["ate_rmse_m"] < 0.01
               for r in records)
    assert len({r["poses_sha256"] for r in records}) == 4  # the settings do differ
    settings = _accuracy(out / "summary_settings.csv")
    assert settings[0][:4] == ["frame_step", "setting", "runs", "frames"]
    assert [row[:4] for row in settings[1:]] == [["1", "num_edges=256", "1", str(n[0])],
                                                 ["1", "num_edges=512", "1", str(n[0])],
                                                 ["2", "num_edges=256", "1", str(n[1])],
                                                 ["2", "num_edges=512", "1", str(n[1])]]
    assert "| 2 | num_edges=512 | 1 |" in (out / "summary.md").read_text()
    assert (out / "summary.png").read_bytes()[:4] == b"\x89PNG"  # matplotlib: the dev extra
    # a second sweep finds everything written and runs nothing
    before = (out / "log" / "process-0.jsonl").read_bytes()
    assert main(["batch", str(toml), "--out", str(out), "--no-progress"]) == 0
    assert (out / "log" / "process-0.jsonl").read_bytes() == before


def test_two_processes_equal_one_process(single, cache, tmp_path):
    toml, one = single
    run = _cli(str(toml), "--out", str(tmp_path / "two"), "--processes", "2", cache=cache)
    log, _ = run.communicate(timeout=600)
    assert run.returncode == 0, log
    lines = _lines(tmp_path / "two")
    assert sorted(r["process"] for r in lines) == [0, 0, 1, 1]  # both took their share
    _assert_same_sweep(one, tmp_path / "two")


def test_killed_sweep_resumes_and_ends_with_the_same_summary(single, cache, tmp_path):
    toml, one = single
    out = tmp_path / "killed"
    log = out / "log" / "process-0.jsonl"
    run = _cli(str(toml), "--out", str(out), cache=cache, start_new_session=True)
    deadline = time.monotonic() + 600
    while not (log.is_file() and log.read_bytes().count(b"\n")) and run.poll() is None:
        assert time.monotonic() < deadline
        time.sleep(0.02)
    os.kill(run.pid, signal.SIGKILL)
    run.communicate()
    finished = [r["key"] for r in _lines(out)]
    assert 1 <= len(finished) < 4, "the sweep must be killed part-way"
    assert not (out / "summary.csv").exists()
    again = _cli(str(toml), "--out", str(out), cache=cache)
    text, _ = again.communicate(timeout=600)
    assert again.returncode == 0, text
    keys = [r["key"] for r in _lines(out)]
    assert keys[:len(finished)] == finished and len(keys) == len(set(keys)) == 4
    assert f"{4 - len(finished)} runs tracked here, {len(finished)} already written" in text
    _assert_same_sweep(one, out)


@pytest.mark.parametrize(("body", "message"), [
    (SWEEP.replace("num_edges = [256, 512]", "num_edgez = [256, 512]"),
     "[grid]: unknown config key 'num_edgez'"),
    (SWEEP.replace("recovery_features = false", "recovery_features = 3"),
     "[base]: --set recovery_features=3: expected a boolean"),
    (SWEEP.replace(str(BUNDLED_CLIP), "/no/such/sequence"), "source /no/such/sequence: not found"),
    (SWEEP.replace("num_edges = [256, 512]", ""), "[grid] is empty"),
    (SWEEP.replace("[256, 512]", "[]"), "[grid] num_edges must be a non-empty list"),
    (SWEEP.replace(f'"{BUNDLED_CLIP}"', '"realsense"'), "a live camera cannot be swept"),
    (SWEEP.replace("seeds = [3]", "seeds = []"), "seeds must be a non-empty list"),
    ("frame_step = 2\n" + SWEEP, "unknown key(s) frame_step"),
    (SWEEP.replace("[grid]", "[grid]\nseed = [1, 2]"), "give the seeds as seeds = [...]"),
    (SWEEP.replace("[grid]", "[grid"), "not valid TOML"),
])
def test_bad_sweep_file_is_refused_before_anything_runs(tmp_path, capsys, body, message):
    toml = tmp_path / "bad.toml"
    toml.write_text(body)
    with pytest.raises(sweep.SweepError, match=None) as err:
        sweep.load_sweep(toml)
    assert message in str(err.value) and str(toml) in str(err.value)
    assert main(["batch", str(toml), "--out", str(tmp_path / "out"), "--no-progress"]) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "out").exists()  # nothing ran


def test_bad_command_lines(tmp_path, capsys):
    toml = tmp_path / "s.toml"
    toml.write_text(SWEEP)
    for args, message in [
            ([], "--out DIR is required with a sweep file"),
            (["--out", "o", "--coordinator", "h:1"], "go together"),
            (["--out", "o", "--processes", "2", "--cluster"], "choose one of"),
            (["--out", "o", "--coordinator", "h:1", "--num-processes", "2", "--process-id",
              "2"], "--process-id must be 0 .. 1")]:
        assert main(["batch", str(toml), *args]) == 2
        assert message in capsys.readouterr().err
    configs = tmp_path / "c.json"
    configs.write_text("[{}]")
    assert main(["batch", str(configs), "--processes", "2"]) == 2
    assert "for a sweep file (.toml) only" in capsys.readouterr().err


def test_evaluate_refuses_runs_it_does_not_have():
    from edgevo_jax import Config
    from edgevo_jax.runs.batch import evaluate

    seq = load_sequence(BUNDLED_CLIP)
    with pytest.raises(ValueError, match=r"runs \[\(0, 2\)\] name no"):
        evaluate([seq], [Config(), Config(eta=0.5)], runs=[(0, 1), (0, 2)], progress=False)
