"""Bit-for-bit reproducible arithmetic on the CPU, whatever the batch size.

XLA's CPU backend contracts a multiply and an add into one fused multiply-add (FMA, one
rounding instead of two) wherever the two land in the same compiled kernel, and where they
land depends on the program's shapes: a run vmapped alone (a batch of one) and the same run
in a batch of three were compiled into kernels that rounded differently (by ~1e-7 per pose),
which Levenberg-Marquardt's accept / reject decisions amplify to millimetres over a sequence.
Without FMA every elementwise operation is rounded once, in any kernel, and a run gives the
same trajectory alone and in any batch (``batch.py``; tests/test_batch.py checks it).

So ``cap_cpu_isa`` caps XLA's CPU instruction set at AVX (no FMA) through ``XLA_FLAGS``
before JAX starts its CPU backend. The cost for this library's small kernels is within
noise; programs dominated by large matrix products run slower without FMA. Set
``EDGEVO_EXACT=0`` before importing edgevo_jax to leave XLA's flags alone (results then
agree alone and batched to ~1e-7 per pose, not bit for bit). Only x86-64 CPUs are capped;
elsewhere (ARM, GPUs) the batch-size invariance is not guaranteed.

``full_precision_products`` sets JAX's default matmul precision to "highest": on GPUs JAX
otherwise multiplies float32 matrices on TF32 tensor cores (10-bit mantissas), and the
selection's and the window's products lost enough that batched runs on an H100 drifted off
by metres (README, GPU); on CPUs it changes nothing.
"""

from __future__ import annotations

import os
import platform
import warnings

FLAG = "--xla_cpu_max_isa=AVX"


class ExactnessWarning(UserWarning):
    """JAX's CPU backend started before edgevo_jax could cap its instruction set."""


def cap_cpu_isa() -> bool:
    """Add ``FLAG`` to ``XLA_FLAGS`` unless EDGEVO_EXACT=0, the machine is not x86-64, or
    XLA_FLAGS already sets the ISA. Warns (``ExactnessWarning``) when JAX's backends are
    already running, since the flag can no longer take effect. Returns whether the flag is
    (now) in XLA_FLAGS."""
    flags = os.environ.get("XLA_FLAGS", "")
    if "xla_cpu_max_isa" in flags:
        return FLAG in flags.split()
    if os.environ.get("EDGEVO_EXACT", "1") == "0":
        return False
    if platform.machine().lower() not in ("x86_64", "amd64"):
        return False
    if _backends_started():
        warnings.warn(
            "JAX's CPU backend started before edgevo_jax was imported, so XLA may use fused "
            "multiply-adds: batched runs can then differ from runs alone by ~1e-7 per pose. "
            f"Import edgevo_jax before running JAX code, or set XLA_FLAGS={FLAG}.",
            ExactnessWarning, stacklevel=3)
        return False
    os.environ["XLA_FLAGS"] = f"{flags} {FLAG}".strip()
    return True


def full_precision_products() -> bool:
    """Set ``jax_default_matmul_precision`` to "highest" unless the user chose one (the
    JAX_DEFAULT_MATMUL_PRECISION variable or ``jax.config``); EDGEVO_EXACT=0 leaves it.
    Returns whether edgevo_jax set it."""
    import jax

    if os.environ.get("EDGEVO_EXACT", "1") == "0":
        return False
    if jax.config.jax_default_matmul_precision is not None:
        return False
    jax.config.update("jax_default_matmul_precision", "highest")
    return True


def _backends_started() -> bool:
    try:
        from jax._src import xla_bridge
    except ImportError:  # JAX not importable or its layout changed: assume not started
        return False
    started = getattr(xla_bridge, "backends_are_initialized", None)
    return bool(started()) if started is not None else False
