"""The rolling-shutter model (frontend/shutter.py): both sides against an exact simulation of a
rolling-shutter camera, its Jacobian against jacfwd, and the tracker on the fast clip."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from edgevo_jax import Config
from edgevo_jax.camera import Intrinsics, unproject
from edgevo_jax.datasets import load_sequence
from edgevo_jax.frontend.residuals import point_jacobian, warp
from edgevo_jax.frontend.selection import KeyframeEdges
from edgevo_jax.frontend.shutter import (
    RowMotion,
    Shutter,
    depths_at_colour_time,
    row_motion,
    shutter_rate,
    shutter_warp,
    unroll_edges,
)
from edgevo_jax.geometry import Pose, exp_np
from edgevo_jax.image.interp import bilinear, bilinear_with_grad
from edgevo_jax.io import matrices_to_poses7
from edgevo_jax.metrics import ate
from edgevo_jax.runs.run import run_sequence

INTR = Intrinsics(517.3, 516.5, 318.6, 255.3)
H, W = 480, 640
TAU = 0.02  # readout (s)
#: body twist per second [v, w]: 90 deg/s about a tilted axis and 0.3 m/s
VEL = np.array([0.2, -0.1, 0.2, 0.8, 1.2, -0.6])


def _rs_observe(T_cam0_w: np.ndarray, pts_w: np.ndarray, tau: float, vel: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray]:
    """Exact rolling-shutter observation of world points (3, K) by a camera whose pose at
    time t (0 at the middle row) is T_cam(t)_w = exp(-t vel) T_cam0_w: each point's row v
    solves v = row of its projection at t = tau (v - ref) / H (fixed point, 30 rounds).
    Returns pixels (2, K) and depths (K,) in the row's camera."""
    ref = 0.5 * (H - 1)
    v = np.full(pts_w.shape[1], ref)
    for _ in range(30):
        uv, z = np.zeros((2, v.size)), np.zeros(v.size)
        for k in range(v.size):
            T = exp_np(-tau * (v[k] - ref) / H * vel) @ T_cam0_w
            p = T[:3, :3] @ pts_w[:, k] + T[:3, 3]
            uv[:, k] = [INTR.fx * p[0] / p[2] + INTR.cx, INTR.fy * p[1] / p[2] + INTR.cy]
            z[k] = p[2]
        v = uv[1]
    return uv, z


def _scene(seed: int, n: int = 200) -> np.ndarray:
    rng = np.random.default_rng(seed)
    uv = np.stack([rng.uniform(40, W - 40, n), rng.uniform(30, H - 30, n)])
    z = rng.uniform(1.0, 4.0, n)
    return np.stack([(uv[0] - INTR.cx) / INTR.fx * z, (uv[1] - INTR.cy) / INTR.fy * z, z])


def test_unroll_edges_moves_a_keyframe_to_its_middle_rows_time():
    """Edges seen by a rolling-shutter keyframe, unrolled with its per-row twist, land where
    a global shutter at the middle row's time sees them (0.05 px, 1e-3 relative depth);
    without the unrolling they are pixels off."""
    pts = _scene(0)
    uv_rs, z_rs = _rs_observe(np.eye(4), pts, TAU, VEL)
    edges = KeyframeEdges(uv=uv_rs.astype(np.float32), rho=(1 / z_rs).astype(np.float32),
                          grad=np.zeros((2, uv_rs.shape[1]), np.float32),
                          valid=np.ones(uv_rs.shape[1], bool))
    out = unroll_edges(edges, VEL * TAU / H, INTR, H)
    uv_gs = np.stack([INTR.fx * pts[0] / pts[2] + INTR.cx, INTR.fy * pts[1] / pts[2] + INTR.cy])
    assert np.abs(uv_rs - uv_gs).max() > 3.0  # the shear the model removes
    assert np.abs(out.uv - uv_gs).max() < 0.05
    np.testing.assert_allclose(1 / out.rho, pts[2], rtol=1e-3)


def test_depths_taken_after_the_colour_image_are_moved_to_its_time():
    """Edges on a wall facing the camera whose depths come from a depth image taken 15 ms
    after the colour image (the camera moving at VEL): moved to the colour time, their
    depths are the colour camera's within 1/15 of the error read (RMS 0.5 mm here, from
    12.7); a lag of 0 leaves them as they were. (The pixel is kept, the depth image is not
    read again: on a surface of slope s the error left is s times the pixel's motion.)"""
    rng = np.random.default_rng(1)
    uv = np.stack([rng.uniform(40, W - 40, 300), rng.uniform(30, H - 30, 300)])
    ray = np.stack([(uv[0] - INTR.cx) / INTR.fx, (uv[1] - INTR.cy) / INTR.fy, np.ones(300)])
    n, c = np.array([0.0, 0.0, 1.0]), 2.0  # a wall facing the camera, 2 m away
    z_colour = c / (n @ ray)
    lag = 0.015
    T = exp_np(lag * VEL)  # the depth camera (at the lag) in the colour camera (at 0)
    z_read = (c - n @ T[:3, 3]) / (n @ (T[:3, :3] @ ray))
    edges = KeyframeEdges(uv=uv.astype(np.float32), rho=(1 / z_read).astype(np.float32),
                          grad=np.zeros((2, 300), np.float32), valid=np.ones(300, bool))
    moved = depths_at_colour_time(edges, VEL, lag, INTR)
    before = np.sqrt(np.mean((z_read - z_colour) ** 2))
    after = np.sqrt(np.mean((1 / moved.rho - z_colour) ** 2))
    assert before > 5e-3 and after < before / 15
    np.testing.assert_array_equal(depths_at_colour_time(edges, VEL, 0.0, INTR).rho, edges.rho)


def test_shutter_warp_predicts_where_a_rolling_shutter_frame_sees_a_point():
    """Keyframe points warped into a frame moving at VEL (pose T at its middle row) land
    where the exact rolling-shutter simulation sees them (0.05 px); a zero twist is the
    plain warp, bit for bit."""
    pts = jnp.asarray(_scene(1))
    T = exp_np(np.array([0.03, -0.01, 0.02, 0.02, -0.05, 0.01]))
    uv_rs, _ = _rs_observe(T, np.asarray(pts), TAU, VEL)
    rows = RowMotion(twist=jnp.asarray(VEL * TAU / H), ref=jnp.asarray(0.5 * (H - 1)),
                     rate=jnp.asarray(0.0))
    with jax.enable_x64(True):
        pose = Pose.from_matrix(jnp.asarray(T))
        uv, _, _ = shutter_warp(INTR, pose, pts, rows)
        plain, _ = warp(INTR, pose, pts)
        still, _, scale = shutter_warp(INTR, pose, pts, rows._replace(twist=jnp.zeros(6)))
    assert np.abs(np.asarray(plain) - uv_rs).max() > 3.0
    assert np.abs(np.asarray(uv) - uv_rs).max() < 0.05
    np.testing.assert_array_equal(np.asarray(still), np.asarray(plain))
    np.testing.assert_array_equal(np.asarray(scale), 1.0)


def _field() -> jnp.ndarray:
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    return jnp.asarray(3.0 * np.sin(u / 37.0) * np.cos(v / 29.0) + 0.01 * u)


def test_residual_jacobian_with_the_shutter_matches_jacfwd():
    """The solve's Jacobian (point Jacobian at the moved point, times 1 + d rate) against
    jax.jacfwd of the residual whose row motion is read from the perturbed pose, as the
    solve's cost is: within 4 % of the largest entry at 90 deg/s (it leaves out the row's
    own dependence on the pose, f |twist_row| relative: 3 % here)."""
    with jax.enable_x64(True):
        pts = jnp.asarray(_scene(2, 60))
        T = Pose.from_matrix(jnp.asarray(exp_np(np.array([0.02, 0.01, -0.03, 0.03, 0.02,
                                                          -0.04]))))
        dt = 1 / 30
        # the previous frame, dt earlier at the same velocity: T_prev_kf = exp(dt VEL) T
        prev = jnp.asarray(exp_np(VEL * dt) @ np.asarray(T.as_matrix()))
        shutter = Shutter(prev, jnp.asarray(shutter_rate(TAU, H, dt)))
        field = _field()

        def residuals(xi):
            Ti = T.retract(xi)
            uv, _, _ = shutter_warp(INTR, Ti, pts, row_motion(Ti, shutter, 0, H))
            return bilinear(field, uv)[0]

        numeric = jax.jacfwd(residuals)(jnp.zeros(6)).T
        rows = row_motion(T, shutter, 0, H)
        uv, moved, scale = shutter_warp(INTR, T, pts, rows)
        _, grad, _ = bilinear_with_grad(field, uv)
        analytic = point_jacobian(INTR, moved, grad) * scale
        np.testing.assert_allclose(np.asarray(rows.twist) / float(shutter.rate), VEL * dt,
                                   rtol=1e-6)  # the twist is the motion from prev
        err = np.abs(np.asarray(analytic - numeric)).max() / np.abs(np.asarray(numeric)).max()
        assert err < 0.04, err
        # without the 1 + d rate scale the Jacobian is off by up to ~20 % here
        plain = point_jacobian(INTR, moved, grad)
        assert np.abs(np.asarray(plain - numeric)).max() / np.abs(numeric).max() > 0.05


def test_the_unrolled_points_are_unprojected_like_any_others():
    """unroll_edges leaves padding slots and a zero twist alone."""
    uv = np.array([[100.0, 200.0, 0.0], [50.0, 400.0, 0.0]], np.float32)
    edges = KeyframeEdges(uv=uv, rho=np.array([0.5, 0.25, 1.0], np.float32),
                          grad=np.zeros((2, 3), np.float32), valid=np.array([True, True, False]))
    same = unroll_edges(edges, np.zeros(6), INTR, H)
    np.testing.assert_allclose(same.uv, uv, atol=1e-4)
    moved = unroll_edges(edges, VEL * TAU / H, INTR, H)
    assert moved.uv[0, 2] == 0.0 and moved.rho[2] == 1.0  # padding untouched
    np.testing.assert_allclose(unproject(INTR, jnp.asarray(moved.uv[:, :2]),
                                         jnp.asarray(moved.rho[:2]))[2],
                               1 / moved.rho[:2], rtol=1e-6)


@pytest.mark.slow
def test_the_shutter_model_cuts_the_drift_on_the_fast_clip(shared_clip):
    """fr1_rpy's first 120 frames (75 deg/s hand-held rotation): the source's readout time
    (20 ms, the Freiburg cameras') against a global shutter, same seed: ATE at most 0.6 x
    (measured 19 against 54 mm)."""
    seq = load_sequence(shared_clip("rgbd_dataset_freiburg1_rpy_first120"))
    assert seq.readout_s == pytest.approx(0.020)
    scores = []
    for config in (Config(), Config(readout_s=0.0)):
        run = run_sequence(seq, config, progress=False)
        scores.append(ate(seq.groundtruth, (run.timestamps, matrices_to_poses7(run.poses)))
                      ["rmse"])
    assert scores[0] < 0.6 * scores[1], scores


def test_the_window_sees_each_keyframe_through_its_rolling_shutter():
    """``backend.window.edge_residuals`` with keyframes' row twists: an edge hosted by a
    rolling-shutter keyframe (unrolled to its middle row's time) lands in another
    rolling-shutter keyframe where the exact simulation sees it (fields u and v read the
    pixel back, 0.05 px); zero twists are the plain window, bit for bit."""
    from edgevo_jax.window.problem import WindowProblem, edge_residuals

    pts_w = _scene(3, 40)
    T_w = [np.eye(4), np.linalg.inv(exp_np(np.array([0.03, -0.01, 0.02, 0.02, -0.05, 0.01])))]
    vel = [VEL, -0.7 * VEL]
    uv, rho = [], []
    for T, v in zip(T_w, vel, strict=True):
        seen, z = _rs_observe(np.linalg.inv(T), pts_w, TAU, v)
        e = KeyframeEdges(uv=seen.astype(np.float32), rho=(1 / z).astype(np.float32),
                          grad=np.zeros_like(seen, np.float32), valid=np.ones(z.size, bool))
        e = unroll_edges(e, v * TAU / H, INTR, H)
        uv.append(e.uv)
        rho.append(e.rho)
    v_grid, u_grid = np.mgrid[0:H, 0:W].astype(np.float64)
    twists = np.stack([v * TAU / H for v in vel])
    with jax.enable_x64(True):
        def residuals(field, row_twists):
            problem = WindowProblem(
                poses=jnp.asarray(np.stack(T_w)), uv=jnp.asarray(np.stack(uv), jnp.float64),
                rho=jnp.asarray(np.stack(rho), jnp.float64), valid=jnp.ones((2, 40), bool),
                fields=(jnp.asarray(field),) * 2, intrinsics=jnp.asarray(np.asarray(INTR)),
                row_twists=row_twists)
            return np.asarray(edge_residuals(problem).r)[:, 0]  # (target, edge)

        got_u = residuals(u_grid, jnp.asarray(twists))
        got_v = residuals(v_grid, jnp.asarray(twists))
        plain = residuals(u_grid, None)
        np.testing.assert_array_equal(residuals(u_grid, jnp.zeros((2, 6))), plain)
    for j, T in enumerate(T_w):  # target j sees the edges hosted by the other keyframe
        seen, _ = _rs_observe(np.linalg.inv(T), pts_w, TAU, vel[j])
        assert np.abs(got_u[j] - seen[0]).max() < 0.05
        assert np.abs(got_v[j] - seen[1]).max() < 0.05
        assert np.abs(plain[j] - seen[0]).max() > 1.0
