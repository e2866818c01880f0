"""scripts/depth_step_offsets.py: the distance from an edge to the depth step along its
gradient (the measurement behind Config.activation_depth_reach)."""

from __future__ import annotations

import numpy as np
from conftest import load_script


def test_step_offsets_finds_the_step_and_skips_edges_without_one():
    module = load_script("depth_step_offsets")
    h, w = 40, 80
    uu = np.mgrid[0:h, 0:w][1]
    depth = np.where(uu < 40, 1.0, 1.5).astype(np.float32)  # the step between 39 and 40
    uv = np.array([[35.0, 39.0, 42.0, 47.0, 10.0], [20.0] * 5])
    grad = np.tile([[-1.0], [0.0]], 5)  # either direction along the line works
    got = module.step_offsets(depth, uv, grad, span=8)
    # 35 -> 4.5 px, 39 -> 0.5 px, 42 -> 2.5 px, 47 -> 7.5 px; the edge at 10 sees no step
    np.testing.assert_array_equal(got, [4.5, 0.5, 2.5, 7.5])
