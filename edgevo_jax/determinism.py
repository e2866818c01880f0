"""Arithmetic that does not depend on the batch size or the device: two switches.

Importing edgevo_jax changes no process-wide setting. Instead:

- ``full_precision(fn)`` wraps each of edgevo's jitted programs so that they trace under
  ``jax.default_matmul_precision("highest")``: float32 products stay float32 on GPUs (JAX's
  default there is TF32, 10-bit mantissas), for edgevo's computations only. A precision the
  user chose (``jax.config`` or a ``jax.default_matmul_precision`` context around the call)
  stands. On CPUs it changes nothing.
- ``enable_batch_exact()`` (the ``edgevo`` CLI and every tracker, through
  ``programs.enable_cache``, call it: one arithmetic, one cache key) caps XLA's CPU instruction
  set at AVX, without fused multiply-adds, through ``XLA_FLAGS``. With FMA, how a multiply
  and an add round depends on which compiled kernel they land in, and that depends on the
  program's shapes: a run alone and the same run in a batch round differently (~1e-7 per
  pose), which Levenberg-Marquardt's accept / reject decisions amplify. Capped, a run gives
  the same trajectory alone and in any batch (``batch.py``). It must run before JAX starts
  its CPU backend (the first JAX computation); the environment variable ``EDGEVO_EXACT=0``
  turns the call into a no-op. Only x86-64 CPUs are capped.
"""

from __future__ import annotations

import functools
import os
import platform
import warnings
from collections.abc import Callable
from typing import TypeVar

FLAG = "--xla_cpu_max_isa=AVX"

F = TypeVar("F", bound=Callable)


class ExactnessWarning(UserWarning):
    """JAX's CPU backend started before ``enable_batch_exact`` could cap its instruction set."""


def enable_batch_exact() -> bool:
    """Add ``FLAG`` to ``XLA_FLAGS`` (batch-size-exact CPU arithmetic, see the module doc)
    unless EDGEVO_EXACT=0, the machine is not x86-64, or XLA_FLAGS already sets the ISA.
    Warns (``ExactnessWarning``) and leaves XLA_FLAGS alone when JAX's backends already
    run, since the flag could no longer take effect. Returns whether the flag is (now) in
    XLA_FLAGS."""
    flags = os.environ.get("XLA_FLAGS", "")
    if "xla_cpu_max_isa" in flags:
        return FLAG in flags.split()
    if os.environ.get("EDGEVO_EXACT", "1") == "0":
        return False
    if platform.machine().lower() not in ("x86_64", "amd64"):
        return False
    if _backends_started():
        warnings.warn(
            "JAX's CPU backend started before enable_batch_exact(), so XLA may use fused "
            "multiply-adds: batched runs can then differ from runs alone by ~1e-7 per pose. "
            f"Call it before any JAX computation, or set XLA_FLAGS={FLAG}.",
            ExactnessWarning, stacklevel=2)
        return False
    os.environ["XLA_FLAGS"] = f"{flags} {FLAG}".strip()
    return True


def full_precision(fn: F) -> F:
    """``fn`` (a jitted callable) called under ``jax.default_matmul_precision("highest")``
    unless a precision is already in force (set by the user in ``jax.config``, by
    JAX_DEFAULT_MATMUL_PRECISION, or by a context around the call). The precision is part
    of jit's cache key, so the program compiled for it is reused on every call."""
    import jax

    @functools.wraps(fn)
    def call(*args, **kwargs):
        if jax.config.jax_default_matmul_precision is not None:
            return fn(*args, **kwargs)
        with jax.default_matmul_precision("highest"):
            return fn(*args, **kwargs)

    return call  # type: ignore[return-value]


def _backends_started() -> bool:
    try:
        from jax._src import xla_bridge
    except ImportError:  # JAX not importable or its layout changed: assume not started
        return False
    started = getattr(xla_bridge, "backends_are_initialized", None)
    return bool(started()) if started is not None else False
