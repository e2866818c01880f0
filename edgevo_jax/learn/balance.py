"""The depth residual's weight against the edges (``Config.depth_weight``, w), learnt by
implicit differentiation of the plain tracker's solve.

At the pose T* that ``align.track`` returns, the level-0 normal equations' gradient vanishes,
F(T*, w) = g_edges(T*) + w g_depth(T*) = 0, with the hard decisions (gates, the consistency
test, the nearest pixels of the depth lookup) those taken at T*. The implicit function
theorem gives the pose's derivative along a left twist, d xi / d w = -(dF/dxi)^-1 dF/dw,
both derivatives exact (``jax.jacfwd`` of ``align.normal_equations``, decisions held as
constants). A pose loss L(T*) against the true relative pose (``losses.rpe_loss``) then has
dL / d log w = w (dL/dxi . d xi / d w). The solve's start, the coarse levels and the rolling
shutter's previous pose are constants of the derivative (a converged level-0 pose depends on
none of them through F).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from ..camera import Intrinsics, unproject
from ..derive import SolveKnobs, SolveStructure
from ..frontend.align import normal_equations, track
from ..frontend.selection import KeyframeEdges
from ..frontend.shutter import Shutter
from ..geometry import Pose
from ..image.preprocess import EdgeMap
from .losses import rpe_loss


class WeightGradient(NamedTuple):
    """One pair's solve and its sensitivity to the depth weight: ``T_c_k`` (4, 4) the
    solve's T_cur_kf, ``loss`` () its ``rpe_loss`` (m + rot_weight rad) against the truth,
    ``grad_log_weight`` () dL / d log w, ``pose_rate`` (6,) d xi / d log w (the pose's
    change along a left twist [v, w] per unit of log w), ``inliers`` () level-0 inlier
    edges."""

    T_c_k: jnp.ndarray
    loss: jnp.ndarray
    grad_log_weight: jnp.ndarray
    pose_rate: jnp.ndarray
    inliers: jnp.ndarray


def depth_weight_gradient(
    kf: KeyframeEdges,
    dist: tuple[jnp.ndarray, ...],
    edge_map: EdgeMap,
    T_init: jnp.ndarray,
    intr: Intrinsics,
    knobs: SolveKnobs,
    T_true: jnp.ndarray,
    *,
    config: SolveStructure,
    shutter: Shutter | None = None,
    rot_weight: float = 0.1,
) -> WeightGradient:
    """Solve one pair as the tracker does (``align.track`` with ``knobs``, whose
    ``depth_weight`` is w) from T_init (4, 4), and return the pose loss against the true
    T_cur_kf ``T_true`` (4, 4, metres) with its derivative in log w (module docstring).
    ``kf`` needs depth points (``depth_pts``) and ``edge_map`` a depth map, else the
    derivative is 0. Jit with ``config`` static."""
    res = track(kf, dist, edge_map, T_init, intr, config, knobs, shutter)
    dtype = dist[0].dtype
    T = Pose.from_matrix(jnp.asarray(res.T_c_k, dtype))
    pts_k = unproject(intr, kf.uv, kf.rho)
    w = jnp.asarray(knobs.depth_weight, dtype)

    def F(xi, weight):
        k = knobs._replace(depth_weight=weight)
        return normal_equations(T.retract(xi), pts_k, kf, dist[0], edge_map, intr, 0, k,
                                shutter).g

    zero = jnp.zeros(6, dtype)
    A, b = jax.jacfwd(F, argnums=(0, 1))(zero, w)
    A = A + jnp.finfo(dtype).eps * (jnp.abs(jnp.trace(A)) + 1.0) * jnp.eye(6, dtype=dtype)
    dxi_dw = -jnp.linalg.solve(A, b)

    def loss_at(xi):
        return rpe_loss(T.retract(xi).as_matrix(), jnp.asarray(T_true, dtype),
                        rot_weight=rot_weight)

    loss, dL_dxi = jax.value_and_grad(loss_at)(zero)
    ok = res.inliers >= 6  # otherwise no step was taken and T* is no stationary point
    rate = jnp.where(ok, w * dxi_dw, 0.0)
    return WeightGradient(res.T_c_k, loss, dL_dxi @ rate, rate, res.inliers)
