"""Depth registration (edgevo_jax.depth_registration): a depth map re-rendered in another
camera pose, checked on planes, an occluder and a real frame of the bundled clip."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from edgevo_jax.camera import CAMERAS, Intrinsics, checked_pose
from edgevo_jax.cli import BUNDLED_CLIP
from edgevo_jax.depth_registration import register_depth

K = Intrinsics(500.0, 500.0, 39.5, 29.5)


def _T(rvec=(0.0, 0.0, 0.0), t=(0.0, 0.0, 0.0)) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(np.asarray(rvec, np.float64))[0]
    T[:3, 3] = t
    return T


def test_identity_returns_the_valid_pixels_exactly():
    rng = np.random.default_rng(0)
    depth = rng.uniform(0.5, 4.0, (60, 80)).astype(np.float32)
    depth[rng.random(depth.shape) < 0.2] = 0.0
    depth[3, 4] = np.nan
    out = register_depth(depth, K, K, np.eye(4))
    assert out.dtype == np.float32 and out.shape == depth.shape
    valid = np.isfinite(depth) & (depth > 0)
    np.testing.assert_array_equal(out[valid], depth[valid])
    assert np.all(out[~valid] == 0)


def test_translation_of_a_fronto_parallel_plane_shifts_it_by_f_t_over_z():
    """A plane at z = 2 m seen from a camera 0.02 m to the left (p_color = p_depth + t,
    t_x = +0.02): every point moves by fx * t_x / z = 5 pixels to the right."""
    depth = np.full((60, 80), 2.0, np.float32)
    out = register_depth(depth, K, K, _T(t=(0.02, 0.0, 0.0)))
    np.testing.assert_array_equal(out[:, 5:], 2.0)
    assert np.all(out[:, :5] == 0)  # nothing lands there
    # along z: the plane moves away, same pixels shrink towards the principal point
    out = register_depth(depth, K, K, _T(t=(0.0, 0.0, 0.5)))
    assert np.allclose(out[out > 0], 2.5)


def test_occlusion_keeps_the_nearer_surface():
    """A near square in front of a far wall; seen from the side, the square covers part of
    the wall's pixels and wins there."""
    depth = np.full((60, 80), 4.0, np.float32)
    depth[20:40, 30:50] = 1.0
    out = register_depth(depth, K, K, _T(t=(0.024, 0.0, 0.0)))  # square: 12 px, wall: 3 px
    # columns 53-61: the wall's columns 50-58 and the square's land there; the square wins
    np.testing.assert_array_equal(out[20:40, 42:62], 1.0)
    np.testing.assert_array_equal(out[20:40, 62:], 4.0)  # the wall right of the square
    np.testing.assert_array_equal(out[20:40, 33:42], 0.0)  # disoccluded: nothing seen there
    np.testing.assert_array_equal(out[:20, 3:], 4.0)


def test_shape_and_intrinsics_of_the_colour_camera():
    depth = np.full((60, 80), 2.0, np.float32)
    K2 = Intrinsics(1000.0, 1000.0, 79.5, 59.5)  # the same view on a grid twice as fine
    out = register_depth(depth, K, K2, np.eye(4), shape=(120, 160))
    assert out.shape == (120, 160)
    assert np.all(out[::2, ::2] == 2.0) and np.all(out[1::2, 1::2] == 0.0)  # cracks stay 0


def test_round_trip_on_a_real_frame_recovers_most_pixels_within_a_millimetre():
    raw = cv2.imread(str(BUNDLED_CLIP / "depth" / "1305031102.160407.png"), cv2.IMREAD_UNCHANGED)
    depth = raw.astype(np.float32) / 5000.0
    intr = CAMERAS["fr1"].camera.intrinsics
    T = _T(rvec=np.deg2rad([0.4, -0.3, 0.2]), t=(0.01, -0.005, 0.003))
    there = register_depth(depth, intr, intr, T)
    back = register_depth(there, intr, intr, np.linalg.inv(T))
    valid = depth > 0
    close = valid & (np.abs(back - depth) < 1e-3)
    assert close.sum() > 0.85 * valid.sum(), close.sum() / valid.sum()


@pytest.mark.parametrize("T, why", [
    (np.eye(3), "4x4"),
    (np.full((4, 4), np.nan), "finite"),
    (np.diag([1.0, 1.0, -1.0, 1.0]), "rotation"),
    (np.diag([2.0, 1.0, 1.0, 1.0]), "rotation"),
    (np.vstack([np.eye(4)[:3], [0.0, 0.0, 1.0, 1.0]]), "last row"),
])
def test_not_rigid_is_refused(T, why):
    with pytest.raises(ValueError, match=why):
        checked_pose(T, "T_color_depth")
    with pytest.raises(ValueError, match="T_color_depth"):
        register_depth(np.ones((4, 4)), K, K, T)


def test_not_2d_is_refused():
    with pytest.raises(ValueError, match="2-D"):
        register_depth(np.ones((4, 4, 1)), K, K, np.eye(4))
