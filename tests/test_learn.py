"""Gradients of the pose w.r.t. the learnable Params on real frames (bundled fr1/xyz clip):
both adjoints against central finite differences in float64, implicit vs unrolled at a
converged pose, finiteness with empty masks, the defaults reproducing ``solve.track``, and
the relative-pose losses."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
import pytest

from edgevo_jax import Config
from edgevo_jax.cli import BUNDLED_CLIP
from edgevo_jax.datasets import groundtruth_pose_at, load_sequence
from edgevo_jax.geometry import inverse_np
from edgevo_jax.io import poses7_to_matrices
from edgevo_jax.learn import (
    edge_magnitudes,
    pose_loss,
    relative_pose_error,
    rpe_loss,
    selection_scores,
    track_differentiable,
)
from edgevo_jax.params import Params
from edgevo_jax.preprocess import preprocess
from edgevo_jax.selection import keyframe_edges
from edgevo_jax.solve import KeyframeEdges, track

CONFIG = Config(num_edges=128)
NAMES = ["log_huber0", "log_huber1", "log_huber2", "eta", "log_temperature", "reobs_a",
         "w_mag", "w_depth", "w_residual", "w_level", "b"]
_diff = jax.jit(track_differentiable,
                static_argnames=("config", "adjoint", "consistency", "checkpoint"))


@pytest.fixture(scope="module")
def clip():
    """Keyframe edges of frame 0 (128, spg), their magnitudes, and frames 1-5 (numpy)."""
    seq = load_sequence(BUNDLED_CLIP)
    f0 = preprocess(*seq.load_frame(0), CONFIG)
    edges = keyframe_edges(f0, CONFIG, seed=0, intr=seq.intrinsics)
    frames = {k: preprocess(*seq.load_frame(k), CONFIG) for k in (1, 2, 5)}
    gt = {k: poses7_to_matrices(groundtruth_pose_at(seq, seq.timestamps[k])[None])[0]
          for k in (0, 1, 2, 5)}
    T_gt = {k: inverse_np(gt[k]) @ gt[0] for k in (1, 2, 5)}  # T_cur_kf
    return seq, edges, edge_magnitudes(f0, edges), frames, T_gt


def problem(clip, k, dtype):
    """(kf, dist, edge_map, mag, T_gt) of pair (0, k) as device arrays of ``dtype``."""
    _, edges, mag, frames, T_gt = clip
    kf = KeyframeEdges(jnp.asarray(edges.uv, dtype), jnp.asarray(edges.rho, dtype),
                       jnp.asarray(edges.grad, dtype), jnp.asarray(edges.valid))
    f = frames[k]
    dist = tuple(jnp.asarray(d, dtype) for d in f.dist)
    return kf, dist, jax.tree.map(jnp.asarray, f.edge_map), jnp.asarray(mag, dtype), jnp.asarray(
        T_gt[k], dtype)


def flatten(p: Params) -> jnp.ndarray:
    return jnp.concatenate([jnp.ravel(x) for x in p])


def unflatten(v: jnp.ndarray, like: Params) -> Params:
    out, i = [], 0
    for x in like:
        out.append(v[i:i + x.size].reshape(x.shape))
        i += x.size
    return Params(*out)


def trained_like(config: Config, **changes) -> Params:
    """Non-default params: every weighting-model input matters (residual slope included)."""
    p = Params.default(config)._replace(
        weight_w=jnp.array([0.1, -0.2, 0.3, 0.05]), weight_b=jnp.asarray(0.1),
        log_huber=jnp.log(jnp.array([1.2, 0.9, 1.1])))
    return p._replace(**{k: jnp.asarray(v) for k, v in changes.items()})


def loss_and_grad(clip, k, params, config, adjoint):
    """Jitted v -> pose loss against ground truth, and its value_and_grad (float64)."""
    seq = clip[0]
    kf, dist, ng, mag, T_gt = problem(clip, k, jnp.float64)

    def loss(v):
        out = track_differentiable(kf, dist, ng, jnp.eye(4), seq.intrinsics,
                                   unflatten(v, params), config, mag=mag, adjoint=adjoint)
        return pose_loss(out.T_c_k, T_gt)

    return jax.jit(loss), jax.jit(jax.value_and_grad(loss))


def central_differences(loss, v, eps):
    return np.array([(loss(v + e) - loss(v - e)) / (2 * eps)
                     for e in np.eye(v.size) * eps])


def test_default_params_reproduce_the_plain_tracker(clip):
    """float32, the tracker's own dtype: hard consistency is the same computation (same
    pose to the bit); the soft test with the default temperature stays within 1 mm / 0.05 deg."""
    seq = clip[0]
    p0 = Params.default(CONFIG)
    for k in (1, 2):
        kf, dist, ng, mag, _ = problem(clip, k, jnp.float32)
        ref = jax.jit(track, static_argnames="config")(
            kf, dist, ng, jnp.eye(4, dtype=jnp.float32), seq.intrinsics, config=CONFIG)
        hard = _diff(kf, dist, ng, jnp.eye(4, dtype=jnp.float32), seq.intrinsics, p0, CONFIG,
                     mag=mag, consistency="hard")
        np.testing.assert_array_equal(hard.T_c_k, ref.T_c_k)
        assert int(hard.inliers) == int(ref.inliers) and float(hard.cost) == float(ref.cost)
        # soft against hard, each run until its steps stop helping (the default stop after 3
        # rejections in a row would compare where two different paths happened to stop)
        converged = CONFIG.replace(max_rejects=10)
        ref = jax.jit(track, static_argnames="config")(
            kf, dist, ng, jnp.eye(4, dtype=jnp.float32), seq.intrinsics, config=converged)
        soft = _diff(kf, dist, ng, jnp.eye(4, dtype=jnp.float32), seq.intrinsics, p0,
                     converged, mag=mag)
        t_err, r_err = relative_pose_error(soft.T_c_k, ref.T_c_k)
        assert float(t_err) < 1e-3 and float(r_err) < np.radians(0.05), (t_err, r_err)
        assert abs(int(soft.inliers) - int(ref.inliers)) <= 2


def test_unrolled_gradients_equal_finite_differences(clip):
    """Every parameter, a few LM tries per level (every level matters), float64."""
    config = CONFIG.replace(iterations=(3, 3, 3))
    with jax.enable_x64(True):
        params = trained_like(config)
        loss, vg = loss_and_grad(clip, 2, params, config, "unrolled")
        v = flatten(params)
        _, grad = vg(v)
        fd = central_differences(loss, v, 1e-6)
    grad = np.asarray(grad)
    assert NAMES[5] == "reobs_a" and grad[5] == 0.0 and fd[5] == 0.0  # selection-only
    for name, g, f in zip(NAMES, grad, fd, strict=True):
        if name != "reobs_a":
            assert abs(g - f) <= 1e-4 * abs(f) and f != 0.0, (name, g, f)


def test_checkpointed_unrolled_gradients_are_the_same(clip):
    config = CONFIG.replace(iterations=(3, 3, 3))
    seq = clip[0]
    with jax.enable_x64(True):
        params = trained_like(config)
        kf, dist, ng, mag, T_gt = problem(clip, 2, jnp.float64)

        def loss(p, checkpoint):
            out = track_differentiable(kf, dist, ng, jnp.eye(4), seq.intrinsics, p, config,
                                       mag=mag, checkpoint=checkpoint)
            return pose_loss(out.T_c_k, T_gt)

        g_plain = jax.jit(jax.grad(loss), static_argnums=1)(params, False)
        g_ckpt = jax.jit(jax.grad(loss), static_argnums=1)(params, True)
    for a, b in zip(g_plain, g_ckpt, strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-20)


@pytest.mark.parametrize("case", ["real", "no_valid_edges", "out_of_view"])
def test_gradients_are_finite_on_real_frames_and_empty_masks(clip, case):
    """Default params (Huber kinks, zero weights), both adjoints; empty masks give zero
    gradients, not NaN."""
    seq = clip[0]
    with jax.enable_x64(True):
        kf, dist, ng, mag, T_gt = problem(clip, 1, jnp.float64)
        T_init = jnp.eye(4)
        if case == "no_valid_edges":
            kf = kf._replace(valid=jnp.zeros_like(kf.valid))
        elif case == "out_of_view":
            T_init = T_init.at[0, 3].set(50.0)  # every edge warps far outside the image
        params = Params.default(CONFIG)
        for adjoint in ("unrolled", "implicit"):
            def loss(p, adjoint=adjoint):
                out = _diff(kf, dist, ng, T_init, seq.intrinsics, p, CONFIG, mag=mag,
                            adjoint=adjoint)
                return pose_loss(out.T_c_k, T_gt) + jnp.sum(out.covariance)

            grads = jax.grad(loss)(params)
            for leaf in grads:
                assert bool(jnp.all(jnp.isfinite(leaf))), (case, adjoint, grads)
            if case != "real":
                assert all(float(jnp.max(jnp.abs(x))) == 0.0 for x in grads), (case, grads)


def test_losses():
    with jax.enable_x64(True):
        T_gt = jaxlie.SE3.exp(jnp.array([0.1, -0.2, 0.05, 0.1, 0.2, -0.1]))
        delta = jaxlie.SE3.exp(jnp.array([0.03, 0.0, -0.04, 0.0, 0.0, 0.2]))  # 5 cm, 0.2 rad
        T_est = (T_gt @ delta).as_matrix()
        t_err, r_err = relative_pose_error(T_est, T_gt.as_matrix())
        np.testing.assert_allclose(t_err, np.linalg.norm(delta.translation()), rtol=1e-12)
        np.testing.assert_allclose(r_err, 0.2, rtol=1e-9)
        np.testing.assert_allclose(rpe_loss(T_est, T_gt.as_matrix(), rot_weight=0.5),
                                   t_err + 0.1, rtol=1e-12)
        np.testing.assert_allclose(pose_loss(T_est, T_gt.as_matrix(), rot_weight=2.0),
                                   float(t_err) ** 2 + 4.0 * 2.0 * (1.0 - np.cos(0.2)),
                                   rtol=1e-12)
        same = T_gt.as_matrix()
        for fn in (rpe_loss, pose_loss):  # at (numerically) zero error: no NaN from sqrt
            assert float(fn(same, same)) < 1e-12
            assert bool(jnp.all(jnp.isfinite(jax.grad(fn)(same, same))))
        assert float(jnp.max(jnp.abs(jax.grad(rpe_loss)(jnp.eye(4), jnp.eye(4))))) == 0.0


def test_reobservation_offset_gradient_through_the_selection_scores():
    with jax.enable_x64(True):
        mag = jnp.array([80.0, 100.0, 150.0, 400.0])
        gains = jnp.array([0.3, 1.2, 0.7, 0.1])
        params = Params.default(CONFIG)._replace(reobs_a=jnp.asarray(110.0))

        def total(a):
            return jnp.sum(selection_scores(mag, gains, params._replace(reobs_a=a)) ** 2)

        g = jax.grad(total)(params.reobs_a)
        fd = (total(110.0 + 1e-3) - total(110.0 - 1e-3)) / 2e-3
    assert float(g) != 0.0 and abs(float(g) - float(fd)) <= 1e-5 * abs(float(fd))


def test_params_default_and_argument_checks(clip):
    p = Params.default(CONFIG)
    np.testing.assert_allclose(jnp.exp(p.log_huber), CONFIG.huber_delta)
    assert p.eta == np.float32(CONFIG.eta) and float(p.reobs_a) == CONFIG.canny_high
    seq = clip[0]
    kf, dist, ng, mag, _ = problem(clip, 1, jnp.float32)
    with pytest.raises(ValueError, match="adjoint"):
        track_differentiable(kf, dist, ng, jnp.eye(4), seq.intrinsics, p, CONFIG,
                             adjoint="forward")
    with pytest.raises(ValueError, match="consistency"):
        track_differentiable(kf, dist, ng, jnp.eye(4), seq.intrinsics, p, CONFIG,
                             consistency="fuzzy")
    assert np.all(mag[np.asarray(kf.valid)] >= CONFIG.canny_high)  # culled edges' magnitudes
