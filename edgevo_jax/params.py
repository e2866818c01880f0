"""Learnable parameters of the tracker: a pytree kept apart from the static ``Config``.

``Params.default(config)`` reproduces the untrained tracker: the Huber radii and the
consistency threshold are the config's, the re-observation offset is ``canny_high`` (the
paper's ``a``) and the per-edge weighting model outputs exactly 1 for every edge.

- ``log_huber`` (L,): log of the Huber radius of each pyramid level (pixels of that level);
  a log value keeps the radius positive under gradient steps.
- ``eta``: the gradient-consistency margin (g(p) . g(p') >= eta, paper: 0.6).
- ``log_temperature``: log of the temperature tau of the soft consistency weight
  sigmoid((g(p) . g(p') - eta) / tau) used by the differentiable path (``learn.py``) in
  place of the hard test; tau -> 0 gives the hard test back.
- ``reobs_a``: the offset of the re-observation probability 1 / (1 + exp(a - m_e)). It only
  enters edge selection (``learn.selection_scores``), never the alignment.
- ``weight_w`` (4,), ``weight_b``: a linear layer on the normalised edge features of
  ``edge_features`` (gradient magnitude, depth, residual, level); each inlier's Huber weight
  is scaled by 2 * sigmoid(w . f + b), in (0, 2), which is exactly 1 at w = 0, b = 0.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from .config import Config

#: Default temperature of the soft gradient-consistency weight (see ``Params``): edges whose
#: g(p) . g(p') lies more than ~0.1 from eta get a weight within 1e-4 of the hard test's.
DEFAULT_TEMPERATURE = 0.01
NUM_FEATURES = 4


class Params(NamedTuple):
    """Learnable parameters (a pytree of arrays); see the module docstring."""

    log_huber: jnp.ndarray
    eta: jnp.ndarray
    log_temperature: jnp.ndarray
    reobs_a: jnp.ndarray
    weight_w: jnp.ndarray
    weight_b: jnp.ndarray

    @staticmethod
    def default(config: Config, dtype: jnp.dtype | None = None) -> Params:
        """The parameters of the untrained tracker of ``config`` (float32 unless x64 is on,
        or ``dtype``)."""
        dtype = dtype or jnp.result_type(float)
        return Params(
            log_huber=jnp.log(jnp.asarray(config.huber_delta, dtype)),
            eta=jnp.asarray(config.eta, dtype),
            log_temperature=jnp.log(jnp.asarray(DEFAULT_TEMPERATURE, dtype)),
            reobs_a=jnp.asarray(config.canny_high, dtype),
            weight_w=jnp.zeros(NUM_FEATURES, dtype),
            weight_b=jnp.zeros((), dtype),
        )

    def huber_delta(self, level: int) -> jnp.ndarray:
        """The Huber radius of ``level`` (pixels of that level)."""
        return jnp.exp(self.log_huber[level])

    @property
    def temperature(self) -> jnp.ndarray:
        """The soft consistency temperature tau."""
        return jnp.exp(self.log_temperature)


def edge_features(
    mag: jnp.ndarray, rho: jnp.ndarray, r: jnp.ndarray, level: int, config: Config
) -> jnp.ndarray:
    """Normalised features (4, K) of K edges: log(m / canny_high) of the gradient magnitude m
    (0 at the culling threshold; pass zeros when unknown), log depth (m), the residual over
    the level's gate, and the level over the coarsest one."""
    dtype = r.dtype
    f_mag = jnp.log(jnp.maximum(mag.astype(dtype), 1e-6) / config.canny_high)
    f_depth = -jnp.log(jnp.maximum(rho.astype(dtype), 1e-6))
    f_res = r / config.max_residual[level]
    f_level = jnp.full_like(r, level / max(config.num_levels - 1, 1))
    return jnp.stack([jnp.where(mag > 0, f_mag, 0.0), f_depth, f_res, f_level])


def edge_weight(params: Params, features: jnp.ndarray) -> jnp.ndarray:
    """The weighting model's scale (K,) of each edge's Huber weight: 2 * sigmoid(w . f + b)
    for features (4, K); exactly 1 with the default (zero) weights."""
    return 2.0 * jax.nn.sigmoid(params.weight_w @ features + params.weight_b)
