"""Robust weighting: Huber influence as IRLS weights."""

from __future__ import annotations

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
