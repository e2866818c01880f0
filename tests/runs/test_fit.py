"""edgevo_jax.runs.fit, the parts of scripts/learn_weights.py that need no tracking: the
items a part of a clip gives, evaluation in fixed-size chunks, adam over minibatches with
the fixed Params held and a non-finite step skipped, and the learnt weight's curves (the
whole fit end to end: tests/test_learn_script.py)."""

from __future__ import annotations

import math
from types import SimpleNamespace

import jax.numpy as jnp
import numpy as np
import pytest

from edgevo_jax import Config
from edgevo_jax.cli import BUNDLED_CLIP
from edgevo_jax.datasets import load_sequence
from edgevo_jax.frontend.robust import FEATURES
from edgevo_jax.learn.params import Params
from edgevo_jax.runs import fit


def _part(frames: tuple[int, int], with_gt: set[int]) -> fit.Part:
    return fit.Part(None, 1, frames, {i: np.eye(4) for i in with_gt})


def test_pairs_and_windows_stay_inside_the_part_and_need_ground_truth():
    part = _part((2, 7), {2, 3, 4, 6})  # frame 5 has no ground truth
    assert part.pairs([1, 2]) == [((1, 2), (1, 3)), ((1, 2), (1, 4)), ((1, 3), (1, 4)),
                                  ((1, 4), (1, 6))]
    assert part.windows(2) == [((1, 2), [(1, 3), (1, 4)])]
    assert _part((0, 3), {0, 1, 2}).windows(3) == []  # a window needs size + 1 frames


def test_make_part_clips_the_range_and_interpolates_the_ground_truth():
    seq = load_sequence(BUNDLED_CLIP)
    part = fit.make_part(seq, 0, (5, 100))
    assert part.frames == (5, len(seq)) and part.index == 0
    assert set(part.gt) <= set(range(5, len(seq))) and part.gt
    assert all(T.shape == (4, 4) and np.isfinite(T).all() for T in part.gt.values())


def test_evaluate_and_mean_loss_count_every_item_once():
    """7 items in chunks of 3: the last chunk is padded by repetition, the padding left out."""
    t = np.arange(7, dtype=np.float64) * 1e-3  # m
    r = np.full(7, 0.01)  # rad
    calls = []

    def err(params, ki, fi, T):
        calls.append(len(ki))
        return t[np.asarray(ki)], r[np.asarray(ki)]

    ki = np.arange(7)
    out = fit.evaluate(err, None, ki, ki, np.zeros((7, 4, 4)), batch=3, rot_weight=0.1)
    assert calls == [3, 3, 3]
    assert out["pairs"] == 7 and out["t_mean_mm"] == pytest.approx(3.0)
    assert out["t_median_mm"] == pytest.approx(3.0)
    assert out["r_mean_deg"] == pytest.approx(math.degrees(0.01))
    assert out["loss"] == pytest.approx(np.mean(t + 0.1 * r))
    mean = fit.mean_loss(lambda p, i: np.asarray(i, float) ** 2, None, (ki,), batch=3)
    assert mean == pytest.approx(np.mean(np.arange(7.0) ** 2))


def test_train_moves_the_fitted_params_and_skips_a_non_finite_step():
    pytest.importorskip("optax")
    params0 = Params.default(Config(), jnp.float32)
    params0 = params0._replace(weight_b2=jnp.float32(1.0))
    calls = []

    def vg(params, idx):  # the loss 0.5 |params|^2 over the fitted leaves: its gradient
        calls.append(np.asarray(idx))  # is those params (the smooth mode gives FIXED none)
        grads = params._replace(**{k: jnp.zeros_like(getattr(params, k)) for k in fit.FIXED})
        if len(calls) == 2:
            grads = grads._replace(eta=jnp.full_like(params.eta, jnp.nan))
        return 0.5 * sum(jnp.sum(p * p) for p in params), grads

    def value(params, idx):
        return jnp.full(idx.shape, float(params.weight_b2))

    items = (jnp.arange(5),)
    params, losses, full = fit.train(vg, value, params0, items, steps=3, batch=2, lr=0.1,
                                     rng=np.random.default_rng(0), start_loss=1.0)
    assert len(losses) == 3 and len(full) == 4 and full[0] == 1.0
    assert full[2] == full[1]  # the skipped step leaves the loss as it was
    assert all(len(c) == 2 and len(set(c.tolist())) == 2 for c in calls)
    assert float(params.weight_b2) < 1.0  # two adam steps of 0.1 towards 0
    assert float(params.weight_b2) == pytest.approx(full[-1])
    for name in fit.FIXED:
        np.testing.assert_array_equal(getattr(params, name), getattr(params0, name))


def test_weight_curves_are_one_for_the_default_params():
    config = Config()
    rng = np.random.default_rng(0)
    n = 50
    kf = SimpleNamespace(valid=np.arange(n) < 40, mag=rng.uniform(50, 200, n),
                         rho=rng.uniform(0.3, 2.0, n), disc=rng.uniform(0, 0.2, n))
    params = Params.default(config, jnp.float32)
    curves = fit.weight_curves(params, config, {"kf": kf}, points=5)
    assert list(curves) == list(FEATURES)
    for c in curves.values():
        assert len(c["feature"]) == len(c["weight"]) == 5
        assert c["edges_5_95"][0] <= c["edges_5_95"][1]
        np.testing.assert_allclose(c["weight"], 1.0, rtol=1e-6)
    moved = fit.weight_curves(params._replace(weight_b2=jnp.float32(0.5)), config,
                              {"kf": kf}, points=5)
    assert all(not np.allclose(c["weight"], 1.0) for c in moved.values())
