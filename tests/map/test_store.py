"""The keyframe map (``map.store``): predicted overlap is the share of a keyframe's edges a
camera sees; queries return anchored keyframes only, best first, without those left out;
covisibility is taken both ways; the cap refuses keyframes and says so."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from edgevo_jax.camera import Intrinsics
from edgevo_jax.frontend.selection import KeyframeEdges
from edgevo_jax.geometry import exp_np
from edgevo_jax.map import KeyframeMap, MapFullWarning, MapKeyframe, edge_points
from edgevo_jax.map import predicted_overlap as overlap
from edgevo_jax.map.recognition import NUM_FERNS

INTR = Intrinsics(525.0, 525.0, 319.5, 239.5)
SHAPE = (480, 640)


def edges(n: int = 400, seed: int = 0, depth: float = 2.0) -> KeyframeEdges:
    rng = np.random.default_rng(seed)
    uv = np.stack([rng.uniform(0, 639, n), rng.uniform(0, 479, n)]).astype(np.float32)
    rho = np.full(n, 1.0 / depth, np.float32)
    valid = np.ones(n, bool)
    valid[-20:] = False  # padding slots
    return KeyframeEdges(uv, rho, np.zeros((2, n), np.float32), valid)


def entry(key: int, pose=None, *, code_seed: int = 0, anchored: bool = True) -> MapKeyframe:
    e = edges(seed=key)
    code = np.random.default_rng(code_seed).integers(0, 16, NUM_FERNS).astype(np.uint8)
    return MapKeyframe(key, float(key), np.eye(4) if pose is None else pose, e,
                       edge_points(e, INTR), None, code, anchored=anchored)


def turn(deg: float, axis: int = 1) -> np.ndarray:
    xi = np.zeros(6)
    xi[3 + axis] = np.radians(deg)
    return exp_np(xi)


def test_edge_points_back_project_the_valid_edges():
    e = edges()
    p = edge_points(e, INTR)
    assert p.shape == (3, 380)
    u = INTR.fx * p[0] / p[2] + INTR.cx
    np.testing.assert_allclose(u, e.uv[0, :380], atol=1e-3)
    np.testing.assert_allclose(p[2], 2.0, rtol=1e-6)


def test_predicted_overlap_is_the_share_of_edges_in_view():
    p = edge_points(edges(), INTR)
    assert overlap(p, np.eye(4), INTR, SHAPE) == 1.0
    assert overlap(p, turn(180.0), INTR, SHAPE) == 0.0  # all behind the camera
    half = overlap(p, turn(-31.0), INTR, SHAPE)  # turned by half the field of view
    assert 0.3 < half < 0.7
    assert overlap(np.zeros((3, 0), np.float32), np.eye(4), INTR, SHAPE) == 0.0


def test_queries_return_anchored_keyframes_best_first_and_leave_out_what_is_asked():
    m = KeyframeMap(INTR, SHAPE, max_keyframes=10)
    for key, pose, seed in ((0, np.eye(4), 1), (1, turn(20.0), 2), (2, turn(90.0), 3)):
        m.add(entry(key, pose, code_seed=seed))
    m.add(entry(3, np.eye(4), code_seed=1, anchored=False))  # a guess: never returned
    query = entry(9, code_seed=1).code
    got = m.recognise(query, k=3)
    assert [c.id for c in got][:1] == [0] and got[0].score == 1.0
    assert 3 not in [c.id for c in got]
    assert [c.id for c in m.recognise(query, k=3, exclude=[0])][0] != 0
    near = m.overlapping(turn(5.0), k=3, min_overlap=0.3)
    assert [c.id for c in near] == [0, 1]  # 90 degrees away is not seen; best first
    assert near[0].score > near[1].score
    assert m.overlapping(turn(5.0), k=3, min_overlap=0.3, exclude=[0, 1]) == []


def test_covisibility_is_symmetric_and_anchoring_moves_a_guess_into_the_map():
    m = KeyframeMap(INTR, SHAPE, max_keyframes=10)
    m.add(entry(0))
    m.add(entry(1, turn(10.0)))
    m.add(entry(2, turn(120.0)))
    assert m.covisible(0)[1] == m.covisible(1)[0] > 0.5
    assert 2 not in m.covisible(0)
    shift = np.eye(4)
    shift[0, 3] = 5.0  # a guess 5 m off, made while lost
    m.add(entry(3, shift @ turn(12.0), anchored=False))
    assert m.covisible(3) == {} and 3 not in [c.id for c in m.recognise(entry(3).code, k=5)]
    back = np.linalg.inv(shift)
    m.anchor([3], back)
    np.testing.assert_allclose(m[3].pose, turn(12.0), atol=1e-12)
    assert m[3].anchored and m.covisible(3)[1] > 0.5


def test_the_cap_refuses_keyframes_and_says_so_once():
    m = KeyframeMap(INTR, SHAPE, max_keyframes=2)
    assert m.add(entry(0)) and m.add(entry(1))
    with pytest.warns(MapFullWarning, match="keyframe 2 and later"):
        assert not m.add(entry(2))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert not m.add(entry(3))
    assert len(m) == 2 and m.full_at == 2
    per = m[0].nbytes
    assert per > 380 * 3 * 4 and m.nbytes >= 2 * per


def test_bad_keyframes_are_refused_by_name():
    m = KeyframeMap(INTR, SHAPE, max_keyframes=3)
    m.add(entry(0))
    with pytest.raises(ValueError, match="in the map already"):
        m.add(entry(0))
    with pytest.raises(ValueError, match="fern"):
        m.add(MapKeyframe(5, 0.0, np.eye(4), edges(), np.zeros((3, 0), np.float32), None,
                          np.zeros(3, np.uint8)))
    with pytest.raises(ValueError, match="max_keyframes"):
        KeyframeMap(INTR, SHAPE, max_keyframes=0)
