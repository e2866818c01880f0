"""determinism: XLA's CPU instruction set is capped (no FMA) before JAX starts,
so that a run gives the same result alone and in a batch (tests/test_batch.py checks that), and
float32 products at full precision on GPUs too."""

from __future__ import annotations

import os
import platform
import subprocess
import sys

import pytest

import edgevo_jax  # noqa: F401  (imported for its effect on XLA_FLAGS)
from edgevo_jax import determinism

X86 = platform.machine().lower() in ("x86_64", "amd64")


@pytest.mark.skipif(not X86, reason="the cap applies to x86-64 CPUs only")
def test_importing_the_package_capped_this_process(monkeypatch):
    import os

    if os.environ.get("EDGEVO_EXACT") == "0":
        pytest.skip("EDGEVO_EXACT=0: the cap is off by request")
    assert determinism.FLAG in os.environ.get("XLA_FLAGS", "").split()


def test_cap_respects_opt_out_and_existing_flags(monkeypatch):
    monkeypatch.setattr(determinism, "_backends_started", lambda: False)
    monkeypatch.setattr(platform, "machine", lambda: "x86_64")
    monkeypatch.setenv("XLA_FLAGS", "--xla_force_host_platform_device_count=4")
    monkeypatch.setenv("EDGEVO_EXACT", "0")
    assert determinism.cap_cpu_isa() is False
    assert "max_isa" not in determinism.os.environ["XLA_FLAGS"]
    monkeypatch.delenv("EDGEVO_EXACT")
    assert determinism.cap_cpu_isa() is True
    assert determinism.os.environ["XLA_FLAGS"].split() == [
        "--xla_force_host_platform_device_count=4", determinism.FLAG]
    assert determinism.cap_cpu_isa() is True  # idempotent: the flag is not added twice
    assert determinism.os.environ["XLA_FLAGS"].count("max_isa") == 1
    monkeypatch.setenv("XLA_FLAGS", "--xla_cpu_max_isa=SSE4_2")  # the user's own choice
    assert determinism.cap_cpu_isa() is False
    assert determinism.os.environ["XLA_FLAGS"] == "--xla_cpu_max_isa=SSE4_2"
    monkeypatch.setattr(platform, "machine", lambda: "aarch64")
    monkeypatch.setenv("XLA_FLAGS", "")
    assert determinism.cap_cpu_isa() is False


def test_warns_when_the_backend_started_first(monkeypatch):
    monkeypatch.setattr(determinism, "_backends_started", lambda: True)
    monkeypatch.setattr(platform, "machine", lambda: "x86_64")
    monkeypatch.setenv("XLA_FLAGS", "")
    monkeypatch.delenv("EDGEVO_EXACT", raising=False)
    with pytest.warns(determinism.ExactnessWarning, match="before edgevo_jax was imported"):
        assert determinism.cap_cpu_isa() is False
    assert determinism.os.environ["XLA_FLAGS"] == ""


def test_float32_products_at_full_precision_unless_the_user_chose():
    """GPUs' TF32 products made batched runs drift by metres (determinism.py); a user's own
    choice of precision stands."""
    if os.environ.get("EDGEVO_EXACT") == "0":
        pytest.skip("EDGEVO_EXACT=0: edgevo_jax leaves the precision alone")
    code = "import edgevo_jax, jax; print(jax.config.jax_default_matmul_precision)"
    env = {k: v for k, v in os.environ.items() if k != "JAX_DEFAULT_MATMUL_PRECISION"}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True,
                         text=True, check=True).stdout.split()
    assert out[-1] == "highest"
    env["JAX_DEFAULT_MATMUL_PRECISION"] = "bfloat16"
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True,
                         text=True, check=True).stdout.split()
    assert out[-1] == "bfloat16"
