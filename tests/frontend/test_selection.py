"""Edge selection: Proposition 1's 1/2 bound, partitions, determinism, the logdet gains."""

from __future__ import annotations

import itertools
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from edgevo_jax import Config
from edgevo_jax.cli import BUNDLED_CLIP
from edgevo_jax.datasets import load_sequence
from edgevo_jax.frontend.selection import (
    _add_edge,
    candidates,
    depth_discontinuity,
    logdet_gains,
    partition_greedy,
    partition_ids,
    partition_order,
    select,
)
from edgevo_jax.image.preprocess import preprocess

LAM = 1.0


def objective(J: np.ndarray, S) -> float:
    """f(S) = logdet(lam I + sum_{e in S} J_e J_e^T) - logdet(lam I): monotone submodular."""
    A = LAM * np.eye(6) + sum((np.outer(J[:, e], J[:, e]) for e in S), np.zeros((6, 6)))
    return float(np.linalg.slogdet(A)[1] - 6 * np.log(LAM))


@st.composite
def matroid_instances(draw):
    sizes = draw(st.lists(st.integers(1, 3), min_size=2, max_size=4))
    n = sum(sizes)
    seed = draw(st.integers(0, 2**31 - 1))
    scale = draw(st.sampled_from([0.3, 1.0, 5.0]))
    rng = np.random.default_rng(seed)
    J = rng.normal(size=(6, n)) * scale
    counts = np.asarray(sizes, np.int32)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int32)
    return J, starts, counts, seed


@given(matroid_instances())
@settings(max_examples=40, deadline=None)
def test_partition_greedy_reaches_half_the_brute_force_optimum(instance):
    """EdgeVO Proposition 1: under a partition matroid the greedy gets >= OPT / 2."""
    J, starts, counts, seed = instance
    with jax.enable_x64(True):
        idx, taken = partition_greedy(
            jnp.asarray(J), jnp.ones(J.shape[1]), jnp.ones(J.shape[1], bool),
            jnp.asarray(starts), jnp.asarray(counts), jax.random.key(seed),
            num_edges=len(starts), lam=LAM, max_per_cell=3)
        chosen = np.asarray(idx)[np.asarray(taken)]
    parts = [np.arange(s, s + c) for s, c in zip(starts, counts, strict=True)]
    opt = max(objective(J, S) for S in itertools.product(*parts))
    assert len(chosen) == len(parts)
    assert objective(J, chosen) >= 0.5 * opt - 1e-9
    # at most one edge per partition
    owner = {int(e): i for i, row in enumerate(parts) for e in row}
    assert len({owner[int(e)] for e in chosen}) == len(chosen)


def test_batched_gains_equal_one_at_a_time_and_the_determinant_ratio():
    with jax.enable_x64(True):
        rng = np.random.default_rng(0)
        B = rng.normal(size=(6, 6))
        A = B @ B.T + np.eye(6)
        J = rng.normal(size=(6, 50)) * 3.0
        batched = logdet_gains(jnp.asarray(J), jnp.asarray(np.linalg.inv(A)),
                               jnp.asarray(np.linalg.slogdet(A)[1]))
        one_by_one = [np.linalg.slogdet(A + np.outer(J[:, e], J[:, e]))[1] for e in range(50)]
        np.testing.assert_allclose(batched, one_by_one, rtol=1e-10)
        ratio = [np.log(np.linalg.det(A + np.outer(J[:, e], J[:, e])) / np.linalg.det(A))
                 for e in range(50)]
        np.testing.assert_allclose(batched - np.linalg.slogdet(A)[1], ratio, rtol=1e-9)


def test_sherman_morrison_update_keeps_the_inverse_and_logdet():
    with jax.enable_x64(True):
        rng = np.random.default_rng(1)
        A_inv, logdet = jnp.eye(6) / LAM, jnp.asarray(6 * np.log(LAM))
        A = LAM * np.eye(6)
        for _ in range(20):
            j = rng.normal(size=6) * 2.0
            A_inv, logdet = _add_edge(A_inv, logdet, jnp.asarray(j))
            A = A + np.outer(j, j)
        np.testing.assert_allclose(A_inv, np.linalg.inv(A), rtol=1e-8, atol=1e-12)
        np.testing.assert_allclose(logdet, np.linalg.slogdet(A)[1], rtol=1e-10)


def test_partition_order_holds_each_point_once_in_its_cell():
    rng = np.random.default_rng(2)
    uv = np.stack([rng.uniform(0, 63, 400), rng.uniform(0, 47, 400)])
    cell_id, num_cells = partition_ids(uv, 64, 48, 8)
    order, starts, counts = partition_order(cell_id, 16, seed=0)
    assert sorted(order.tolist()) == list(range(400))  # a permutation
    nonempty = np.unique(cell_id)
    assert starts.size == nonempty.size and counts.sum() == 400
    for s, c, cell in zip(starts, counts, nonempty, strict=True):
        assert np.all(cell_id[order[s:s + c]] == cell)
        assert c == int(np.sum(cell_id == cell))


def test_partition_order_shuffles_crowded_cells_by_seed():
    cell_id = np.repeat(np.arange(3), 40)  # 40 points per cell, 16 compete
    a = partition_order(cell_id, 16, seed=0)[0]
    b = partition_order(cell_id, 16, seed=1)[0]
    assert not np.array_equal(a[:16], b[:16])
    np.testing.assert_array_equal(a, partition_order(cell_id, 16, seed=0)[0])


def test_random_order_is_a_permutation_and_usable_ones_come_first():
    from edgevo_jax.frontend.selection import first_usable, random_order

    for n in (1, 5, 64, 1000):
        perm = np.asarray(random_order(jax.random.key(n), n))
        assert sorted(perm.tolist()) == list(range(perm.size)) and perm.size >= n
    perms = {tuple(np.asarray(random_order(jax.random.key(k), 64))) for k in range(20)}
    assert len(perms) == 20  # the key matters
    usable = jnp.asarray(np.arange(10) % 3 == 0)
    perm = jnp.asarray([7, 12, 3, 0, 9, 1, 6, 15, 2, 4, 5, 8, 10, 11, 13, 14])
    first, live = first_usable(perm, usable, 6)
    np.testing.assert_array_equal(np.asarray(first)[np.asarray(live)], [3, 0, 9, 6])
    assert np.asarray(live).tolist() == [True] * 4 + [False] * 2


@pytest.fixture(scope="module")
def real_candidates():
    seq = load_sequence(BUNDLED_CLIP)
    rgb, depth = seq.load_frame(0)
    frame = preprocess(rgb, depth, Config())
    return seq, candidates(frame, Config()), frame.shape


def _select(real, **overrides):
    seq, cands, (h, w) = real
    config = Config().replace(**overrides)
    return select(cands, config, T_prior=np.eye(4), intr=seq.intrinsics, width=w, height=h,
                  seed=config.seed)


@pytest.mark.parametrize("mode", ["spg", "greedy", "random"])
def test_same_seed_same_selection_other_seed_other_selection(real_candidates, mode):
    a = _select(real_candidates, selection=mode, seed=3)
    b = _select(real_candidates, selection=mode, seed=3)
    c = _select(real_candidates, selection=mode, seed=4)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)
    assert len(a) == Config().num_edges and len(set(a.tolist())) == len(a)


def test_spg_takes_one_edge_per_partition_on_a_real_frame(real_candidates):
    seq, cands, (h, w) = real_candidates
    for cell in (4, 16):
        idx = _select(real_candidates, cell_size=cell)
        cell_id, _ = partition_ids(cands.uv[:, idx], w, h, cell)
        assert len(set(cell_id.tolist())) == len(idx)


def test_all_keeps_every_culled_edge(real_candidates):
    _, cands, _ = real_candidates
    np.testing.assert_array_equal(_select(real_candidates, selection="all"),
                                  np.arange(cands.rho.size))


def test_spg_spreads_wider_than_plain_greedy(real_candidates):
    """The point of partitions (paper, Fig. 5): plain greedy clusters, partitions spread."""
    seq, cands, (h, w) = real_candidates
    coverage = {}
    for mode in ("spg", "greedy"):
        uv = cands.uv[:, _select(real_candidates, selection=mode, cell_size=16)]
        cell_id, _ = partition_ids(uv, w, h, 32)
        coverage[mode] = len(set(cell_id.tolist()))
    assert coverage["spg"] > coverage["greedy"]


def test_depth_discontinuity_measures_depth_steps_and_skips_missing_depth():
    """(max - min) / z over the 5 x 5 window: 0 on a flat surface, the step's size over the
    edge's depth at a step, missing depth (0, negative, NaN, inf) left out, huge values
    clamped to 1000, no warnings; zeros without a depth image."""
    d = np.full((20, 20), 1.0, np.float32)
    d[:, 10:] = 2.0
    d[0, 0], d[1, 1], d[2, 2], d[15, 2] = np.inf, np.nan, -1.0, 0.0
    d[18, 18] = 3e38
    uv = np.array([[4.0, 9.0, 10.0, 15.0, 1.0, 2.0, 17.0],
                   [5.0, 5.0, 5.0, 5.0, 1.0, 15.0, 17.0]])
    z = np.array([1.0, 1.0, 2.0, 2.0, 1.0, 1.0, 2.0], np.float32)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        out = depth_discontinuity(d, uv, z)
    np.testing.assert_allclose(out, [0.0, 1.0, 0.5, 0.0, 0.0, 0.0, 1000.0], atol=1e-6)
    assert out.dtype == np.float32
    np.testing.assert_array_equal(depth_discontinuity(None, uv, z), np.zeros(7, np.float32))


def test_spg_choice_is_the_same_in_the_merged_candidate_buffer(monkeypatch):
    """spg pads 1025-4096 candidates to one buffer of 4096 (``candidate_size``: one program
    where there were two): the partitions are visited in the same random order, so the
    edges chosen are those of the 2048 buffer, bit for bit; greedy keeps its own buckets."""
    from edgevo_jax import Intrinsics
    from edgevo_jax.frontend import selection

    rng = np.random.default_rng(7)
    n = 1500
    angle = rng.uniform(0, 2 * np.pi, n)
    cands = selection.Candidates(
        uv=np.stack([rng.uniform(0, 639, n), rng.uniform(0, 479, n)]).astype(np.float32),
        rho=rng.uniform(0.2, 1.0, n).astype(np.float32),
        grad=np.stack([np.cos(angle), np.sin(angle)]).astype(np.float32),
        mag=rng.uniform(20, 200, n).astype(np.float32))
    config = Config()
    kw = {"T_prior": np.eye(4), "intr": Intrinsics(525.0, 525.0, 319.5, 239.5),
          "width": 640, "height": 480, "seed": 3}
    assert selection.candidate_size(n, config) == 4096
    assert selection.candidate_size(n, config.replace(selection="greedy")) == 2048
    merged = select(cands, config, **kw)
    monkeypatch.setattr(selection, "candidate_size",
                        lambda m, c: selection._bucket(m, c.max_edges))  # the 2048 buffer
    alone = select(cands, config, **kw)
    assert merged.size == config.num_edges
    np.testing.assert_array_equal(merged, alone)
