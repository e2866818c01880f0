"""SE(3) helpers on top of jaxlie. Twists are [v, w] (translation first), as in jaxlie.

``T_a_b`` maps points from frame b to frame a. Host-side 4x4 helpers use numpy float64.
"""

from __future__ import annotations

import jax.numpy as jnp
import jaxlie
import numpy as np


def retract_left(T: jaxlie.SE3, xi: jnp.ndarray) -> jaxlie.SE3:
    """Left-multiplicative update exp(xi) * T, xi = [v, w] (6,)."""
    return jaxlie.SE3.exp(xi) @ T


def transform_points(T: jaxlie.SE3, pts: jnp.ndarray) -> jnp.ndarray:
    """R @ p + t for points (3, K) (struct of arrays)."""
    R, t = T.rotation().as_matrix(), T.translation()
    x, y, z = pts[0], pts[1], pts[2]
    return jnp.stack([R[i, 0] * x + R[i, 1] * y + R[i, 2] * z + t[i] for i in range(3)])


def inverse_np(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid 4x4 transform (numpy)."""
    R, t = T[:3, :3], T[:3, 3]
    out = np.eye(4)
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ t
    return out


def rotation_angle_np(T: np.ndarray) -> float:
    """Rotation angle (rad) of a 4x4 rigid transform."""
    c = (np.trace(T[:3, :3]) - 1.0) / 2.0
    return float(np.arccos(np.clip(c, -1.0, 1.0)))


def orthonormalise_np(T: np.ndarray) -> np.ndarray:
    """T (4, 4) with its rotation block projected back onto SO(3) (float32 round-off)."""
    u, _, vt = np.linalg.svd(T[:3, :3])
    out = T.copy()
    out[:3, :3] = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
    return out


def scale_motion_np(T: np.ndarray, s: float) -> np.ndarray:
    """exp(s log T) for a 4x4 rigid motion T: s = 0.5 is half the rotation angle and half
    the screw motion (numpy float64 out)."""
    xi = np.asarray(jaxlie.SE3.from_matrix(T).log(), np.float64)
    return np.asarray(jaxlie.SE3.exp(s * xi).as_matrix(), np.float64)
