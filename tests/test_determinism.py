"""determinism: importing edgevo_jax changes no process-wide setting; batch-size-exact CPU
arithmetic is opt-in (``enable_batch_exact``, which conftest.py and the CLI call; a run then
gives the same result alone and in a batch, tests/test_batch.py); edgevo's own programs
multiply float32 at full precision unless the user chose a precision."""

from __future__ import annotations

import platform
import subprocess
import sys

import jax
import jax.numpy as jnp
import pytest

from edgevo_jax import determinism

X86 = platform.machine().lower() in ("x86_64", "amd64")


def test_importing_the_package_changes_no_process_wide_setting():
    code = (
        "import os, jax\n"
        "before = (os.environ.get('XLA_FLAGS'), jax.config.values.copy())\n"
        "import edgevo_jax, edgevo_jax.cli, edgevo_jax.runs.batch, edgevo_jax.learn\n"
        "after = (os.environ.get('XLA_FLAGS'), jax.config.values.copy())\n"
        "print(before == after)\n"
    )
    env = {"PATH": "/usr/bin:/bin", "XLA_FLAGS": "--xla_force_host_platform_device_count=2"}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True,
                         text=True, check=True).stdout.split()
    assert out[-1] == "True"


@pytest.mark.skipif(not X86, reason="the cap applies to x86-64 CPUs only")
def test_cli_and_conftest_capped_this_process():
    import os

    if os.environ.get("EDGEVO_EXACT") == "0":
        pytest.skip("EDGEVO_EXACT=0: the cap is off by request")
    assert determinism.FLAG in os.environ.get("XLA_FLAGS", "").split()


def test_cap_respects_opt_out_and_existing_flags(monkeypatch):
    monkeypatch.setattr(determinism, "_backends_started", lambda: False)
    monkeypatch.setattr(determinism.platform, "machine", lambda: "x86_64")
    monkeypatch.setenv("XLA_FLAGS", "--xla_force_host_platform_device_count=4")
    monkeypatch.setenv("EDGEVO_EXACT", "0")
    assert determinism.enable_batch_exact() is False
    assert "max_isa" not in determinism.os.environ["XLA_FLAGS"]
    monkeypatch.delenv("EDGEVO_EXACT")
    assert determinism.enable_batch_exact() is True
    assert determinism.os.environ["XLA_FLAGS"].split() == [
        "--xla_force_host_platform_device_count=4", determinism.FLAG]
    assert determinism.enable_batch_exact() is True  # idempotent: the flag is not added twice
    assert determinism.os.environ["XLA_FLAGS"].count("max_isa") == 1
    monkeypatch.setenv("XLA_FLAGS", "--xla_cpu_max_isa=SSE4_2")  # the user's own cap stands
    assert determinism.enable_batch_exact() is False
    assert determinism.os.environ["XLA_FLAGS"] == "--xla_cpu_max_isa=SSE4_2"
    monkeypatch.setenv("XLA_FLAGS", "")
    monkeypatch.setattr(determinism.platform, "machine", lambda: "aarch64")
    assert determinism.enable_batch_exact() is False
    assert determinism.os.environ["XLA_FLAGS"] == ""


def test_cap_warns_when_jax_already_started(monkeypatch):
    monkeypatch.setattr(determinism, "_backends_started", lambda: True)
    monkeypatch.setattr(determinism.platform, "machine", lambda: "x86_64")
    monkeypatch.setenv("XLA_FLAGS", "")
    monkeypatch.delenv("EDGEVO_EXACT", raising=False)
    with pytest.warns(determinism.ExactnessWarning, match="before enable_batch_exact"):
        assert determinism.enable_batch_exact() is False
    assert determinism.os.environ["XLA_FLAGS"] == ""


def test_full_precision_applies_to_the_wrapped_program_only_and_yields_to_the_user():
    """GPUs' TF32 products made batched runs drift by metres; edgevo's programs trace under
    "highest", a user's own choice stands, and the process-wide setting is untouched."""
    seen = []

    def f(x):
        seen.append(jax.config.jax_default_matmul_precision)  # at trace time
        return x @ x

    wrapped = determinism.full_precision(jax.jit(f))
    x = jnp.eye(2)
    wrapped(x)
    assert seen == ["highest"]
    assert jax.config.jax_default_matmul_precision is None
    with jax.default_matmul_precision("bfloat16"):
        wrapped(x)
    assert seen == ["highest", "bfloat16"]
    wrapped(x)  # cached: no new trace for the precision already compiled
    assert seen == ["highest", "bfloat16"]
