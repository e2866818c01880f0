"""The implicit adjoint of the edge alignment's optimum (``learn.differentiable``): the pose
T* as its 12 parameters (``flat``, ``unflat``), passed through unchanged forward; its
vector-Jacobian product is the implicit function theorem on the stationarity F(T*, inputs) =
J^T W r = 0, with the tracker's decisions (inliers, consistency) held fixed."""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp

from ..geometry import Pose


def flat(T: Pose) -> jnp.ndarray:
    """A pose's parameters as one array (12,): R row by row, then t."""
    return jnp.concatenate([T.R.reshape(-1), T.t])


def unflat(x: jnp.ndarray) -> Pose:
    """The pose of parameters ``x`` (12,) (``flat``'s inverse)."""
    return Pose(x[:9].reshape(3, 3), x[9:])


def _tangent_cotangent(T: Pose, ct: jnp.ndarray) -> jnp.ndarray:
    """Cotangent of the pose parameters (``flat``, 12) -> of a left twist at T (6)."""
    _, vjp = jax.vjp(lambda xi: flat(T.retract(xi)), jnp.zeros(6, ct.dtype))
    return vjp(ct)[0]


@partial(jax.custom_vjp, nondiff_argnums=(0,))
def implicit_pose(stationarity, T_params: jnp.ndarray, inputs) -> jnp.ndarray:
    """T* (``flat`` parameters, (12,)) unchanged; its VJP is the implicit function theorem
    on ``stationarity(T, inputs) = (F (6,), inliers)`` with F = 0 at T* (no step taken, so
    no gradient, where under 6 inliers)."""
    del stationarity, inputs
    return T_params


def _implicit_fwd(stationarity, T_params, inputs):
    return T_params, (T_params, inputs)


def _implicit_bwd(stationarity, res, ct):
    T_params, inputs = res
    T = unflat(T_params)
    ct_xi = _tangent_cotangent(T, ct)

    def F_xi(xi):
        return stationarity(T.retract(xi), inputs)[0]

    A = jax.jacfwd(F_xi)(jnp.zeros(6, T_params.dtype))  # dF/dxi (6, 6), exact
    F0, vjp_in, inliers = jax.vjp(lambda i: stationarity(T, i), inputs, has_aux=True)
    ok = inliers >= 6  # otherwise no step was taken and T* is no stationary point
    eye = jnp.eye(6, dtype=A.dtype)
    eps = jnp.finfo(A.dtype).eps * (jnp.abs(jnp.trace(A)) + 1.0)
    A = jnp.where(ok, A + eps * eye, eye)
    adj = jnp.linalg.solve(A.T, ct_xi)
    (ct_inputs,) = vjp_in(jnp.where(ok, -adj, 0.0))
    del F0
    return jnp.zeros_like(T_params), ct_inputs


implicit_pose.defvjp(_implicit_fwd, _implicit_bwd)
