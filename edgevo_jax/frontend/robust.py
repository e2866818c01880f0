"""Robust weighting: Huber influence as IRLS weights, and the learnable per-edge weighting
model that scales them (``params.Params``: weight_w1, weight_b1, weight_w2, weight_b2)."""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp


def huber_weights(r: jnp.ndarray, delta: float | jnp.ndarray) -> jnp.ndarray:
    """IRLS weights of the Huber loss: 1 for |r| <= delta, delta / |r| beyond.

    Minimising sum w_i r_i^2 with these weights re-solved each iteration minimises the Huber
    cost (EdgeVO's weighted distance residuals).
    """
    a = jnp.abs(r)
    return jnp.where(a <= delta, 1.0, delta / jnp.maximum(a, 1e-12))


def huber_cost(r: jnp.ndarray, delta: float | jnp.ndarray) -> jnp.ndarray:
    """Huber loss: r^2 / 2 for |r| <= delta, delta (|r| - delta / 2) beyond."""
    a = jnp.abs(r)
    return jnp.where(a <= delta, 0.5 * a * a, delta * (a - 0.5 * delta))


class EdgeWeighting(NamedTuple):
    """The per-edge weighting model as the solve takes it (``derive.SolveKnobs.weighting``):
    each inlier's Huber weight is scaled by 2 * sigmoid(w2 . tanh(w1 f + b1) + b2), a
    one-hidden-layer network on the edge features f (NUM_FEATURES, K) of
    ``weighting_features``; w1 (hidden, NUM_FEATURES), b1 (hidden,), w2 (hidden,), b2 ().
    mag_scale () normalises the gradient magnitude (the Canny high threshold, the paper's
    re-observation offset) and level_feature (L,) is each pyramid level's feature value."""

    w1: jnp.ndarray
    b1: jnp.ndarray
    w2: jnp.ndarray
    b2: jnp.ndarray
    mag_scale: jnp.ndarray
    level_feature: jnp.ndarray


#: The model's inputs, in the order of ``weighting_features``' rows.
FEATURES = ("gradient magnitude", "depth", "depth discontinuity", "residual", "level",
            "re-observation")
NUM_FEATURES = len(FEATURES)


def weighting_features(
    mag: jnp.ndarray, rho: jnp.ndarray, disc: jnp.ndarray, r: jnp.ndarray,
    gate: float | jnp.ndarray, level_feature: float | jnp.ndarray,
    mag_scale: float | jnp.ndarray,
) -> jnp.ndarray:
    """Normalised features (NUM_FEATURES, K) of K edges, each O(1): log(m / mag_scale) of
    the gradient magnitude m (0 where m = 0, unknown); log depth (m) from the inverse depth
    rho; log(1 + 10 disc) of the depth discontinuity (``selection.depth_discontinuity``,
    (max - min) / z of the depths around the edge); the residual r over the level's gate;
    the level's feature value; the re-observation probability 1 / (1 + exp(mag_scale - m))
    of edge selection (0 where m = 0)."""
    dtype = r.dtype
    known = mag > 0
    m = mag.astype(dtype)
    f_mag = jnp.where(known, jnp.log(jnp.maximum(m, 1e-6) / mag_scale), 0.0)
    f_depth = -jnp.log(jnp.maximum(rho.astype(dtype), 1e-6))
    f_disc = jnp.log1p(10.0 * jnp.maximum(disc.astype(dtype), 0.0))
    f_level = jnp.full_like(r, level_feature)
    f_reobs = jnp.where(known, jax.nn.sigmoid(m - mag_scale), 0.0)
    return jnp.stack([f_mag, f_depth, f_disc, r / gate, f_level, f_reobs])


def weighting_scale(weighting: EdgeWeighting, features: jnp.ndarray) -> jnp.ndarray:
    """The model's scale (K,) of each edge's Huber weight for features (NUM_FEATURES, K):
    2 * sigmoid(w2 . tanh(w1 f + b1) + b2); exactly 1 at w2 = 0, b2 = 0."""
    hidden = jnp.tanh(weighting.w1 @ features + weighting.b1[:, None])
    return 2.0 * jax.nn.sigmoid(weighting.w2 @ hidden + weighting.b2)


def edge_weights(
    weighting: EdgeWeighting, mag: jnp.ndarray, rho: jnp.ndarray, disc: jnp.ndarray,
    r: jnp.ndarray, gate: float | jnp.ndarray, level: int,
) -> tuple[jnp.ndarray, jnp.ndarray]:
    """The weighting model's scale (K,) of each edge at residuals r (K,) on ``level``, and
    its slope d scale / dr (K,) (the residual is one of its inputs), as
    ``align.robust_system`` takes them (``weight``, ``weight_slope``)."""

    def scale(r):
        f = weighting_features(mag, rho, disc, r, gate, weighting.level_feature[level],
                               weighting.mag_scale)
        return weighting_scale(weighting, f)

    # elementwise in r: the JVP with ones is each weight's own slope
    return jax.jvp(scale, (r,), (jnp.ones_like(r),))
