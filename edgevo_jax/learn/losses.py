"""Differentiable pose losses against ground truth (safe at zero error): ``rpe_loss`` /
``pose_loss`` of one relative pose; ``window_rpe_loss``, the mean RPE of the motions
between frames i and i + d of a window; ``ate_loss``, the ATE of a chunk after rigid
alignment, equal to TUM's ``evaluate_ate`` (``metrics.ate``). Poses are T_world_cam
(..., 4, 4) in metres."""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp

from ..geometry import Pose


def _safe_norm(x: jnp.ndarray) -> jnp.ndarray:
    """Euclidean norm with a zero (not NaN) gradient at 0."""
    sq = jnp.sum(x * x)
    pos = sq > 0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, sq, 1.0)), 0.0)


def _relative(T_est: jnp.ndarray, T_gt: jnp.ndarray) -> tuple[jnp.ndarray, jnp.ndarray]:
    """E = T_gt^-1 T_est as (rotation (3, 3), translation (3,)), from 4x4 matrices."""
    E = Pose.from_matrix(T_gt, orthonormalise=None).inverse() \
        @ Pose.from_matrix(T_est, orthonormalise=None)
    return E.R, E.t


def relative_pose_error(T_est: jnp.ndarray, T_gt: jnp.ndarray) -> tuple[jnp.ndarray, jnp.ndarray]:
    """Translation (m) and rotation (rad) error of an estimated relative pose T_est (4, 4)
    against the true one T_gt: of E = T_gt^-1 T_est. The angle comes from the chordal
    distance, 2 asin(|R_E - I|_F / sqrt(8)), so its gradient is finite everywhere (and 0
    at E = I, where a norm's is not defined)."""
    R, t = _relative(T_est, T_gt)
    chord = _safe_norm(R - jnp.eye(3, dtype=R.dtype))
    angle = 2.0 * jnp.arcsin(jnp.clip(chord / jnp.sqrt(8.0), 0.0, 1.0 - 1e-12))
    return _safe_norm(t), angle


def rpe_loss(T_est: jnp.ndarray, T_gt: jnp.ndarray, *, rot_weight: float = 1.0) -> jnp.ndarray:
    """Relative-pose error, translation (m) + rot_weight * rotation (rad)."""
    t_err, r_err = relative_pose_error(T_est, T_gt)
    return t_err + rot_weight * r_err


def pose_loss(T_est: jnp.ndarray, T_gt: jnp.ndarray, *, rot_weight: float = 1.0) -> jnp.ndarray:
    """Smooth squared relative-pose error: |t_E|^2 + rot_weight^2 |R_E - I|_F^2 / 2 of
    E = T_gt^-1 T_est (the rotation term is 2 (1 - cos angle) ~ angle^2)."""
    R, t = _relative(T_est, T_gt)
    rot = jnp.sum((R - jnp.eye(3, dtype=R.dtype)) ** 2) / 2.0
    return jnp.sum(t * t) + rot_weight**2 * rot


def window_rpe_loss(
    T_est: jnp.ndarray,
    T_gt: jnp.ndarray,
    *,
    rot_weight: float = 1.0,
    deltas: tuple[int, ...] = (1,),
    valid: jnp.ndarray | None = None,
) -> jnp.ndarray:
    """Relative-pose error over a window of N poses: the mean ``rpe_loss`` (translation m +
    rot_weight * rotation rad) of the motions between frames i and i + d, d in ``deltas``
    (frames, static), estimated against true.

    T_est, T_gt (N, 4, 4): each frame's pose in one fixed frame, T_ref_cam (world poses, or
    inv(T_c_k) of frames tracked against a keyframe); the motion i -> j is P_i^-1 P_j, as
    TUM's and evo's RPE take it (``metrics.rpe``). ``valid`` (N,)
    bool: frames to use (a pair counts when both are valid; 0 when none does)."""
    n = T_est.shape[0]
    pairs = [(i, i + d) for d in deltas for i in range(n - d)]
    if not pairs:
        raise ValueError(f"a window of {n} poses has no pair {deltas} frames apart")
    i, j = (jnp.asarray(x) for x in zip(*pairs, strict=True))
    inv_est, inv_gt = (Pose.from_matrix(T, orthonormalise=None).inverse().as_matrix()
                       for T in (T_est, T_gt))
    rel_est, rel_gt = inv_est[i] @ T_est[j], inv_gt[i] @ T_gt[j]
    losses = jax.vmap(partial(rpe_loss, rot_weight=rot_weight))(rel_est, rel_gt)
    if valid is None:
        return jnp.mean(losses)
    w = (valid[i] & valid[j]).astype(losses.dtype)
    return jnp.sum(w * losses) / jnp.maximum(jnp.sum(w), 1.0)


def rigid_alignment(
    model: jnp.ndarray, data: jnp.ndarray, weights: jnp.ndarray | None = None
) -> tuple[jnp.ndarray, jnp.ndarray]:
    """R (3, 3), t (3,) minimising sum_i w_i |R m_i + t - d_i|^2 over rotations (no scale)
    for points model, data (N, 3): Horn / Umeyama through the SVD of the cross-covariance,
    with TUM's reflection fix (``metrics.horn_align``, in JAX). Not meant to be
    differentiated (singular vectors are not smooth where singular values meet):
    ``ate_loss`` holds it constant."""
    w = jnp.ones(model.shape[0], model.dtype) if weights is None else weights.astype(model.dtype)
    total = jnp.maximum(jnp.sum(w), 1e-30)
    mu_m = (w @ model) / total
    mu_d = (w @ data) / total
    cross = (data - mu_d).T @ ((model - mu_m) * w[:, None])  # sum_i w_i d_i m_i^T
    u, _, vh = jnp.linalg.svd(cross)
    flip = jnp.linalg.det(u) * jnp.linalg.det(vh) < 0
    s = jnp.diag(jnp.array([1.0, 1.0, 1.0], model.dtype).at[2].set(jnp.where(flip, -1.0, 1.0)))
    R = u @ s @ vh
    return R, mu_d - R @ mu_m


def ate_loss(
    T_est: jnp.ndarray, T_gt: jnp.ndarray, *, valid: jnp.ndarray | None = None
) -> jnp.ndarray:
    """ATE of a chunk (m): the RMS position error after aligning the estimated positions
    (translations of T_est (N, 4, 4), T_world_cam or any fixed frame) onto the true ones
    (T_gt) by the best rigid motion (``rigid_alignment``, no scale), as TUM's
    ``evaluate_ate`` (``metrics.ate``'s rmse) on the same, associated poses. ``valid`` (N,)
    bool: poses to use (>= 3 needed for a unique alignment).

    Differentiable with safe gradients: the alignment is held constant (stop_gradient),
    which gives the exact gradient of the aligned sum of squares (the alignment minimises
    it: by the envelope theorem its own change does not contribute), with no SVD derivative
    (undefined where singular values meet, as for straight-line motion); the square root
    has gradient 0 (not NaN) at 0."""
    p, q = T_est[:, :3, 3], T_gt[:, :3, 3]
    w = jnp.ones(p.shape[0], p.dtype) if valid is None else valid.astype(p.dtype)
    R, t = rigid_alignment(*jax.lax.stop_gradient((p, q)), w)
    err = p @ R.T + t - q
    mse = jnp.sum(w * jnp.sum(err * err, axis=1)) / jnp.maximum(jnp.sum(w), 1.0)
    pos = mse > 0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, mse, 1.0)), 0.0)

