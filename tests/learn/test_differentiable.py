"""Gradients of the pose w.r.t. the learnable Params on real frames (bundled fr1/xyz clip):
both adjoints against central finite differences in float64 (the implicit one at a
converged pose), finiteness with empty masks, the defaults reproducing ``solve.track``, and
the relative-pose losses."""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
import pytest

from edgevo_jax import Config
from edgevo_jax.cli import BUNDLED_CLIP
from edgevo_jax.datasets import groundtruth_pose_at, load_sequence
from edgevo_jax.frontend.align import track
from edgevo_jax.frontend.chunk import predict_matrix
from edgevo_jax.frontend.selection import KeyframeEdges, keyframe_edges
from edgevo_jax.geometry import inverse_np
from edgevo_jax.image.interp import stack_edge_maps
from edgevo_jax.image.preprocess import preprocess
from edgevo_jax.io import matrices_to_poses7, poses7_to_matrices
from edgevo_jax.learn import (
    ate_loss,
    edge_magnitudes,
    level_system,
    newton_decrement,
    pose_loss,
    relative_pose_error,
    rigid_alignment,
    rpe_loss,
    selection_scores,
    track_differentiable,
    track_window,
    window_rpe_loss,
)
from edgevo_jax.learn.params import Params, flatten, unflatten
from edgevo_jax.metrics import ate

CONFIG = Config(num_edges=128)
#: the full-resolution level alone (tests whose property does not depend on the levels:
#: their gradient programs build in a third of the time)
ONE_LEVEL = CONFIG.replace(iterations=(10,), huber_delta=(1.0,), max_residual=(5.0,))

def _flat_names(params: Params) -> list[str]:
    """A name per entry of ``flatten(params)``: the field, with its index when not a scalar."""
    names = []
    for field, x in zip(Params._fields, params, strict=True):
        shape = np.shape(x)
        names += [field] if shape == () else [
            field + "".join(str(i) for i in idx) for idx in np.ndindex(shape)]
    return names


NAMES = _flat_names(Params.default(CONFIG))
assert NAMES[:6] == ["log_huber0", "log_huber1", "log_huber2", "eta", "log_temperature",
                     "reobs_a"]
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
                       jnp.asarray(edges.grad, dtype), jnp.asarray(edges.valid),
                       disc=jnp.asarray(edges.disc, dtype))
    f = frames[k]
    dist = tuple(jnp.asarray(d, dtype) for d in f.dist)
    return kf, dist, jax.tree.map(jnp.asarray, f.edge_map), jnp.asarray(mag, dtype), jnp.asarray(
        T_gt[k], dtype)


def trained_like(config: Config, **changes) -> Params:
    """Non-default params: every weighting-model input matters (residual slope included)."""
    p = Params.default(config)._replace(
        weight_w2=jnp.array([0.1, -0.2, 0.3, 0.05, -0.1, 0.2, 0.1, -0.3]),
        weight_b2=jnp.asarray(0.1),
        log_huber=jnp.log(jnp.array([1.2, 0.9, 1.1])[:config.num_levels]))
    return p._replace(**{k: jnp.asarray(v) for k, v in changes.items()})


def loss_and_grad(clip, k, params, config, adjoint, checkpoint=False):
    """Jitted v -> pose loss against ground truth, and its value_and_grad (float64)."""
    seq = clip[0]
    kf, dist, ng, mag, T_gt = problem(clip, k, jnp.float64)

    def loss(v):
        out = track_differentiable(kf, dist, ng, jnp.eye(4), seq.intrinsics,
                                   unflatten(v, params), config, mag=mag, adjoint=adjoint,
                                   checkpoint=checkpoint)
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
    """Every parameter, a few LM tries per level (both levels matter: a coarse and the
    full-resolution one; a third level runs the same code and took a third of this test's
    time to compile), float64; the checkpointed scan (each try recomputed in the backward
    pass) gives the same gradient."""
    config = CONFIG.replace(iterations=(3, 3), huber_delta=(1.0, 1.0), max_residual=(5.0, 5.0))
    names = _flat_names(Params.default(config))
    with jax.enable_x64(True):
        params = trained_like(config)
        loss, vg = loss_and_grad(clip, 2, params, config, "unrolled")
        v = flatten(params)
        _, grad = vg(v)
        fd = central_differences(loss, v, 1e-6)
        _, grad_ckpt = loss_and_grad(clip, 2, params, config, "unrolled", checkpoint=True)[1](v)
    grad = np.asarray(grad)
    np.testing.assert_allclose(grad_ckpt, grad, rtol=1e-10, atol=1e-20)
    k = names.index("reobs_a")
    assert grad[k] == 0.0 and fd[k] == 0.0  # selection-only
    scale = np.max(np.abs(fd))  # some first-layer weights move the loss by ~1e-6 of it
    for name, g, f in zip(names, grad, fd, strict=True):
        if name != "reobs_a":
            assert abs(g - f) <= 1e-4 * abs(f) + 1e-7 * scale and f != 0.0, (name, g, f)


#: level 0 converged: 20 LM tries per round, 3 refinement rounds, no early stop
CONVERGED = CONFIG.replace(iterations=(20, 5, 5), step_tol=0.0, max_rejects=1000)
#: parameters that do not enter level 0: the coarse levels' Huber radii, the first layer's
#: weights of the level feature (0 at level 0) and reobs_a (selection only)
NOT_AT_LEVEL0 = ("log_huber1", "log_huber2", "reobs_a",
                 *(f"weight_w1{h}4" for h in range(Params.default(CONFIG).weight_w1.shape[0])))


@pytest.mark.slow
def test_implicit_gradients_are_exact_at_a_converged_pose(clip):
    """Bicubic fields, refinement rounds, float64, pair (0, 2): the pose ends at a stationary
    point of its own hard decisions (Newton decrement ~1e-25; the plain bilinear LM stops at
    ~0.2); there the implicit gradient equals central differences to 1e-4 relative for every
    parameter that enters level 0, with the decisions (gate, visibility, nearest edges) the
    same at every FD pose; the others have zero gradient and FD (to rounding). (The unrolled
    adjoint is checked against differences in the test before; through three refinement
    rounds of bicubic levels its program took 80 of this test's 146 s to build.)"""
    seq, config = clip[0], CONVERGED
    with jax.enable_x64(True):
        params = trained_like(config)
        kf, dist, ng, mag, T_gt = problem(clip, 2, jnp.float64)

        def pose(v):
            return track_differentiable(kf, dist, ng, jnp.eye(4), seq.intrinsics,
                                        unflatten(v, params), config, mag=mag, adjoint="implicit",
                                        interpolation="bicubic", refine=3).T_c_k

        @jax.jit
        def forward(v):
            T = pose(v)
            system, mask, dots = level_system(kf, dist, ng, T, seq.intrinsics,
                                              unflatten(v, params), config, mag=mag,
                                              interpolation="bicubic")
            return pose_loss(T, T_gt), mask, dots, newton_decrement(system), system.cost

        v = flatten(params)
        _, mask, dots, decrement, cost = forward(v)
        assert float(decrement) < 1e-20 * float(cost), (decrement, cost)
        g_implicit = np.asarray(jax.jit(jax.grad(lambda v: pose_loss(pose(v), T_gt)))(v))
        eps = 1e-4
        scale = np.max(np.abs(g_implicit))
        for i, name in enumerate(NAMES):
            e = np.zeros(v.size)
            e[i] = eps
            (lp, mp, dp, decp, _), (lm, mm, dm, decm, _) = forward(v + e), forward(v - e)
            for m, d, dec in ((mp, dp, decp), (mm, dm, decm)):  # the same smooth piece
                assert np.array_equal(m, mask) and np.array_equal(d, dots), name
                assert float(dec) < 1e-20 * float(cost), (name, dec)
            fd = (float(lp) - float(lm)) / (2 * eps)
            g = g_implicit[i]
            if name in NOT_AT_LEVEL0:
                assert g == 0.0 and abs(fd) < 1e-12, (name, g, fd)
            else:
                assert abs(g - fd) <= 1e-4 * abs(fd) + 1e-7 * scale and fd != 0.0, (name, g, fd)


@pytest.mark.parametrize("case", ["real", "no_valid_edges", "out_of_view"])
def test_gradients_are_finite_on_real_frames_and_empty_masks(clip, case):
    """Default params (Huber kinks, zero weights), both adjoints; empty masks give zero
    gradients, not NaN. One level (``ONE_LEVEL``): every level runs the same code, and the
    gradient programs of three took 80 of this test's 90 s to build."""
    seq = clip[0]
    with jax.enable_x64(True):
        kf, dist, ng, mag, T_gt = problem(clip, 1, jnp.float64)
        T_init = jnp.eye(4)
        if case == "no_valid_edges":
            kf = kf._replace(valid=jnp.zeros_like(kf.valid))
        elif case == "out_of_view":
            T_init = T_init.at[0, 3].set(50.0)  # every edge warps far outside the image
        params = Params.default(ONE_LEVEL)
        for adjoint in ("unrolled", "implicit"):
            def loss(p, adjoint=adjoint):
                out = _diff(kf, dist, ng, T_init, seq.intrinsics, p, ONE_LEVEL, mag=mag,
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


def random_trajectory(rng: np.random.Generator, n: int, noise: float = 0.0) -> np.ndarray:
    """(n, 4, 4) T_world_cam along a random smooth path (float64), optionally perturbed."""
    twists = np.cumsum(rng.normal(scale=0.05, size=(n, 6)), axis=0)
    twists += rng.normal(scale=noise, size=(n, 6))
    return np.stack([np.asarray(jaxlie.SE3.exp(jnp.asarray(x)).as_matrix()) for x in twists])


def test_ate_loss_is_tum_ate_and_its_gradient_is_exact():
    """Equal to metrics.ate (TUM's evaluate_ate) on the same poses, the reflection case
    included; zero with a zero gradient for a rigidly moved copy of the truth; gradient =
    central differences (float64)."""
    rng = np.random.default_rng(5)
    with jax.enable_x64(True):
        gt = random_trajectory(rng, 12)
        est = random_trajectory(np.random.default_rng(5), 12, noise=0.02)
        ts = np.arange(12) * 0.1
        ref = ate((ts, matrices_to_poses7(gt)), (ts, matrices_to_poses7(est)))["rmse"]
        np.testing.assert_allclose(ate_loss(jnp.asarray(est), jnp.asarray(gt)), ref, rtol=1e-10)
        # a mirror image: the best orthogonal map is a reflection, TUM's fix keeps a rotation
        mirrored = est.copy()
        mirrored[:, 0, 3] *= -1.0
        R, _ = rigid_alignment(jnp.asarray(mirrored[:, :3, 3]), jnp.asarray(gt[:, :3, 3]))
        assert abs(float(jnp.linalg.det(R)) - 1.0) < 1e-12
        ref_m = ate((ts, matrices_to_poses7(gt)), (ts, matrices_to_poses7(mirrored)))["rmse"]
        np.testing.assert_allclose(ate_loss(jnp.asarray(mirrored), jnp.asarray(gt)), ref_m,
                                   rtol=1e-10)
        # masked poses are left out
        valid = np.arange(12) % 3 != 0
        ref_v = ate((ts[valid], matrices_to_poses7(gt[valid])),
                    (ts[valid], matrices_to_poses7(est[valid])))["rmse"]
        np.testing.assert_allclose(ate_loss(jnp.asarray(est), jnp.asarray(gt),
                                            valid=jnp.asarray(valid)), ref_v, rtol=1e-10)
        # rigidly moved truth
        G = np.asarray(jaxlie.SE3.exp(jnp.array([0.3, -1.0, 2.0, 0.5, -0.4, 2.5])).as_matrix())
        moved = jnp.asarray(G @ gt)
        assert float(ate_loss(moved, jnp.asarray(gt))) < 1e-12
        # (an RMS, like a norm, has no gradient at 0: rounding picks one of norm <= 1)
        g0 = jax.grad(ate_loss)(moved, jnp.asarray(gt))
        assert bool(jnp.all(jnp.isfinite(g0))) and float(jnp.linalg.norm(g0)) <= 1.0 + 1e-9
        none = jnp.zeros(12, bool)  # no pose: 0, and a zero gradient (not NaN)
        assert float(ate_loss(moved, jnp.asarray(gt), valid=none)) == 0.0
        g_none = jax.grad(ate_loss)(moved, jnp.asarray(gt), valid=none)
        assert float(jnp.max(jnp.abs(g_none))) == 0.0
        # gradient w.r.t. every estimated position, against central differences
        grad = np.asarray(jax.grad(ate_loss)(jnp.asarray(est), jnp.asarray(gt)))[:, :3, 3]
        steps = np.zeros((36, 12, 4, 4))
        steps[np.arange(36), np.repeat(np.arange(12), 3), np.tile(np.arange(3), 12), 3] = 1e-6
        losses = jax.jit(jax.vmap(ate_loss, in_axes=(0, None)))
        fd = (losses(est + steps, gt) - losses(est - steps, gt)).reshape(12, 3) / 2e-6
        np.testing.assert_allclose(grad, fd, rtol=1e-6, atol=1e-9)
        assert np.all(grad != 0.0)


def test_window_rpe_loss():
    """The mean rpe_loss of the relative motions (i, i + d); blind to the frame the poses
    are given in; zero for the truth; gradient = central differences (float64)."""
    rng = np.random.default_rng(9)
    with jax.enable_x64(True):
        gt = jnp.asarray(random_trajectory(rng, 6))
        est = jnp.asarray(random_trajectory(np.random.default_rng(9), 6, noise=0.01))
        inv = np.linalg.inv
        pair_loss = jax.jit(partial(rpe_loss, rot_weight=0.3))
        expected = np.mean([float(pair_loss(inv(est[i]) @ est[i + d], inv(gt[i]) @ gt[i + d]))
                            for d in (1, 2) for i in range(6 - d)])
        value = window_rpe_loss(est, gt, rot_weight=0.3, deltas=(1, 2))
        np.testing.assert_allclose(value, expected, rtol=1e-12)
        G = jnp.asarray(jaxlie.SE3.exp(jnp.array([1.0, 0.2, -0.3, 0.4, 0.1, -2.0])).as_matrix())
        np.testing.assert_allclose(window_rpe_loss(G @ est, gt, rot_weight=0.3, deltas=(1, 2)),
                                   expected, rtol=1e-10)
        assert float(window_rpe_loss(G @ gt, gt)) < 1e-7  # chordal angle of rounding: ~1e-8
        valid = jnp.array([True, True, False, True, True, True])
        pair_loss = jax.jit(rpe_loss)
        expected_v = np.mean([float(pair_loss(inv(est[i]) @ est[i + 1], inv(gt[i]) @ gt[i + 1]))
                              for i in (0, 3, 4)])
        np.testing.assert_allclose(window_rpe_loss(est, gt, valid=valid), expected_v,
                                   rtol=1e-12)

        def of_twist(x):
            return window_rpe_loss(est.at[3].set(jaxlie.SE3.exp(x).as_matrix() @ est[3]), gt,
                                   rot_weight=0.3, deltas=(1, 2))

        x0 = jnp.zeros(6)
        grad = jax.jit(jax.grad(of_twist))(x0)
        losses = jax.jit(jax.vmap(of_twist))
        fd = (losses(jnp.eye(6) * 1e-6) - losses(-jnp.eye(6) * 1e-6)) / 2e-6
        np.testing.assert_allclose(grad, fd, rtol=1e-6, atol=1e-9)
        with pytest.raises(ValueError, match="no pair"):
            window_rpe_loss(est[:2], gt[:2], deltas=(2,))


def test_track_window_is_the_frame_by_frame_loop(clip):
    """Frames 1, 2, 5 against keyframe 0, each from the constant-velocity prediction of the
    two before it: the same poses as calling track_differentiable frame by frame."""
    seq, edges, mag, frames, _ = clip
    kf = jax.tree.map(jnp.asarray, edges)._replace(mag=jnp.asarray(mag))
    ks = (1, 2, 5)
    dist = tuple(jnp.asarray(np.stack([frames[k].dist[lv] for k in ks])) for lv in range(3))
    em = jax.tree.map(jnp.asarray, stack_edge_maps([frames[k].edge_map for k in ks]))
    params = trained_like(CONFIG)
    eye = jnp.eye(4, dtype=jnp.float32)
    out = jax.jit(track_window, static_argnames=("config", "consistency"))(
        kf, dist, em, eye, eye, seq.intrinsics, params, CONFIG, consistency="hard")
    a, b = eye, eye
    for j in range(len(ks)):
        one = _diff(kf, tuple(d[j] for d in dist), jax.tree.map(lambda x, j=j: x[j], em),
                    predict_matrix(a, b), seq.intrinsics, params, CONFIG, consistency="hard")
        np.testing.assert_allclose(out.T_c_k[j], one.T_c_k, atol=1e-6)
        a, b = one.T_c_k, a


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
