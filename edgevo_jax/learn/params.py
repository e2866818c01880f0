"""Learnable parameters of the tracker: a pytree kept apart from the static ``Config``.

``Params.default(config)`` reproduces the untrained tracker: the Huber radii and the
consistency threshold are the config's, the re-observation offset is ``canny_high`` (the
paper's ``a``) and the per-edge weighting model outputs exactly 1 for every edge.

- ``log_huber`` (L,): log of the Huber radius of each pyramid level (pixels of that level);
  a log value keeps the radius positive under gradient steps.
- ``eta``: the gradient-consistency margin (g(p) . g(p') >= eta, paper: 0.6).
- ``log_temperature``: log of the temperature tau of the soft consistency weight
  sigmoid((g(p) . g(p') - eta) / tau) used by ``learn.differentiable``'s soft mode in place
  of the hard test; tau -> 0 gives the hard test back. The smooth training mode
  (``learn.smooth``) takes its temperatures from ``Smoothing`` instead, not learnt.
- ``reobs_a``: the offset of the re-observation probability 1 / (1 + exp(a - m_e)). It only
  enters edge selection (``learn.selection_scores``), never the alignment.
- ``weight_w1`` (HIDDEN, 6), ``weight_b1`` (HIDDEN,), ``weight_w2`` (HIDDEN,), ``weight_b2``:
  the per-edge weighting model (``robust.EdgeWeighting``), a one-hidden-layer network on the
  normalised edge features of ``robust.weighting_features`` (gradient magnitude, depth, depth
  discontinuity, residual, level, re-observation probability); each inlier's Huber weight is
  scaled by 2 * sigmoid(w2 . tanh(w1 f + b1) + b2), in (0, 2). The defaults have w2 = 0 and
  b2 = 0, so the scale is exactly 1 (the plain tracker), and w1 drawn once from a fixed seed
  (``WEIGHTING_SEED``; with w2 = 0 the first layer has no gradient until w2 moves off zero).
  The pose does not change under a scale common to all edges of a level, so only differences
  between edges (and between residuals) are learnt.
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

from ..config import Config
from ..derive import SolveKnobs, solve_knobs
from ..frontend.robust import NUM_FEATURES, EdgeWeighting

#: Default temperature of the soft gradient-consistency weight (see ``Params``): edges whose
#: g(p) . g(p') lies more than ~0.1 from eta get a weight within 1e-4 of the hard test's.
DEFAULT_TEMPERATURE = 0.01
#: Hidden units of the weighting model, and the seed of its default first layer.
HIDDEN = 8
WEIGHTING_SEED = 0
_WEIGHTING_FIELDS = ("weight_w1", "weight_b1", "weight_w2", "weight_b2")


def _default_w1() -> np.ndarray:
    """The default first layer (HIDDEN, NUM_FEATURES): N(0, 1 / NUM_FEATURES) entries from
    ``WEIGHTING_SEED`` (the features are O(1), so the hidden units start in tanh's slope)."""
    rng = np.random.default_rng(WEIGHTING_SEED)
    return rng.normal(0.0, 1.0 / np.sqrt(NUM_FEATURES), (HIDDEN, NUM_FEATURES))


class Params(NamedTuple):
    """Learnable parameters (a pytree of arrays); see the module docstring."""

    log_huber: jnp.ndarray
    eta: jnp.ndarray
    log_temperature: jnp.ndarray
    reobs_a: jnp.ndarray
    weight_w1: jnp.ndarray
    weight_b1: jnp.ndarray
    weight_w2: jnp.ndarray
    weight_b2: jnp.ndarray

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
            weight_w1=jnp.asarray(_default_w1(), dtype),
            weight_b1=jnp.zeros(HIDDEN, dtype),
            weight_w2=jnp.zeros(HIDDEN, dtype),
            weight_b2=jnp.zeros((), dtype),
        )

    @property
    def weighting_is_identity(self) -> bool:
        """Whether the weighting model scales every edge by exactly 1 (w2 = 0, b2 = 0; host
        side, concrete values only)."""
        return not (np.any(np.asarray(self.weight_w2) != 0) or np.asarray(self.weight_b2) != 0)

    def huber_delta(self, level: int) -> jnp.ndarray:
        """The Huber radius of ``level`` (pixels of that level)."""
        return jnp.exp(self.log_huber[level])

    @property
    def temperature(self) -> jnp.ndarray:
        """The soft consistency temperature tau."""
        return jnp.exp(self.log_temperature)


def _level_features(config: Config) -> np.ndarray:
    """Each level's feature value, level / (L - 1) (float64)."""
    n = config.num_levels
    return np.arange(n, dtype=np.float64) / max(n - 1, 1)


def weighting_of(params: Params, config: Config) -> EdgeWeighting:
    """The weighting model of ``params`` as the solve takes it (``robust.EdgeWeighting``;
    arrays of params' dtype, traceable)."""
    dtype = jnp.asarray(params.weight_w2).dtype
    return EdgeWeighting(*(jnp.asarray(getattr(params, f)) for f in _WEIGHTING_FIELDS),
                         jnp.asarray(config.canny_high, dtype),
                         jnp.asarray(_level_features(config), dtype))


def solve_knobs_of(params: Params, config: Config) -> SolveKnobs:
    """The plain tracker's ``SolveKnobs`` with the numbers of ``params`` (host side, numpy
    float32, for ``odometry.Odometry(..., params=...)``): Huber radius exp(log_huber) per
    level, consistency threshold eta, and the weighting model when it is not the identity
    (``Params.weighting_is_identity`` false; otherwise ``weighting`` stays None and the solve
    compiles to the program of ``derive.solve_knobs(config)``: ``Params.default(config)``
    gives the same numbers, hence the same trajectory). The plain tracker keeps the hard
    consistency test, so ``log_temperature`` does not enter; ``reobs_a`` enters the edge
    selection (``selection.keyframe_edges(..., reobs_a=)``), not the solve."""
    log_huber = np.asarray(params.log_huber, np.float64)
    if log_huber.shape != (config.num_levels,):
        raise ValueError(f"Params.log_huber has shape {log_huber.shape}, the config has "
                         f"{config.num_levels} pyramid levels")
    weighting = None
    if not params.weighting_is_identity:
        weighting = EdgeWeighting(*(np.asarray(getattr(params, f), np.float32)
                                    for f in _WEIGHTING_FIELDS),
                                  np.float32(config.canny_high),
                                  _level_features(config).astype(np.float32))
    return solve_knobs(config, huber_delta=np.exp(log_huber), eta=np.asarray(params.eta),
                       weighting=weighting)


def params_to_dict(params: Params) -> dict[str, float | list[float]]:
    """Params as plain numbers (JSON), one entry per field."""
    return {name: np.asarray(v, np.float64).tolist()
            for name, v in zip(Params._fields, params, strict=True)}


def params_from_dict(values: dict, config: Config) -> Params:
    """Params from ``params_to_dict``'s numbers (other keys are ignored; missing fields take
    ``Params.default(config)``'s values). ValueError for a field of the wrong shape, and for
    the linear weighting model of earlier versions (``weight_w``, ``weight_b``)."""
    if "weight_w" in values or "weight_b" in values:
        raise ValueError("these Params hold the earlier linear weighting model (weight_w, "
                         "weight_b); this version's model is weight_w1, weight_b1, weight_w2, "
                         "weight_b2: fit again with scripts/learn_weights.py")
    default = Params.default(config)
    fields = {}
    for name, d in zip(Params._fields, default, strict=True):
        if name not in values:
            fields[name] = d
            continue
        v = jnp.asarray(np.asarray(values[name], np.float64), d.dtype)
        if v.shape != d.shape:
            raise ValueError(f"Params.{name} must have shape {d.shape}, got {v.shape}")
        fields[name] = v
    return Params(**fields)


def flatten(params: Params) -> jnp.ndarray:
    """Every parameter in one vector (finite differences, optimisers over a flat vector)."""
    return jnp.concatenate([jnp.ravel(x) for x in params])


def unflatten(v: jnp.ndarray, like: Params) -> Params:
    """The inverse of ``flatten``: ``v`` cut into the shapes of ``like``'s fields."""
    out, i = [], 0
    for x in like:
        out.append(v[i:i + x.size].reshape(x.shape))
        i += x.size
    return Params(*out)
