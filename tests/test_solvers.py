"""The one Levenberg-Marquardt (solvers.py): it converges where optimistix's does, its damping
policy grows, shrinks and clips lam, and its acceptance, solve and update are pluggable."""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest

from edgevo_jax.solvers import (
    DAMPING,
    POSE_GRAPH_DAMPING,
    WINDOW_DAMPING,
    LevenbergMarquardt,
    LMState,
    euclidean_norm,
    lower_cost,
)

# y = a exp(b t) + c sampled with a fixed perturbation: a small nonlinear least-squares problem
T = np.linspace(0.0, 2.0, 25)
Y = 1.7 * np.exp(-1.3 * T) + 0.4 + 0.01 * np.sin(7.0 * T)
X0 = np.array([1.0, -0.5, 0.0])


def residuals(x: jnp.ndarray, _args=None) -> jnp.ndarray:
    return x[0] * jnp.exp(x[1] * jnp.asarray(T, x.dtype)) + x[2] - jnp.asarray(Y, x.dtype)


class System(NamedTuple):
    """J^T J (3, 3), J^T r (3,) and the cost 0.5 |r|^2 at a point."""

    H: jnp.ndarray
    g: jnp.ndarray
    cost: jnp.ndarray


def system_at(x: jnp.ndarray, _old=None) -> System:
    r = residuals(x)
    J = jax.jacfwd(residuals)(x)
    return System(J.T @ J, J.T @ r, 0.5 * r @ r)


def damped(x, s: System, lam):
    return -jnp.linalg.solve(s.H + lam * jnp.diag(jnp.diag(s.H)), s.g)


def plus(x, delta):
    return x + delta


def lm_solve(lm: LevenbergMarquardt, x0, tries: int, step_tol: float = 0.0, **step_kwargs):
    """``tries`` LM tries in a while loop, stopped early by ``continues``."""

    def cond(carry):
        i, state = carry
        return (i < tries) & lm.continues(state, step_tol)

    def body(carry):
        i, state = carry
        state, _ = lm.step(state, solve=damped, apply=plus, evaluate=system_at, **step_kwargs)
        return i + 1, state

    x0 = jnp.asarray(x0)
    _, state = jax.lax.while_loop(cond, body, (jnp.asarray(0), lm.init(x0, system_at(x0),
                                                                       x0.dtype)))
    return state


def test_converges_to_optimistix_levenberg_marquardt():
    with jax.enable_x64(True):
        ours = jax.jit(lambda x: lm_solve(DAMPING, x, 200, step_tol=1e-14))(X0)
        ref = optx.least_squares(residuals, optx.LevenbergMarquardt(rtol=1e-12, atol=1e-12),
                                 jnp.asarray(X0), max_steps=500)
        assert ours.x.dtype == jnp.float64
        np.testing.assert_allclose(ours.x, ref.value, rtol=1e-7, atol=1e-9)
        assert float(jnp.max(jnp.abs(ours.system.g))) < 1e-9  # stationary
        assert float(ours.system.cost) < float(system_at(jnp.asarray(X0)).cost)


def test_damping_policy_shrinks_grows_and_clips():
    lm = DAMPING
    assert (lm.lam_init, lm.shrink, lm.grow, lm.lam_min, lm.lam_max) == (1e-4, 0.1, 10.0,
                                                                       1e-6, 1e4)
    f32 = jnp.float32
    np.testing.assert_array_equal(lm.damping(jnp.asarray(1e-4, f32), True),
                                  jnp.asarray(1e-4, f32) * 0.1)
    np.testing.assert_array_equal(lm.damping(jnp.asarray(1e-4, f32), False),
                                  jnp.asarray(1e-4, f32) * 10.0)
    assert float(lm.damping(jnp.asarray(1e-6, f32), True)) == pytest.approx(1e-6)  # floor
    assert float(lm.damping(jnp.asarray(1e4, f32), False)) == pytest.approx(1e4)  # ceiling
    # the window's policy differs in its floor only (solvers.py says why)
    assert WINDOW_DAMPING == dataclasses.replace(DAMPING, lam_min=1e-7)
    assert float(WINDOW_DAMPING.damping(jnp.asarray(1e-6, f32), True)) == pytest.approx(1e-7)


def test_the_pose_graph_policy_retries_from_its_old_floor():
    """Kept tries shrink lam to 1e-12 (Gauss-Newton); a rejected one grows it from 1e-6."""
    lm, f64 = POSE_GRAPH_DAMPING, jnp.float64
    with jax.enable_x64(True):
        assert float(lm.damping(jnp.asarray(1e-11, f64), True)) == pytest.approx(1e-12)
        assert float(lm.damping(jnp.asarray(1e-12, f64), True)) == pytest.approx(1e-12)
        assert float(lm.damping(jnp.asarray(1e-12, f64), False)) == pytest.approx(1e-5)
        assert float(lm.damping(jnp.asarray(1e-3, f64), False)) == pytest.approx(1e-2)
    assert DAMPING.lam_retry == 0.0 and WINDOW_DAMPING.lam_retry == 0.0


def test_rejected_tries_keep_the_point_and_grow_lam():
    """With an acceptance that refuses everything, each try keeps x and its system, grows lam
    tenfold up to the ceiling and counts the rejects; ``continues`` stops on max_rejects."""
    x0 = jnp.asarray(X0, jnp.float32)
    state = DAMPING.init(x0, system_at(x0), jnp.float32)
    lams = []
    for k in range(1, 11):
        state, candidate = DAMPING.step(state, solve=damped, apply=plus, evaluate=system_at,
                                        accept=lambda old, new: jnp.asarray(False))
        lams.append(float(state.lam))
        np.testing.assert_array_equal(state.x, x0)
        np.testing.assert_array_equal(state.system.cost, system_at(x0).cost)
        assert int(state.rejects) == k
        assert float(state.step) > 0 and candidate.cost != state.system.cost
        assert bool(DAMPING.continues(state, 0.0, max_rejects=k + 1))
        assert not bool(DAMPING.continues(state, 0.0, max_rejects=k))
    np.testing.assert_allclose(lams[:8], 1e-4 * 10.0 ** np.arange(1, 9), rtol=1e-5)
    assert lams[8:] == pytest.approx([1e4, 1e4])


def test_acceptance_is_pluggable():
    """``lower_cost`` only keeps downhill tries; an acceptance that takes every try walks
    uphill; a kept try shrinks lam and resets the reject count."""
    x0 = jnp.asarray(X0, jnp.float32)
    s0 = system_at(x0)
    uphill = lambda x, s, lam: -damped(x, s, lam)  # noqa: E731
    state = DAMPING.init(x0, s0, jnp.float32, lam=1.0)._replace(
        rejects=jnp.asarray(2, jnp.int32))
    refused, _ = DAMPING.step(state, solve=uphill, apply=plus, evaluate=system_at,
                              accept=lower_cost)
    np.testing.assert_array_equal(refused.x, x0)
    taken, _ = DAMPING.step(state, solve=uphill, apply=plus, evaluate=system_at,
                            accept=lambda old, new: jnp.asarray(True))
    assert float(taken.system.cost) > float(s0.cost)
    assert int(taken.rejects) == 0 and float(taken.lam) == pytest.approx(0.1)
    downhill, _ = DAMPING.step(state, solve=damped, apply=plus, evaluate=system_at)
    assert float(downhill.system.cost) < float(s0.cost)


def test_step_norm_and_continues():
    """``step`` records ``norm(delta)`` (default: euclidean); ``continues`` compares it with
    step_tol, and max_rejects=None leaves the reject count out."""
    x0 = jnp.asarray(X0, jnp.float32)
    state = DAMPING.init(x0, system_at(x0), jnp.float32)
    assert np.isinf(state.step) and int(state.rejects) == 0
    new, _ = DAMPING.step(state, solve=damped, apply=plus, evaluate=system_at)
    delta = damped(x0, system_at(x0), state.lam)
    np.testing.assert_array_equal(new.step, euclidean_norm(delta))
    np.testing.assert_allclose(new.step, jnp.linalg.norm(delta), rtol=1e-6)
    ones, _ = DAMPING.step(state, solve=damped, apply=plus, evaluate=system_at,
                           norm=lambda d: jnp.asarray(1.0, jnp.float32))
    assert float(ones.step) == 1.0
    stuck = ones._replace(rejects=jnp.asarray(99, jnp.int32))
    assert bool(DAMPING.continues(stuck, 0.5)) and not bool(DAMPING.continues(stuck, 0.5, 3))
    assert not bool(DAMPING.continues(stuck, 1.5))


def test_state_is_a_pytree_through_scan_and_vmap():
    """The state crosses lax.scan and vmap (the learnt tracker's unrolled loop, batches)."""
    x0 = jnp.stack([jnp.asarray(X0, jnp.float32), jnp.asarray(X0, jnp.float32) + 0.1])

    def run(x):
        def body(state, _):
            return DAMPING.step(state, solve=damped, apply=plus, evaluate=system_at)[0], None

        return jax.lax.scan(body, DAMPING.init(x, system_at(x), jnp.float32), None, length=5)[0]

    out = jax.jit(jax.vmap(run))(x0)
    assert isinstance(out, LMState) and out.x.shape == (2, 3)
    for k in range(2):
        np.testing.assert_allclose(out.x[k], run(x0[k]).x, rtol=1e-5, atol=1e-6)
    assert dataclasses.is_dataclass(DAMPING) and hash(DAMPING) == hash(LevenbergMarquardt())
