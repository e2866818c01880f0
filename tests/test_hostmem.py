"""hostmem: aligned host arrays equal to what they replace, on 64-byte boundaries."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from edgevo_jax.hostmem import aligned_array, aligned_empty, aligned_stack
from edgevo_jax.image.preprocess import distance_pyramid, preprocess


@given(shape=st.lists(st.integers(1, 9), min_size=0, max_size=3),
       dtype=st.sampled_from([np.uint8, np.int32, np.float32, np.float64, np.bool_]))
@settings(max_examples=40, deadline=None)
def test_aligned_arrays(shape, dtype):
    shape = tuple(shape)
    assert aligned_empty(shape, dtype).ctypes.data % 64 == 0
    x = (np.arange(int(np.prod(shape))) % 7).reshape(shape).astype(dtype)
    y = aligned_array(x)
    assert y.ctypes.data % 64 == 0 and y.dtype == x.dtype and np.array_equal(x, y)
    z = aligned_stack([x, x + 1 if dtype != np.bool_ else ~x])
    assert z.ctypes.data % 64 == 0 and np.array_equal(z, np.stack([x, z[1]])) and z.shape[0] == 2


def test_preprocessed_frames_are_aligned():
    rng = np.random.default_rng(0)
    rgb = (rng.random((48, 64, 3)) * 255).astype(np.uint8)
    depth = rng.uniform(0.5, 3.0, (48, 64)).astype(np.float32)
    from edgevo_jax import Config

    frame = preprocess(rgb, depth, Config())
    for a in (*frame.dist, *(m for m in frame.edge_map if m is not None)):
        assert a.ctypes.data % 64 == 0
    levels = distance_pyramid(frame.dist[0], 3)
    assert all(a.ctypes.data % 64 == 0 for a in levels)
