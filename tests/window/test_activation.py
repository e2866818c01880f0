"""Each activation rule on its own, and the gradient carried through the warp."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from edgevo_jax.camera import Intrinsics, unproject
from edgevo_jax.geometry import Pose
from edgevo_jax.window.activation import activate, carried_gradient

W, H = 100, 60


FILLER = 6  # valid edges with large residuals in the bottom row: they lift the median


def run(uv, r, cos, tracks, valid=None, filler=True):
    """Activation of the given edges (filler edges appended and dropped from the result)."""
    k = len(r)
    if filler:
        uv = list(uv) + [(10 + 15 * i, 55) for i in range(FILLER)]
        r, cos, tracks = list(r) + [50.0] * FILLER, list(cos) + [1.0] * FILLER, \
            list(tracks) + [0] * FILLER
        valid = None if valid is None else list(valid) + [True] * FILLER
    uv = jnp.asarray(np.asarray(uv, np.float32).T)
    n = uv.shape[1]
    valid = jnp.ones(n, bool) if valid is None else jnp.asarray(valid)
    return np.asarray(activate(uv, jnp.asarray(r, jnp.float32), jnp.asarray(cos, jnp.float32),
                               jnp.asarray(tracks, jnp.int32), valid, width=W, height=H,
                               cell=20))[:k]


def test_residual_must_be_under_the_median():
    # four edges in four cells, all agreeing in gradient and equally tracked
    uv = [(5, 5), (25, 5), (45, 5), (65, 5)]
    got = run(uv, [0.1, 0.2, 3.0, 4.0], [1, 1, 1, 1], [1, 1, 1, 1], filler=False)
    assert got.tolist() == [True, True, False, False]


def test_gradient_must_agree_within_30_degrees():
    uv = [(5, 5), (25, 5), (45, 5), (65, 5), (85, 5)]
    cos = [np.cos(np.radians(a)) for a in (0, 29, 31, 90, 0)]
    got = run(uv, [0.1, 0.1, 0.1, 0.1, 60.0], cos, [1] * 5)
    assert got.tolist() == [True, True, False, False, False]


def test_longest_tracked_wins_its_cell_even_with_a_larger_residual():
    uv = [(5, 5), (6, 6), (7, 7), (45, 45), (46, 46), (85, 5)]
    got = run(uv, [0.3, 0.1, 0.2, 0.1, 0.1, 60.0], [1] * 6, [7, 2, 3, 1, 1, 1])
    assert got.tolist() == [True, False, False, True, False, False]  # ties: smaller residual,
    # then lower index


def test_at_most_one_edge_per_cell_and_invalid_edges_never():
    rng = np.random.default_rng(0)
    uv = np.stack([rng.uniform(0, W - 1, 300), rng.uniform(0, H - 1, 300)], axis=1)
    valid = rng.random(300) > 0.2
    got = run(uv, rng.random(300), np.ones(300), rng.integers(0, 5, 300), valid, filler=False)
    cells = (np.floor((uv[:, 1] + 0.5) / 20) * 5 + np.floor((uv[:, 0] + 0.5) / 20))[got]
    assert len(set(cells.tolist())) == got.sum() > 0
    assert not np.any(got & ~valid)


def test_carried_gradient_follows_an_in_plane_rotation():
    intr = Intrinsics(500.0, 500.0, 320.0, 240.0)
    uv = jnp.asarray([[320.0, 400.0, 250.0], [240.0, 300.0, 100.0]])
    pts = unproject(intr, uv, jnp.asarray([0.5, 0.4, 0.8]))
    g = jnp.asarray([[1.0, 0.0, 0.6], [0.0, 1.0, 0.8]])
    np.testing.assert_allclose(carried_gradient(intr, Pose.identity(), pts, g), g,
                               atol=1e-4)
    angle = np.radians(10.0)
    T = Pose.exp(jnp.asarray([0.0, 0.0, 0.0, 0.0, 0.0, angle], jnp.float32))
    out = np.asarray(carried_gradient(intr, T, pts, g))
    expect = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]]) @ g
    np.testing.assert_allclose(out, expect, atol=1e-4)
