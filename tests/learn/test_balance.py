"""The depth residual's weight (``Config.depth_weight``) in the plain solve, and its learnt
derivative (``learn.depth_weight_gradient``) on a real pair of the bundled clip: weight 0 is
the edges alone, and the pose's rate in log w solves the implicit function theorem's equation
with derivatives taken by central differences (float64)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from edgevo_jax import Config
from edgevo_jax.camera import unproject
from edgevo_jax.cli import BUNDLED_CLIP
from edgevo_jax.datasets import groundtruth_pose_at, load_sequence
from edgevo_jax.derive import solve_knobs, solve_structure
from edgevo_jax.frontend.align import normal_equations, track
from edgevo_jax.frontend.depth import depth_points
from edgevo_jax.frontend.selection import keyframe_edges
from edgevo_jax.geometry import Pose, inverse_np
from edgevo_jax.image.preprocess import preprocess
from edgevo_jax.io import poses7_to_matrices
from edgevo_jax.learn import depth_weight_gradient, rpe_loss

#: level 0 run long: many LM tries, no early stop
CONVERGED = Config(iterations=(60, 10, 10), step_tol=0.0, max_rejects=1000)


@pytest.fixture(scope="module")
def pair():
    """Keyframe 0 (edges and depth points) and frame 3 of the bundled clip, with the true
    T_cur_kf (numpy)."""
    seq = load_sequence(BUNDLED_CLIP)
    f0, f3 = (preprocess(*seq.load_frame(k), CONVERGED) for k in (0, 3))
    e = keyframe_edges(f0, CONVERGED, seed=0, intr=seq.intrinsics)
    pts, normals = depth_points(f0.depth, seq.intrinsics, CONVERGED.depth_points,
                                min_depth=CONVERGED.min_depth, max_depth=CONVERGED.max_depth,
                                seed=0)
    gt = [poses7_to_matrices(groundtruth_pose_at(seq, seq.timestamps[k])[None])[0]
          for k in (0, 3)]
    return seq.intrinsics, e._replace(depth_pts=pts, depth_normals=normals), f3, \
        inverse_np(gt[1]) @ gt[0]


def _as(tree, dtype):
    return jax.tree.map(lambda x: jnp.asarray(x, dtype) if np.issubdtype(
        np.asarray(x).dtype, np.floating) else jnp.asarray(x), tree)


def test_weight_zero_is_the_edges_alone(pair):
    """depth_weight 0 adds nothing: the pose of a solve without depth points, bit for bit;
    weight 1 moves it (the knob reaches the solve)."""
    intr, kf, frame, _ = pair
    structure = solve_structure(CONVERGED)

    def solve(kf, weight):
        knobs = solve_knobs(CONVERGED.replace(depth_weight=weight))
        return np.asarray(jax.jit(track, static_argnames="config")(
            _as(kf, jnp.float32), _as(frame.dist, jnp.float32), _as(frame.edge_map, jnp.float32),
            np.eye(4, dtype=np.float32), intr, config=structure, knobs=knobs).T_c_k)

    edges_alone = solve(kf._replace(depth_pts=None, depth_normals=None), 1.0)
    np.testing.assert_array_equal(solve(kf, 0.0), edges_alone)
    assert np.abs(solve(kf, 1.0) - edges_alone).max() > 1e-6


def test_pose_rate_solves_the_implicit_equation_by_differences(pair):
    """In float64, at the returned pose T*: dF/dxi rate = -w dF/dw with both derivatives of
    F = the level-0 gradient g (``align.normal_equations``, decisions retaken at each pose)
    taken by central differences (the function's own are jacfwd), and the loss derivative is
    rate . dL/dxi with dL/dxi by differences too, at two weights. (The plain LM stops short
    of the stationary point, so its pose's response to w is not what rate predicts: the
    rate is the stationary point's, see ``learn.balance``.)"""
    intr, kf, frame, true = pair
    structure = solve_structure(CONVERGED)
    grad_fn = jax.jit(depth_weight_gradient, static_argnames=("config", "rot_weight"))
    with jax.enable_x64(True):
        kf64, dist, em = _as(kf, jnp.float64), _as(frame.dist, jnp.float64), \
            _as(frame.edge_map, jnp.float64)
        truth = jnp.asarray(true)
        pts_k = unproject(intr, kf64.uv, kf64.rho)
        for w in (1.0, 3.0):
            knobs = _as(solve_knobs(CONVERGED.replace(depth_weight=w)), jnp.float64)
            out = grad_fn(kf64, dist, em, jnp.eye(4), intr, knobs, truth, config=structure,
                          rot_weight=0.1)
            T = Pose.from_matrix(out.T_c_k)

            @jax.jit
            def F(xi, weight, T=T, knobs=knobs):
                return normal_equations(T.retract(xi), pts_k, kf64, dist[0], em, intr, 0,
                                        knobs._replace(depth_weight=weight)).g

            h, eye = 1e-7, np.eye(6)
            A = np.stack([(F(h * e, w) - F(-h * e, w)) / (2 * h) for e in eye], axis=1)
            b = np.asarray(F(jnp.zeros(6), w + 1e-3) - F(jnp.zeros(6), w - 1e-3)) / 2e-3
            rate = np.asarray(out.pose_rate)
            lhs, rhs = A @ rate, -w * b
            assert np.linalg.norm(lhs - rhs) <= 0.02 * np.linalg.norm(rhs), (lhs, rhs)
            L = [float(rpe_loss(T.retract(s * h * e).as_matrix(), truth, rot_weight=0.1))
                 for e in eye for s in (1, -1)]
            dL = (np.asarray(L[0::2]) - np.asarray(L[1::2])) / (2 * h)
            assert float(out.grad_log_weight) == pytest.approx(dL @ rate, rel=1e-4)
            assert float(out.loss) == pytest.approx(
                float(rpe_loss(out.T_c_k, truth, rot_weight=0.1)), rel=1e-12)
