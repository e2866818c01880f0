"""Properties of the pure JAX building blocks: interpolation, warp, residual Jacobian, Huber."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from edgevo_jax.camera import Intrinsics, project, unproject
from edgevo_jax.frontend.residuals import residual_and_jacobian, residual_jacobian_autodiff, warp
from edgevo_jax.frontend.robust import huber_cost, huber_weights
from edgevo_jax.geometry import Pose, exp_np, scale_motion_np
from edgevo_jax.image.interp import bicubic, bicubic_with_grad, bilinear, bilinear_with_grad

INTR = Intrinsics(100.0, 110.0, 79.3, 60.7)  # a 160 x 120 camera, off-centre principal point
H, W = 120, 160
floats = st.floats(-2.0, 2.0, allow_nan=False)


def random_pose(rng: np.random.Generator, scale: float) -> Pose:
    return Pose.exp(jnp.asarray(rng.normal(size=6) * scale))


def scene_points(rng: np.random.Generator, n: int) -> jnp.ndarray:
    """(3, n) points seen by INTR at pixels well inside the image, depth 1-3 m."""
    uv = np.stack([rng.uniform(30, W - 30, n), rng.uniform(25, H - 25, n)])
    rho = 1.0 / rng.uniform(1.0, 3.0, n)
    return unproject(INTR, jnp.asarray(uv), jnp.asarray(rho))


def smooth_field(rng: np.random.Generator) -> jnp.ndarray:
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    f = np.zeros((H, W))
    for _ in range(4):
        a, b, c = rng.normal(size=3)
        f += a * np.sin(b * u / 13.0 + c) * np.cos(c * v / 11.0 - b)
    return jnp.asarray(f + 0.3 * rng.random((H, W)))  # add grid-scale roughness as well


@given(a=floats, b=floats, c=floats, seed=st.integers(0, 2**16))
@settings(max_examples=30, deadline=None)
def test_bilinear_is_exact_on_affine_fields(a, b, c, seed):
    with jax.enable_x64(True):
        v, u = np.mgrid[0:H, 0:W].astype(np.float64)
        field = jnp.asarray(a * u + b * v + c)
        rng = np.random.default_rng(seed)
        uv = jnp.asarray(np.stack([rng.uniform(0, W - 1, 50), rng.uniform(0, H - 1, 50)]))
        val, grad, inside = bilinear_with_grad(field, uv)
        assert bool(jnp.all(inside))
        np.testing.assert_allclose(val, a * uv[0] + b * uv[1] + c, atol=1e-9)
        np.testing.assert_allclose(grad[0], a, atol=1e-9)
        np.testing.assert_allclose(grad[1], b, atol=1e-9)


def test_bilinear_flags_points_outside():
    field = jnp.ones((H, W))
    uv = jnp.array([[-0.1, 0.0, W - 1.0, W - 0.9, 5.0], [5.0, 0.0, H - 1.0, 5.0, H - 0.5]])
    _, inside = bilinear(field, uv)
    assert inside.tolist() == [False, True, True, False, False]


_bicubic_jit = jax.jit(bicubic_with_grad)


@given(coef=st.lists(st.floats(-1.0, 1.0), min_size=9, max_size=9),
       seed=st.integers(0, 2**16))
@settings(max_examples=30, deadline=None)
def test_bicubic_is_exact_on_biquadratic_fields(coef, seed):
    """Catmull-Rom reproduces sum c_ab u^a v^b (a, b <= 2) and its gradient where the 4 x 4
    pixels lie inside the field, and passes through the pixel values everywhere."""
    with jax.enable_x64(True):
        v, u = np.mgrid[0:H, 0:W].astype(np.float64) / 50.0  # keep the values O(1)
        c = np.asarray(coef).reshape(3, 3)

        def poly(u, v):
            return sum(c[a, b] * u**a * v**b for a in range(3) for b in range(3))

        def grad(u, v):
            du = sum(a * c[a, b] * u ** (a - 1) * v**b for a in range(1, 3) for b in range(3))
            dv = sum(b * c[a, b] * u**a * v ** (b - 1) for a in range(3) for b in range(1, 3))
            return du / 50.0, dv / 50.0

        field = jnp.asarray(poly(u, v))
        rng = np.random.default_rng(seed)
        uv = np.stack([rng.uniform(1, W - 2, 50), rng.uniform(1, H - 2, 50)])
        val, g, inside = _bicubic_jit(field, jnp.asarray(uv))
        assert bool(jnp.all(inside))
        np.testing.assert_allclose(val, poly(uv[0] / 50.0, uv[1] / 50.0), atol=1e-11)
        np.testing.assert_allclose(g, np.stack(grad(uv[0] / 50.0, uv[1] / 50.0)), atol=1e-11)
        pixels = jnp.asarray(np.stack([rng.integers(0, W, 40), rng.integers(0, H, 40)]), float)
        np.testing.assert_allclose(_bicubic_jit(field, pixels)[0],
                                   field[pixels[1].astype(int), pixels[0].astype(int)],
                                   atol=1e-12)


def test_bicubic_derivative_equals_autodiff_and_finite_differences():
    """On a rough field, near and at the borders too; the derivative is continuous across
    pixel boundaries (C1), unlike the bilinear one. The derivative rule (custom JVP): the
    value's derivative is the returned gradient, the gradient's is the interpolant's Hessian
    (against central differences of the gradient), and a field tangent is looked up."""
    with jax.enable_x64(True):
        rng = np.random.default_rng(3)
        field = smooth_field(rng)
        uv = np.stack([rng.uniform(0, W - 1, 200), rng.uniform(0, H - 1, 200)])
        uv[:, :4] = [[0.0, 0.3, W - 1.0, W - 1.4], [H - 1.0, 0.7, 0.0, H - 1.2]]
        uv = jnp.asarray(uv)
        _, g, inside = _bicubic_jit(field, uv)
        assert bool(jnp.all(inside))
        auto = jax.jit(jax.vmap(jax.grad(lambda p: bicubic(field, p[:, None])[0][0]),
                                in_axes=1, out_axes=1))(uv)
        np.testing.assert_allclose(g, auto, rtol=1e-12, atol=1e-12)
        grad_of = jax.jit(lambda f, p: bicubic_with_grad(f, p)[1])
        for k in range(2):
            d = jnp.zeros((2, uv.shape[1])).at[k].set(1.0)
            _, hess_k = jax.jvp(lambda p: grad_of(field, p), (uv,), (d,))
            fd = (grad_of(field, uv + 1e-6 * d) - grad_of(field, uv - 1e-6 * d)) / 2e-6
            inner = ((uv[0] > 1e-3) & (uv[0] < W - 1 - 1e-3) & (uv[1] > 1e-3)
                     & (uv[1] < H - 1 - 1e-3))
            np.testing.assert_allclose(np.asarray(hess_k)[:, inner], np.asarray(fd)[:, inner],
                                       rtol=1e-5, atol=1e-6)
        d_field = jnp.asarray(rng.normal(size=field.shape))
        (_, _, _), (dv, dg, _) = jax.jvp(bicubic_with_grad, (field, uv),
                                         (d_field, jnp.zeros_like(uv)))
        v_lin, g_lin, _ = bicubic_with_grad(d_field, uv)
        np.testing.assert_allclose(dv, v_lin, atol=1e-12)
        np.testing.assert_allclose(dg, g_lin, atol=1e-12)
        interior = (uv[0] > 1e-3) & (uv[0] < W - 1 - 1e-3) & (uv[1] > 1e-3) & (uv[1] < H - 1 - 1e-3)
        eps = 1e-6
        for k in range(2):
            d = jnp.zeros((2, 1)).at[k].set(eps)
            fd = (_bicubic_jit(field, uv + d)[0] - _bicubic_jit(field, uv - d)[0]) / (2 * eps)
            np.testing.assert_allclose(np.asarray(g[k])[interior], np.asarray(fd)[interior],
                                       rtol=1e-6, atol=1e-7)
        # across a pixel boundary (u = 40): the bicubic gradient is continuous
        across = jnp.array([[40.0 - 1e-9, 40.0 + 1e-9], [30.3, 30.3]])
        g_cubic = bicubic_with_grad(field, across)[1]
        g_linear = bilinear_with_grad(field, across)[1]
        np.testing.assert_allclose(g_cubic[:, 0], g_cubic[:, 1], atol=1e-7)
        assert float(jnp.max(jnp.abs(g_linear[:, 0] - g_linear[:, 1]))) > 1e-3


@pytest.mark.parametrize("scale", [0.0, 1e-7, 1e-3, 0.03])
def test_analytic_jacobian_equals_jacfwd(scale):
    """At random poses (identity and near-identity included) and off-grid sub-pixel points."""
    with jax.enable_x64(True):
        rng = np.random.default_rng(int(scale * 1e7) + 1)
        field = smooth_field(rng)
        pts = scene_points(rng, 200)
        T = random_pose(rng, scale)
        r, J, ok, uv = residual_and_jacobian(field, INTR, T, pts)
        assert bool(jnp.all(ok))
        assert not np.any(np.isclose(uv, np.round(uv), rtol=0, atol=1e-6))  # off the integer grid
        J_auto = residual_jacobian_autodiff(field, INTR, T, pts)
        np.testing.assert_allclose(J, J_auto, rtol=1e-9, atol=1e-9)


def test_jacobian_matches_finite_differences():
    with jax.enable_x64(True):
        rng = np.random.default_rng(7)
        field = jnp.asarray(np.sin(np.mgrid[0:H, 0:W][1] / 9.0) + np.mgrid[0:H, 0:W][0] / 50.0)
        pts = scene_points(rng, 20)
        T = random_pose(rng, 0.02)
        _, J, _, _ = residual_and_jacobian(field, INTR, T, pts)
        eps = 1e-6
        for k in range(6):
            d = np.zeros(6)
            d[k] = eps
            rp = bilinear(field, warp(INTR, Pose.exp(jnp.asarray(d)) @ T, pts)[0])[0]
            rm = bilinear(field, warp(INTR, Pose.exp(jnp.asarray(-d)) @ T, pts)[0])[0]
            np.testing.assert_allclose(J[k], (rp - rm) / (2 * eps), rtol=1e-4, atol=1e-6)


@given(seed=st.integers(0, 2**16))
@settings(max_examples=25, deadline=None)
def test_identity_warp_is_identity_and_inverse_round_trips(seed):
    with jax.enable_x64(True):
        rng = np.random.default_rng(seed)
        uv = jnp.asarray(np.stack([rng.uniform(0, W - 1, 30), rng.uniform(0, H - 1, 30)]))
        rho = jnp.asarray(1.0 / rng.uniform(0.3, 8.0, 30))
        pts = unproject(INTR, uv, rho)
        uv_id, _ = warp(INTR, Pose.identity(jnp.float64), pts)
        np.testing.assert_allclose(uv_id, uv, atol=1e-9)
        T = random_pose(rng, 0.1)
        _, pts_c = warp(INTR, T, pts)
        back = T.inverse().apply(pts_c)
        np.testing.assert_allclose(back, pts, atol=1e-9)
        np.testing.assert_allclose(project(INTR, back), uv, atol=1e-7)


@given(r=st.floats(-50, 50), delta=st.floats(0.1, 5.0))
@settings(max_examples=50, deadline=None)
def test_huber_weight_is_the_irls_weight_of_the_huber_cost(r, delta):
    """d rho / dr = w(r) r: minimising sum w r^2 by IRLS minimises the Huber cost."""
    with jax.enable_x64(True):
        grad = jax.grad(huber_cost)(jnp.asarray(r), delta)
        np.testing.assert_allclose(grad, huber_weights(jnp.asarray(r), delta) * r, atol=1e-12)


def test_intrinsics_pyramid_keeps_the_pixel_centre_convention():
    # the centre of the top-left 2x2 block at level 0 is (0.5, 0.5): pixel (0, 0) of level 1
    p = unproject(INTR, jnp.array([[0.5], [0.5]]), jnp.array([1.0]))
    np.testing.assert_allclose(project(INTR.at_level(1), p), [[0.0], [0.0]], atol=1e-5)


def test_intrinsics_validate_rejects_bad_values():
    with pytest.raises(ValueError, match="finite"):
        Intrinsics(float("nan"), 1.0, 0.0, 0.0).validate()
    with pytest.raises(ValueError, match="positive"):
        Intrinsics(-1.0, 1.0, 0.0, 0.0).validate()


def test_half_a_motion_twice_is_the_motion():
    T = exp_np(np.array([0.1, -0.05, 0.2, 0.3, -0.2, 0.1]))
    half = scale_motion_np(T, 0.5)
    np.testing.assert_allclose(half @ half, T, atol=1e-12)
    np.testing.assert_allclose(scale_motion_np(T, 0.0), np.eye(4), atol=1e-15)
