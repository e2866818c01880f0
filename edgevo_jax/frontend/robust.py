"""Robust weighting: Huber influence as IRLS weights, and the learnable per-edge weighting
model that scales them (``params.Params``: weight_w, weight_b)."""

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
    each inlier's Huber weight is scaled by 2 * sigmoid(w . f + b), f (4, K) the edge
    features of ``weighting_features``; mag_scale () normalises the gradient magnitude (the
    Canny high threshold) and level_feature (L,) is each pyramid level's feature value."""

    w: jnp.ndarray
    b: jnp.ndarray
    mag_scale: jnp.ndarray
    level_feature: jnp.ndarray


def weighting_features(
    mag: jnp.ndarray, rho: jnp.ndarray, r: jnp.ndarray, gate: float | jnp.ndarray,
    level_feature: float | jnp.ndarray, mag_scale: float | jnp.ndarray,
) -> jnp.ndarray:
    """Normalised features (4, K) of K edges: log(m / mag_scale) of the gradient magnitude m
    (0 where m = 0, unknown), log depth (m) from the inverse depth rho, the residual r over
    the level's gate, and the level's feature value."""
    dtype = r.dtype
    f_mag = jnp.log(jnp.maximum(mag.astype(dtype), 1e-6) / mag_scale)
    f_depth = -jnp.log(jnp.maximum(rho.astype(dtype), 1e-6))
    f_level = jnp.full_like(r, level_feature)
    return jnp.stack([jnp.where(mag > 0, f_mag, 0.0), f_depth, r / gate, f_level])


def weighting_scale(w: jnp.ndarray, b: jnp.ndarray, features: jnp.ndarray) -> jnp.ndarray:
    """The model's scale (K,) of each edge's Huber weight: 2 * sigmoid(w . f + b) for
    features (4, K); exactly 1 at w = 0, b = 0."""
    return 2.0 * jax.nn.sigmoid(w @ features + b)


def edge_weights(
    weighting: EdgeWeighting, mag: jnp.ndarray, rho: jnp.ndarray, r: jnp.ndarray,
    gate: float | jnp.ndarray, level: int,
) -> tuple[jnp.ndarray, jnp.ndarray]:
    """The weighting model's scale (K,) of each edge at residuals r (K,) on ``level``, and
    its slope d scale / dr (K,) (the residual is one of its inputs), as
    ``align.robust_system`` takes them (``weight``, ``weight_slope``)."""

    def scale(r):
        f = weighting_features(mag, rho, r, gate, weighting.level_feature[level],
                               weighting.mag_scale)
        return weighting_scale(weighting.w, weighting.b, f)

    # elementwise in r: the JVP with ones is each weight's own slope
    return jax.jvp(scale, (r,), (jnp.ones_like(r),))

