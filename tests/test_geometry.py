"""Properties of ``geometry.Pose`` and its numpy twin, as jaxlie tests its groups: random,
near-identity, near-pi and batched transforms; exp / log round trips; the group axioms;
the action on points against the 4x4 matrix; agreement with jaxlie.SE3 (the reference
implementation); the derivative of ``retract`` at 0 against jax.jacfwd and central finite
differences; the host twin against the device type. Derivative and agreement tests run in
float64 (``jax.enable_x64``), the float32 ones check what the tracker runs on."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from edgevo_jax.geometry import (
    Pose,
    compose_np,
    exp_np,
    inverse_np,
    log_np,
    orthonormalise_np,
    predict,
    predict_np,
    rotation_angle_np,
    scale_motion_np,
)

KINDS = ("random", "near_identity", "near_pi")
seeds = st.integers(0, 2**31 - 1)


def twist(rng: np.random.Generator, kind: str) -> np.ndarray:
    """A twist [v, w] (6,) with |w| < pi: ``random`` (|w| up to 3), ``near_identity``
    (|w| ~ 1e-6, |v| ~ 1e-6) or ``near_pi`` (|w| = pi - 1e-4)."""
    v = rng.normal(size=3)
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    if kind == "random":
        return np.concatenate([v, axis * rng.uniform(0.0, 3.0)])
    if kind == "near_identity":
        return np.concatenate([v * 1e-6, axis * 1e-6 * rng.uniform(0.5, 2.0)])
    return np.concatenate([v, axis * (np.pi - 1e-4)])


def pose(rng: np.random.Generator, kind: str = "random") -> Pose:
    return Pose.exp(jnp.asarray(twist(rng, kind)))


def assert_pose_close(a: Pose, b: Pose, atol: float) -> None:
    np.testing.assert_allclose(np.asarray(a.as_matrix()), np.asarray(b.as_matrix()), atol=atol)


# -- group structure (float64) ------------------------------------------------------------


@pytest.mark.parametrize("kind", KINDS)
@given(seed=seeds)
@settings(max_examples=30, deadline=None)
def test_exp_log_round_trip(kind, seed):
    with jax.enable_x64(True):
        rng = np.random.default_rng(seed)
        xi = twist(rng, kind)
        T = Pose.exp(jnp.asarray(xi))
        np.testing.assert_allclose(np.asarray(T.log()), xi, rtol=1e-9, atol=1e-12)
        assert_pose_close(Pose.exp(T.log()), T, atol=1e-12)


@given(seed=seeds)
@settings(max_examples=30, deadline=None)
def test_log_at_pi_gives_the_rotation_back(seed):
    """At exactly pi the axis' sign is arbitrary: exp(log T) = T is what holds."""
    with jax.enable_x64(True):
        rng = np.random.default_rng(seed)
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        R = 2.0 * np.outer(axis, axis) - np.eye(3)  # rotation by pi about axis
        T = Pose(jnp.asarray(R), jnp.asarray(rng.normal(size=3)))
        w = np.asarray(T.log())[3:]
        np.testing.assert_allclose(np.linalg.norm(w), np.pi, atol=1e-12)
        np.testing.assert_allclose(np.abs(w @ axis), np.pi, atol=1e-12)
        assert_pose_close(Pose.exp(T.log()), T, atol=1e-12)


@given(seed=seeds)
@settings(max_examples=30, deadline=None)
def test_compose_is_associative_with_identity(seed):
    with jax.enable_x64(True):
        rng = np.random.default_rng(seed)
        a, b, c = (pose(rng, kind) for kind in KINDS)
        assert_pose_close((a @ b) @ c, a @ (b @ c), atol=1e-12)
        eye = Pose.identity(jnp.float64)
        assert_pose_close(a @ eye, a, atol=0.0)
        assert_pose_close(eye @ a, a, atol=0.0)
        assert_pose_close(a.compose(b), a @ b, atol=0.0)


@pytest.mark.parametrize("kind", KINDS)
@given(seed=seeds)
@settings(max_examples=20, deadline=None)
def test_inverse_undoes_the_transform(kind, seed):
    with jax.enable_x64(True):
        T = pose(np.random.default_rng(seed), kind)
        eye = Pose.identity(jnp.float64)
        assert_pose_close(T @ T.inverse(), eye, atol=1e-12)
        assert_pose_close(T.inverse() @ T, eye, atol=1e-12)
        assert_pose_close(T.inverse().inverse(), T, atol=1e-15)


@given(seed=seeds)
@settings(max_examples=30, deadline=None)
def test_apply_is_the_homogeneous_matrix_product(seed):
    with jax.enable_x64(True):
        rng = np.random.default_rng(seed)
        T, b = pose(rng), pose(rng)
        pts = rng.normal(size=(3, 7))
        homog = np.asarray(T.as_matrix()) @ np.vstack([pts, np.ones((1, 7))])
        np.testing.assert_allclose(np.asarray(T.apply(jnp.asarray(pts))), homog[:3], atol=1e-12)
        # the action of a composition is the composition of the actions
        np.testing.assert_allclose(np.asarray((T @ b).apply(jnp.asarray(pts))),
                                   np.asarray(T.apply(b.apply(jnp.asarray(pts)))), atol=1e-12)


def test_matrix_round_trip_and_gram_schmidt():
    with jax.enable_x64(True):
        rng = np.random.default_rng(3)
        T = pose(rng)
        M = T.as_matrix()
        assert M.shape == (4, 4)
        np.testing.assert_array_equal(np.asarray(M[3]), [0.0, 0.0, 0.0, 1.0])
        assert_pose_close(Pose.from_matrix(M, orthonormalise=None), T, atol=0.0)
        assert_pose_close(Pose.from_matrix(M), T, atol=1e-14)
        # a drifted rotation block is projected back onto SO(3)
        drifted = M.at[:3, :3].add(jnp.asarray(rng.normal(size=(3, 3)) * 1e-4))
        R = np.asarray(Pose.from_matrix(drifted).R)
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-14)
        np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-14)
        np.testing.assert_allclose(R, np.asarray(T.R), atol=1e-3)


def test_retract_is_exp_times_pose():
    with jax.enable_x64(True):
        rng = np.random.default_rng(4)
        T = pose(rng)
        for kind in KINDS:
            xi = jnp.asarray(twist(rng, kind))
            assert_pose_close(T.retract(xi), Pose.exp(xi) @ T, atol=1e-12)


# -- agreement with jaxlie (float64) --------------------------------------------------------


@pytest.mark.parametrize("kind", KINDS)
@given(seed=seeds)
@settings(max_examples=20, deadline=None)
def test_agrees_with_jaxlie(kind, seed):
    with jax.enable_x64(True):
        rng = np.random.default_rng(seed)
        xi_a, xi_b = twist(rng, kind), twist(rng, "random")
        a, b = Pose.exp(jnp.asarray(xi_a)), Pose.exp(jnp.asarray(xi_b))
        # below |w|^2 = 1e-10 jaxlie's exp takes V = R (an error ~ |v| |w| / 2, 1e-12 here)
        np.testing.assert_allclose(a.as_matrix(), jaxlie.SE3.exp(jnp.asarray(xi_a)).as_matrix(),
                                   rtol=0.0, atol=1e-10)
        # the other operations on the same elements
        ja, jb = jaxlie.SE3.from_matrix(a.as_matrix()), jaxlie.SE3.from_matrix(b.as_matrix())
        np.testing.assert_allclose(a.log(), ja.log(), rtol=1e-8, atol=1e-12)
        np.testing.assert_allclose((a @ b).as_matrix(), (ja @ jb).as_matrix(), rtol=0.0,
                                   atol=1e-12)
        np.testing.assert_allclose(a.inverse().as_matrix(), ja.inverse().as_matrix(),
                                   rtol=0.0, atol=1e-12)
        pts = rng.normal(size=(3, 5))
        np.testing.assert_allclose(a.apply(jnp.asarray(pts)),
                                   np.asarray(ja.apply(jnp.asarray(pts.T))).T, rtol=0.0,
                                   atol=1e-12)


# -- derivative of retract at 0 (float64) ---------------------------------------------------


def _hat(w: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def _retract_jacobian(T: Pose) -> np.ndarray:
    """d (R, t) / d xi of T.retract(xi) at xi = 0, analytic, as (12, 6) over R row by row
    then t: dR/dw_k = [e_k]x R, dt/dv = I, dt/dw_k = e_k x t = -[t]x e_k."""
    R, t = np.asarray(T.R), np.asarray(T.t)
    J = np.zeros((12, 6))
    for k in range(3):
        e = np.eye(3)[k]
        J[:9, 3 + k] = (_hat(e) @ R).reshape(-1)
        J[9:, 3 + k] = np.cross(e, t)
    J[9:, :3] = np.eye(3)
    return J


def _flat_retract(T: Pose):
    return lambda xi: jnp.concatenate([T.retract(xi).R.reshape(-1), T.retract(xi).t])


@pytest.mark.parametrize("kind", KINDS)
def test_retract_derivative_at_zero(kind):
    with jax.enable_x64(True):
        rng = np.random.default_rng(11)
        for _ in range(5):
            T = pose(rng, kind)
            f = _flat_retract(T)
            analytic = _retract_jacobian(T)
            auto = np.asarray(jax.jacfwd(f)(jnp.zeros(6)))
            np.testing.assert_allclose(auto, analytic, atol=1e-12)
            eps = 1e-6
            fd = np.stack([(np.asarray(f(jnp.asarray(eps * e)))
                            - np.asarray(f(jnp.asarray(-eps * e)))) / (2 * eps)
                           for e in np.eye(6)], axis=1)
            np.testing.assert_allclose(fd, analytic, atol=1e-8)


def test_point_derivative_of_retract_at_zero():
    """d (exp(xi) T p) / d xi at 0 = [I | -[T p]x] (3, 6): the residual Jacobian's factor."""
    with jax.enable_x64(True):
        rng = np.random.default_rng(12)
        T, p = pose(rng), rng.normal(size=(3, 1))
        q = np.asarray(T.apply(jnp.asarray(p)))[:, 0]
        analytic = np.concatenate([np.eye(3), -_hat(q)], axis=1)
        auto = jax.jacfwd(lambda xi: T.retract(xi).apply(jnp.asarray(p))[:, 0])(jnp.zeros(6))
        np.testing.assert_allclose(auto, analytic, atol=1e-12)


def test_log_has_finite_gradients_at_the_identity():
    with jax.enable_x64(True):
        g = jax.jacfwd(lambda xi: Pose.exp(xi).log())(jnp.zeros(6))
        np.testing.assert_allclose(g, np.eye(6), atol=1e-12)
        g = jax.grad(lambda xi: jnp.sum(Pose.exp(xi).log() ** 2))(jnp.zeros(6))
        assert np.all(np.isfinite(g))


# -- batched (vmap, and the broadcasting methods) ------------------------------------------


def test_batched_matches_one_by_one():
    with jax.enable_x64(True):
        rng = np.random.default_rng(5)
        xis = jnp.asarray(np.stack([twist(rng, k) for k in KINDS * 3]))
        batch = jax.vmap(Pose.exp)(xis)
        assert batch.R.shape == (9, 3, 3) and batch.t.shape == (9, 3)
        ones = [Pose.exp(x) for x in xis]
        np.testing.assert_allclose(batch.as_matrix(), np.stack([p.as_matrix() for p in ones]),
                                   atol=1e-15)
        np.testing.assert_allclose(jax.vmap(Pose.log)(batch), np.stack([p.log() for p in ones]),
                                   atol=1e-15)
        other = jax.vmap(Pose.exp)(xis[::-1])
        both = batch @ other  # broadcast over the leading axis
        np.testing.assert_allclose(both.as_matrix(), jax.vmap(Pose.compose)(batch, other)
                                   .as_matrix(), atol=1e-15)
        np.testing.assert_allclose(batch.inverse().as_matrix(),
                                   jax.vmap(Pose.inverse)(batch).as_matrix(), atol=1e-15)
        back = Pose.from_matrix(batch.as_matrix(), orthonormalise=None)
        np.testing.assert_array_equal(back.R, batch.R)
        ortho = jax.vmap(Pose.from_matrix)(batch.as_matrix())
        np.testing.assert_allclose(ortho.R, batch.R, atol=1e-14)
        pts = jnp.asarray(rng.normal(size=(9, 3, 4)))
        np.testing.assert_allclose(jax.vmap(Pose.apply)(batch, pts),
                                   np.stack([p.apply(q) for p, q in zip(ones, pts, strict=True)]),
                                   atol=1e-15)
        steps = jnp.asarray(rng.normal(size=(9, 6)) * 0.1)
        np.testing.assert_allclose(jax.vmap(Pose.retract)(batch, steps).as_matrix(),
                                   np.stack([p.retract(s).as_matrix()
                                             for p, s in zip(ones, steps, strict=True)]),
                                   atol=1e-15)


# -- float32 (what the tracker runs on) -----------------------------------------------------


@pytest.mark.parametrize("kind", KINDS)
@given(seed=seeds)
@settings(max_examples=30, deadline=None)
def test_float32_round_trip_is_finite_and_close(kind, seed):
    rng = np.random.default_rng(seed)
    xi = twist(rng, kind).astype(np.float32)
    T = Pose.exp(jnp.asarray(xi))
    assert T.R.dtype == jnp.float32
    back = np.asarray(T.log())
    assert back.dtype == np.float32 and np.all(np.isfinite(back))
    assert_pose_close(Pose.exp(jnp.asarray(back)), T, atol=2e-6)
    # near pi the axis is found from the symmetric part, near 0 from the skew part
    np.testing.assert_allclose(back, xi, rtol=2e-5, atol=2e-6 if kind == "near_pi" else 3e-7)


@pytest.mark.parametrize("theta", [1e-7, 1e-4, 0.0999, 0.1001, 0.4999, 0.5001, 1.5, 3.0])
def test_float32_exp_and_log_match_float64_around_their_series_switches(theta):
    rng = np.random.default_rng(6)
    axis = rng.normal(size=3)
    xi = np.concatenate([rng.normal(size=3), axis / np.linalg.norm(axis) * theta])
    T32 = Pose.exp(jnp.asarray(xi, jnp.float32))
    with jax.enable_x64(True):
        T64 = Pose.exp(jnp.asarray(xi))
        M64 = np.asarray(T64.as_matrix())
        log64 = np.asarray(T64.log())
    np.testing.assert_allclose(np.asarray(T32.as_matrix()), M64, atol=1e-6)
    log32 = np.asarray(Pose.from_matrix(jnp.asarray(M64, jnp.float32)).log())
    np.testing.assert_allclose(log32, log64, rtol=1e-5, atol=1e-6)


# -- the numpy twin --------------------------------------------------------------------------


@pytest.mark.parametrize("kind", KINDS)
@given(seed=seeds)
@settings(max_examples=20, deadline=None)
def test_numpy_twin_agrees_with_the_device_type(kind, seed):
    with jax.enable_x64(True):
        rng = np.random.default_rng(seed)
        xi_a, xi_b = twist(rng, kind), twist(rng, "random")
        a, b = Pose.exp(jnp.asarray(xi_a)), Pose.exp(jnp.asarray(xi_b))
        A, B = exp_np(xi_a), exp_np(xi_b)
        np.testing.assert_allclose(A, np.asarray(a.as_matrix()), atol=1e-12)
        np.testing.assert_allclose(log_np(A), np.asarray(a.log()), rtol=1e-8, atol=1e-10)
        np.testing.assert_allclose(inverse_np(A), np.asarray(a.inverse().as_matrix()),
                                   atol=1e-12)
        np.testing.assert_allclose(compose_np(A, B), np.asarray((a @ b).as_matrix()),
                                   atol=1e-12)
        np.testing.assert_allclose(predict_np(A, B), np.asarray(predict(a, b).as_matrix()),
                                   atol=1e-11)
        np.testing.assert_allclose(rotation_angle_np(A), np.linalg.norm(xi_a[3:]), atol=1e-9)


def test_numpy_twin_is_batched():
    rng = np.random.default_rng(8)
    xis = np.stack([twist(rng, k) for k in KINDS * 2])
    Ts = exp_np(xis)
    assert Ts.shape == (6, 4, 4)
    np.testing.assert_allclose(Ts, np.stack([exp_np(x) for x in xis]), atol=0.0)
    np.testing.assert_allclose(log_np(Ts), xis, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(inverse_np(Ts), np.stack([inverse_np(T) for T in Ts]),
                               atol=1e-15)
    np.testing.assert_allclose(inverse_np(Ts) @ Ts, np.broadcast_to(np.eye(4), Ts.shape),
                               atol=1e-12)
    np.testing.assert_allclose(rotation_angle_np(Ts), np.linalg.norm(xis[:, 3:], axis=1),
                               atol=1e-9)
    assert isinstance(rotation_angle_np(Ts[0]), float)


def test_predict_is_constant_velocity_in_world_and_relative_poses():
    """T_w_i = T_w_(i-1) T_w_(i-2)^-1 T_w_(i-1), and the same formula on T_(i-1)_kf,
    T_(i-2)_kf gives T_i_kf = T_i_w T_w_kf; the motion from i-1 to i is the one before."""
    rng = np.random.default_rng(9)
    kf, prev, last = (exp_np(twist(rng, "random")) for _ in range(3))
    pred = predict_np(last, prev)
    np.testing.assert_allclose(inverse_np(last) @ pred, inverse_np(prev) @ last, atol=1e-12)
    rel = predict_np(inverse_np(last) @ kf, inverse_np(prev) @ kf)
    np.testing.assert_allclose(rel, inverse_np(pred) @ kf, atol=1e-12)
    np.testing.assert_allclose(predict_np(last, last), last, atol=1e-12)


def test_scale_motion_halves_the_screw_motion():
    rng = np.random.default_rng(10)
    for kind in KINDS:
        xi = twist(rng, kind)
        T = exp_np(xi)
        half = scale_motion_np(T, 0.5)
        np.testing.assert_allclose(half @ half, T, atol=1e-12)
        np.testing.assert_allclose(log_np(half), 0.5 * xi, rtol=1e-8, atol=1e-12)
        np.testing.assert_allclose(scale_motion_np(T, 0.0), np.eye(4), atol=1e-15)


def test_orthonormalise_finds_the_nearest_rotation():
    rng = np.random.default_rng(13)
    T = exp_np(twist(rng, "random"))
    drifted = T.copy()
    drifted[:3, :3] += rng.normal(size=(3, 3)) * 1e-6
    out = orthonormalise_np(drifted)
    R = out[:3, :3]
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-14)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-14)
    # the polar factor: the SVD's U V^T
    u, _, vt = np.linalg.svd(drifted[:3, :3])
    np.testing.assert_allclose(R, u @ vt, atol=1e-13)
    np.testing.assert_array_equal(out[:3, 3], drifted[:3, 3])


# -- the unit-quaternion paths: jaxlie's arithmetic, bit for bit in float32 ------------------


@pytest.mark.parametrize("kind", KINDS)
def test_quaternion_paths_are_jaxlies_arithmetic_bit_for_bit(kind):
    """The selection's warp, the window's update and its prior's offsets depend on these
    bits (the tracker's trajectories do): they must stay jaxlie's, op for op. Compared
    under jit, as the tracker runs them (jaxlie jits its methods; op-by-op dispatch rounds
    some of them differently)."""
    rng = np.random.default_rng(14)
    xis = jnp.asarray(np.stack([twist(rng, kind) for _ in range(8)]), jnp.float32)
    base = jnp.asarray(np.stack([twist(rng, "random") for _ in range(8)]), jnp.float32)
    ours = jax.jit(lambda x: Pose.exp(x, method="quaternion"))(xis)
    np.testing.assert_array_equal(ours.as_matrix(), jaxlie.SE3.exp(xis).as_matrix())
    # float32 matrices a little off SO(3), as products of float32 poses are
    M = jaxlie.SE3.exp(base).as_matrix() @ jaxlie.SE3.exp(xis).as_matrix()
    M0 = jaxlie.SE3.exp(base).as_matrix()
    ref = jaxlie.SE3.from_matrix(M)
    projected = jax.jit(lambda m: Pose.from_matrix(m, orthonormalise="quaternion"))(M)
    np.testing.assert_array_equal(projected.R, ref.rotation().as_matrix())
    np.testing.assert_array_equal(projected.t, ref.translation())
    T, T0 = Pose.from_matrix(M, orthonormalise=None), Pose.from_matrix(M0, orthonormalise=None)
    np.testing.assert_array_equal(jax.jit(Pose.log_relative)(T, T0),
                                  (ref @ jaxlie.SE3.from_matrix(M0).inverse()).log())
    assert projected.R.dtype == jnp.float32


@pytest.mark.parametrize("kind", KINDS)
def test_quaternion_paths_agree_with_the_rotation_matrix_ones(kind):
    with jax.enable_x64(True):
        rng = np.random.default_rng(15)
        for _ in range(5):
            xi, xi0 = jnp.asarray(twist(rng, kind)), jnp.asarray(twist(rng, "random"))
            assert_pose_close(Pose.exp(xi, method="quaternion"), Pose.exp(xi), atol=1e-12)
            T0 = Pose.exp(xi0)
            T = Pose.exp(xi) @ T0
            np.testing.assert_allclose(T.log_relative(T0), xi, rtol=1e-7, atol=1e-9)
            np.testing.assert_allclose(T.log_relative(T0), (T @ T0.inverse()).log(),
                                       rtol=1e-7, atol=1e-9)
            assert_pose_close(Pose.from_matrix(T.as_matrix(), orthonormalise="quaternion"), T,
                              atol=1e-12)


def test_from_matrix_rejects_an_unknown_projection():
    with pytest.raises(ValueError, match="orthonormalise"):
        Pose.from_matrix(jnp.eye(4), orthonormalise="svd")
    with pytest.raises(ValueError, match="method"):
        Pose.exp(jnp.zeros(6), method="cayley")
