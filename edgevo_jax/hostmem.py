"""Host arrays that JAX's CPU backend can use in place.

JAX hands a numpy array to its CPU device without a copy when the data starts on a 64-byte
boundary and copies it otherwise (~0.1 ms for one 640x480 float field, on every call that
takes it). The pre-processed frames and the small per-frame inputs are made aligned.
The way back (``to_host``) reads CPU results in place too.
"""

from __future__ import annotations

from functools import cache

import numpy as np


def aligned_empty(shape: tuple[int, ...], dtype: np.dtype | type, align: int = 64
                  ) -> np.ndarray:
    """An uninitialised array whose data starts on an ``align``-byte boundary: JAX's CPU
    backend uses such a numpy array in place, where it copies a misaligned one (~0.1 ms per
    640x480 float field, per call)."""
    n = int(np.prod(shape)) * np.dtype(dtype).itemsize
    buf = np.empty(n + align, np.uint8)
    start = (-buf.ctypes.data) % align
    return buf[start:start + n].view(dtype).reshape(shape)


def aligned_array(x: np.ndarray, dtype: np.dtype | type | None = None) -> np.ndarray:
    """A 64-byte aligned copy of x (optionally cast): see ``aligned_empty``."""
    x = np.asarray(x)
    out = aligned_empty(x.shape, dtype or x.dtype)
    out[...] = x
    return out


def aligned_stack(arrays: list[np.ndarray]) -> np.ndarray:
    """``np.stack(arrays)`` into a 64-byte aligned array (see ``aligned_empty``)."""
    first = np.asarray(arrays[0])
    out = aligned_empty((len(arrays), *first.shape), first.dtype)
    return np.stack(arrays, out=out)


@cache
def _on_cpu() -> bool:
    import jax

    return jax.default_backend() == "cpu"


def to_host(tree):
    """``jax.device_get`` of a pytree of arrays, as numpy arrays. On the CPU backend each
    array is read in place (np.asarray, ~5 us per array; device_get costs ~0.1 ms per call
    there, ~0.2 ms for a solve's results: a fifth of a frame's host work). Elsewhere
    device_get (it starts every copy before waiting for any). The arrays may be read-only."""
    import jax

    return jax.tree.map(np.asarray, tree) if _on_cpu() else jax.device_get(tree)
