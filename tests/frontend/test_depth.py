"""The optional depth residual: keyframe depth points and normals, the point-to-plane residual
and its Jacobian, and the tracker with it switched on."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from edgevo_jax import Config
from edgevo_jax.camera import Intrinsics
from edgevo_jax.cli import BUNDLED_CLIP
from edgevo_jax.datasets import load_sequence
from edgevo_jax.frontend.depth import depth_agreement, depth_points, depth_valid, point_to_plane
from edgevo_jax.geometry import Pose
from edgevo_jax.runs.measure import groundtruth_at
from edgevo_jax.runs.run import run_sequence, summarise
from edgevo_jax.tracking.odometry import Odometry

INTR = Intrinsics(100.0, 110.0, 79.3, 60.7)
H, W = 120, 160


def plane_depth(normal, offset: float) -> np.ndarray:
    """Depth (H, W) of the plane n . p = offset seen by INTR (n facing the camera)."""
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    ray = np.stack([(u - INTR.cx) / INTR.fx, (v - INTR.cy) / INTR.fy, np.ones_like(u)])
    return offset / np.tensordot(np.asarray(normal, np.float64), ray, axes=1)


NORMAL = np.array([0.2, -0.1, -1.0]) / np.linalg.norm([0.2, -0.1, -1.0])


def test_depth_points_lie_on_the_plane_with_its_normal():
    depth = plane_depth(NORMAL, -2.0)
    pts, normals = depth_points(depth, INTR, 64, min_depth=0.1, max_depth=8.0, seed=0)
    assert pts.shape == normals.shape == (3, 64)
    np.testing.assert_allclose(NORMAL @ pts, -2.0, atol=1e-4)
    np.testing.assert_allclose(normals.T, np.broadcast_to(NORMAL, (64, 3)), atol=1e-4)


def test_depth_points_skip_missing_depth_and_steps_and_pad():
    depth = plane_depth(NORMAL, -2.0)
    depth[:, : W // 2] = np.nan  # the left half missing
    depth[H // 2:, W // 2:] *= 1.5  # a depth step
    pts, normals = depth_points(depth, INTR, 4000, min_depth=0.1, max_depth=8.0, seed=0)
    valid = np.asarray(depth_valid(jnp.asarray(normals)))
    assert 0 < valid.sum() < 4000 and not valid[valid.sum():].any()  # padding at the end
    u = INTR.fx * pts[0, valid] / pts[2, valid] + INTR.cx
    v = INTR.fy * pts[1, valid] / pts[2, valid] + INTR.cy
    assert u.min() > W // 2 and not np.any(np.abs(v - H // 2) < 1.0)  # nothing at the step


def test_residual_is_zero_at_the_true_pose_and_its_jacobian_is_the_derivative():
    """Keyframe and frame see the same plane from poses T apart: at T the residuals vanish
    and J equals the derivative of r(exp(xi) T) (jacfwd, float64); away from T they do not
    vanish."""
    with jax.enable_x64(True):
        T = Pose.exp(jnp.array([0.02, -0.01, 0.03, 0.01, -0.02, 0.015]))
        pts_k, n_k = depth_points(plane_depth(NORMAL, -2.0), INTR, 64, min_depth=0.1,
                                  max_depth=8.0, seed=0)
        # the frame's depth: the same plane in the frame's camera
        n_c = np.asarray(T.R) @ NORMAL
        depth_c = jnp.asarray(plane_depth(n_c, -2.0 + float(n_c @ np.asarray(T.t))))
        pts, normals = jnp.asarray(pts_k, jnp.float64), jnp.asarray(n_k, jnp.float64)
        r, J, ok = point_to_plane(T, pts, normals, depth_c, INTR, 0)
        assert int(ok.sum()) > 50
        # nearest-pixel depth: off the plane point by under a pixel's footprint
        assert float(jnp.max(jnp.abs(jnp.where(ok, r, 0.0)))) < 1.0

        def r_at(xi):
            return point_to_plane(T.retract(xi), pts, normals, depth_c, INTR, 0)[0]

        auto = jax.jacfwd(r_at)(jnp.zeros(6))  # (M, 6); the nearest pixel held (round)
        rel = jnp.abs(auto.T - J)[:, ok] / (jnp.abs(J[:, ok]).max() + 1e-12)
        assert float(rel.max()) < 0.05
        moved = point_to_plane(T.retract(jnp.array([0, 0, 0.05, 0, 0, 0.0])), pts, normals,
                               depth_c, INTR, 0)[0]
        assert float(jnp.median(jnp.abs(moved[ok]))) > 5 * float(jnp.median(jnp.abs(r[ok])))


def test_tracker_with_the_depth_residual_tracks_the_bundled_clip():
    """Switched on, keyframes carry depth points, frames carry their depth map, and the
    bundled clip tracks within the plain tracker's ATE bound (through the scan driver)."""
    seq = load_sequence(BUNDLED_CLIP)
    config = Config(depth_residual=True)
    odo = Odometry(config, seq.intrinsics)
    r0 = odo.track(*seq.load_frame(0), seq.timestamps[0])
    assert r0.state == "OK" and odo.state.keyframe.edges.depth_pts.shape == (3, config.depth_points)
    run = run_sequence(seq, config, progress=False)
    stats = summarise(run, seq)
    assert stats["lost"] == 0 and stats["ate_rmse_m"] < 0.01, stats


def test_depth_points_count_must_be_positive():
    with pytest.raises(ValueError, match="depth_points"):
        Config(depth_points=0)


# -- the second opinion: depth_agreement ---------------------------------------------------------
CORNER = [(np.array([0.0, 1.0, 0.0]), 0.25),   # a floor 0.25 m below (y down)
          (np.array([0.0, 0.0, 1.0]), 1.5),    # a wall 1.5 m ahead
          (np.array([1.0, 0.0, 0.0]), 0.25)]   # a wall 0.25 m to the right


def corner_depth(T_world_cam: np.ndarray) -> np.ndarray:
    """Depth (H, W) of the room corner CORNER (planes n . p = d, world frame) seen by INTR
    from T_world_cam: the nearest plane in front along each pixel's ray."""
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    ray = np.stack([(u - INTR.cx) / INTR.fx, (v - INTR.cy) / INTR.fy, np.ones_like(u)])
    R, c = T_world_cam[:3, :3], T_world_cam[:3, 3]
    ray_w = np.tensordot(R, ray, axes=1)
    depth = np.full((H, W), np.inf)
    for n, d in CORNER:
        den = np.tensordot(n, ray_w, axes=1)
        with np.errstate(divide="ignore", invalid="ignore"):
            z = (d - n @ c) / den
        depth = np.where((z > 0.05) & (z < depth), z, depth)
    return np.where(np.isfinite(depth), depth, 0.0)


def moved(x=0.0, y=0.0, z=0.0, yaw_deg=0.0) -> np.ndarray:
    T = np.eye(4)
    a = np.radians(yaw_deg)
    T[:3, :3] = [[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]]
    T[:3, 3] = x, y, z
    return T


def agreement(prev, cur, T_cur_prev, tol=0.02):
    return depth_agreement(prev, cur, T_cur_prev, INTR, tol_m=tol, min_depth=0.1,
                           max_depth=8.0, seed=0)


def test_depth_agreement_is_full_at_the_true_motion_and_falls_centimetres_off():
    prev_pose, cur_pose = moved(), moved(0.05, 0.02, 0.10, yaw_deg=8.0)
    prev, cur = corner_depth(prev_pose), corner_depth(cur_pose)
    truth = np.linalg.inv(cur_pose) @ prev_pose
    assert agreement(prev, cur, truth) > 0.99
    assert agreement(prev, cur, moved(z=0.005) @ truth) > 0.99  # within the tolerance
    # 6 cm across the side wall, along the view onto the far wall, 4 degrees of yaw: the
    # points on the surfaces the error moves them off disagree (a slide along every plane
    # in view, here along the floor, is what depth cannot see)
    shares = [agreement(prev, cur, off @ truth)
              for off in (moved(x=0.06), moved(z=0.06), moved(yaw_deg=4.0))]
    assert max(shares) < 0.85 and min(shares) < 0.65, shares


def test_depth_agreement_says_none_where_it_cannot_judge():
    prev = corner_depth(moved())
    assert agreement(prev, np.zeros_like(prev), np.eye(4)) is None  # no depth in the frame
    assert agreement(np.zeros_like(prev), prev, np.eye(4)) is None  # none in the previous
    assert agreement(prev, prev, moved(yaw_deg=180.0)) is None      # nothing in view


def test_depth_agreement_on_real_frames_follows_the_ground_truth():
    seq = load_sequence(BUNDLED_CLIP)
    (_, d0), (_, d1) = seq.load_frame(0), seq.load_frame(4)  # 6 cm apart
    g = groundtruth_at(seq, seq.timestamps[[0, 4]])
    truth = np.linalg.inv(g[1]) @ g[0]
    intr = seq.intrinsics
    share = depth_agreement(d0, d1, truth, intr, tol_m=0.02, min_depth=0.1, max_depth=8.0,
                            seed=0)
    off = depth_agreement(d0, d1, moved(z=0.08) @ truth, intr, tol_m=0.02, min_depth=0.1,
                          max_depth=8.0, seed=0)
    assert share > 0.9 and off < 0.5
