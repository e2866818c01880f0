"""The local map (local_map.py) driven with real keyframes of the bundled clip: activation,
refinement, marginalisation into a prior, and its wiring into the tracker."""

from __future__ import annotations

import jax
import numpy as np
import pytest

from edgevo_jax import Config
from edgevo_jax.cli import BUNDLED_CLIP
from edgevo_jax.datasets import load_sequence
from edgevo_jax.datasets.groundtruth import groundtruth_pose_at
from edgevo_jax.frontend.selection import keyframe_edges
from edgevo_jax.image.preprocess import preprocess
from edgevo_jax.io import poses7_to_matrices
from edgevo_jax.runs.run import run_sequence, summarise
from edgevo_jax.window.sliding import SlidingWindow, depth_continuous

CONFIG = Config(mapping=True, window_size=3, mapping_iterations=3)


@pytest.fixture(scope="module")
def driven():
    """Frames 0, 2, 4, 6, 8 of the bundled clip handed to a 3-keyframe window as keyframes at
    their ground-truth poses, the newest nudged by 4 mm (as tracking would leave it)."""
    seq = load_sequence(BUNDLED_CLIP)
    lm = SlidingWindow(CONFIG, np.asarray(seq.intrinsics), (seq.height, seq.width))
    steps = []
    for n, i in enumerate(range(0, 10, 2)):
        frame = preprocess(*seq.load_frame(i), CONFIG)
        t = float(seq.timestamps[i])
        gt = poses7_to_matrices(np.asarray(groundtruth_pose_at(seq, t))[None])[0]
        pose = gt.copy()
        pose[:3, 3] += np.array([0.004, -0.002, 0.0]) * (n > 0)
        edges = keyframe_edges(frame, CONFIG, seed=n, intr=seq.intrinsics)
        before = [kf.pose.copy() for kf in lm.window]
        out, stats = lm.add_keyframe(pose, edges, frame)
        steps.append({"gt": gt, "pose_in": pose, "pose_out": out, "stats": stats, "before": before,
                      "prior": None if lm.prior is None else jax.device_get(lm.prior),
                      "active": [int(kf.active.sum()) for kf in lm.window],
                      "track": [int(kf.track.max()) for kf in lm.window]})
    return lm, steps


def test_window_fills_then_slides(driven):
    lm, steps = driven
    assert [len(s["active"]) for s in steps] == [1, 2, 3, 3, 3]
    assert [s["stats"]["refined"] for s in steps] == [False, False, True, True, True]
    assert steps[0]["prior"] is None and steps[2]["prior"] is None  # nothing dropped yet
    for s in steps[3:]:
        H = np.asarray(s["prior"].H)
        assert H.shape == (6 * 3 + 4,) * 2  # in the layout of the window after the slide
        np.testing.assert_allclose(H, H.T, atol=1e-6 * np.abs(H).max())
        assert np.linalg.eigvalsh(H.astype(np.float64)).min() > -1e-4 * np.abs(H).max()
        assert np.all(np.isfinite(np.asarray(s["prior"].b)))


def test_edges_are_activated_and_tracked(driven):
    _, steps = driven
    # a keyframe's edges become active once a later keyframe sees them; the newest has none
    # (about half the edges of these desk frames sit within 5 px of a depth step: 10+ each)
    for s in steps[1:]:
        assert s["active"][-1] == 0 and all(a >= 10 for a in s["active"][:-1]), s["active"]
        assert max(s["track"][:-1]) >= 1


def test_only_edges_on_continuous_depth_are_activated(driven):
    """Edges on a depth step (real frames have them: the desk's and the monitor's outlines)
    are kept as tracked edges but never activated."""
    lm, _ = driven
    for kf in lm.window:
        assert not np.any(kf.active & ~kf.activatable)
        assert np.all(kf.activatable <= kf.valid)
    assert sum(int((kf.valid & ~kf.activatable).sum()) for kf in lm.window) > 20


def test_depth_continuous_passes_slanted_planes_and_fails_steps_and_holes():
    h, w = 60, 80
    vv, uu = np.mgrid[0:h, 0:w].astype(np.float64)
    rng = np.random.default_rng(0)
    angle = rng.uniform(0, 2 * np.pi, 40)
    grad = np.stack([np.cos(angle), np.sin(angle)])
    uv = np.stack([rng.integers(10, w - 10, 40), rng.integers(10, h - 10, 40)]).astype(float)
    # a steep plane (inverse depth affine in the pixels: 0.33 to 1.6 m across the image)
    plane = 1.0 / (0.6 + 0.02 * uu + 0.01 * vv)
    for reach in (3, 5):
        assert depth_continuous(plane.astype(np.float32), uv, grad, max_step=0.0105,
                                reach=reach).all()
    # a 2 cm step at 1 m (0.0198 / m in inverse depth) at column 40: edges within 3 px of
    # it along their gradient fail, those farther away pass
    step = np.where(uu < 40, 1.0, 1.02).astype(np.float32)
    uv_x = np.array([[37.0, 38.0, 39.0, 40.0, 42.0, 43.0, 30.0, 50.0], [30.0] * 8])
    across = np.tile([[1.0], [0.0]], 8)
    got = depth_continuous(step, uv_x, across, max_step=0.0105, reach=3)
    np.testing.assert_array_equal(got, [False, False, False, False, False, True, True, True])
    # with a reach of 5 px, the edge 3 px past the step fails too, the one 10 px away passes
    got = depth_continuous(step, uv_x, across, max_step=0.0105, reach=5)
    np.testing.assert_array_equal(got, [False, False, False, False, False, False, True, True])
    # the same edges with gradients along the step (the depth is constant along it) pass
    along = np.tile([[0.0], [1.0]], 8)
    assert depth_continuous(step, uv_x, along, max_step=0.0105, reach=5).all()
    # a missing depth pixel within reach, or the image border, fails the edge
    holes = plane.astype(np.float32).copy()
    holes[30, 32] = 0.0
    holes[30, 52] = np.nan
    edges = np.array([[30.0, 50.0, 1.0, 30.0], [30.0, 30.0, 30.0, 20.0]])
    got = depth_continuous(holes, edges, np.tile([[1.0], [0.0]], 4), max_step=0.0105, reach=3)
    np.testing.assert_array_equal(got, [False, False, False, True])


def test_refinement_moves_poses_a_little_and_keeps_the_gauge(driven):
    lm, steps = driven
    for s in steps[2:]:
        moved = np.linalg.norm(s["pose_out"][:3, 3] - s["pose_in"][:3, 3])
        assert 0 < moved < 0.02 and np.all(np.isfinite(s["pose_out"]))
        assert s["stats"]["inliers"] > 50  # residuals of the active edges in the window
    # intrinsics stay the calibration's unless mapping_intrinsics is on
    np.testing.assert_array_equal(lm.intrinsics, np.asarray(
        load_sequence(BUNDLED_CLIP).intrinsics, np.float32))


def test_refinement_keeps_the_oldest_keyframe_fixed():
    """The gauge: a window refinement leaves the oldest keyframe's pose as it was."""
    seq = load_sequence(BUNDLED_CLIP)
    lm = SlidingWindow(CONFIG, np.asarray(seq.intrinsics), (seq.height, seq.width))
    for n, i in enumerate((0, 3, 6)):
        frame = preprocess(*seq.load_frame(i), CONFIG)
        gt = poses7_to_matrices(np.asarray(
            groundtruth_pose_at(seq, float(seq.timestamps[i])))[None])[0]
        if n == 0:
            oldest = gt.copy()
        lm.add_keyframe(gt, keyframe_edges(frame, CONFIG, seed=n, intr=seq.intrinsics), frame)
    np.testing.assert_array_equal(lm.window[0].pose, oldest)


def test_tracker_reports_mapping_time_and_off_switch():
    seq = load_sequence(BUNDLED_CLIP)
    on = run_sequence(seq, CONFIG.replace(window_size=3), progress=False, max_frames=6)
    off = run_sequence(seq, CONFIG.replace(mapping=False), progress=False, max_frames=6)
    kf_on = [r for r in on.results if r.keyframe]
    assert kf_on and all(r.mapping_ms is not None and r.mapping_ms > 0 for r in kf_on)
    assert all(r.mapping_ms is None for r in off.results)
    stats = summarise(on, seq)
    assert "mapping_ms" in stats and np.all(np.isfinite(on.poses))


def test_fields_per_keyframe_equal_stacked_fields(driven):
    """The window passes each keyframe's distance field and edge map as they are (a tuple,
    no stacked copy); the normal equations must be those of the stacked arrays, bit for bit,
    and dropping a keyframe must drop its tuple entries."""
    import jax.numpy as jnp

    from edgevo_jax.window.problem import normal_equations, remove_keyframe

    lm, _ = driven
    per_kf, _ = lm._problem()
    assert isinstance(per_kf.fields, tuple) and isinstance(per_kf.edge_map, tuple)
    stacked = per_kf._replace(
        fields=jnp.stack(per_kf.fields),
        edge_map=jax.tree.map(lambda *xs: jnp.stack(xs), *per_kf.edge_map))
    ne = jax.jit(normal_equations, static_argnames="config")
    a = jax.device_get(ne(per_kf, config=lm._mcfg))
    b = jax.device_get(ne(stacked, config=lm._mcfg))
    assert int(a.count) > 50  # real residuals pass the gate and the gradient test
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(x, y)
    rest = remove_keyframe(per_kf, 1)
    assert rest.fields == (per_kf.fields[0], *per_kf.fields[2:])
    assert rest.edge_map == (per_kf.edge_map[0], *per_kf.edge_map[2:])
    np.testing.assert_array_equal(rest.uv, np.delete(np.asarray(per_kf.uv), 1, axis=0))


def test_grid_of_huber_radii_shares_one_compilation():
    """The window's Huber radius, gate and eta are traced (derive.split_window): two
    configurations that differ in them only give the same static part, so one compiled
    program serves both."""
    from edgevo_jax.derive import split_window, window_config

    a = split_window(window_config(Config(huber_delta=(0.5,) * 3)))
    b = split_window(window_config(Config(huber_delta=(2.0,) * 3, max_residual=(4.0,) * 3)))
    assert a[0] == b[0] and hash(a[0]) == hash(b[0])
    assert float(a[1][0]) == 0.5 and float(b[1][0]) == 2.0 and float(b[1][1]) == 4.0
