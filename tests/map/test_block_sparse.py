"""The pose graph's block-sparse systems (``map.block_sparse``): the host LU, and the
Cholesky of symmetric ones, solve what the blocks say (against a dense solve of the same
matrix), on the movable nodes only, with padding edges ignored and parallel edges summed, in
float32 and float64, under jit and vmap, the same bits every call; the matrix-vector product
and the PCG agree with it."""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from edgevo_jax.map import block_sparse as bs


def random_blocks(seed: int, n: int = 7, dtype=np.float64) -> tuple[bs.Blocks, np.ndarray]:
    """A symmetric positive definite block matrix on n nodes: a chain, a loop, a doubled edge
    and two padding edges (joining nodes 0 and 2 with garbage blocks); node 3 is not movable.
    Also its dense (6n, 6n) form over all nodes (identity rows for node 3)."""
    rng = np.random.default_rng(seed)
    pairs = [(k, k + 1) for k in range(n - 1)] + [(0, n - 1), (1, 2), (0, 2), (0, 2)]
    valid = np.array([True] * (n + 1) + [False, False])
    movable = np.ones(n, bool)
    movable[3] = False
    dense = np.zeros((6 * n, 6 * n))
    D = np.zeros((n, 6, 6))
    U, L = np.zeros((len(pairs), 6, 6)), np.zeros((len(pairs), 6, 6))
    for e, (a, b) in enumerate(pairs):
        G = rng.normal(size=(6, 6))
        M = G @ G.T + np.eye(6)
        if valid[e]:
            D[a] += M
            D[b] += M
            U[e] = L[e] = -M
            for r, c, blk in ((a, a, M), (b, b, M), (a, b, -M), (b, a, -M)):
                dense[6 * r:6 * r + 6, 6 * c:6 * c + 6] += blk
        else:
            U[e], L[e] = 1e3 * G, -1e3 * G.T  # must not count
    D += 0.1 * np.eye(6)
    dense += 0.1 * np.eye(6 * n)
    keep = np.repeat(movable, 6)
    dense[~keep] = 0.0
    dense[:, ~keep] = 0.0
    dense[~keep, ~keep] = 1.0
    i, j = (np.array(v, np.int32) for v in zip(*pairs, strict=True))
    H = bs.Blocks(*(jnp.asarray(a, dtype) for a in (D, U, L)), jnp.asarray(i), jnp.asarray(j),
                  jnp.asarray(valid), jnp.asarray(movable))
    return H, dense


def test_direct_solves_the_blocks_on_the_movable_nodes():
    with jax.enable_x64(True):
        H, dense = random_blocks(0)
        b = np.random.default_rng(1).normal(size=(7, 6))
        x = np.asarray(jax.jit(bs.direct)(H, jnp.asarray(b)))
        np.testing.assert_allclose(x.ravel(), np.linalg.solve(dense, b.ravel()), rtol=1e-10,
                                   atol=1e-12)
        np.testing.assert_array_equal(x[3], b[3])  # not movable: its right-hand side
        np.testing.assert_allclose(np.asarray(bs.matvec(H, jnp.asarray(x))), b, atol=1e-10)
        # the product is the dense matrix's
        np.testing.assert_allclose(np.asarray(bs.matvec(H, jnp.asarray(b))).ravel(),
                                   dense @ b.ravel(), rtol=1e-12)


def test_direct_in_float32_and_on_a_zero_right_hand_side():
    H, dense = random_blocks(2, dtype=np.float32)
    b = np.random.default_rng(3).normal(size=(7, 6)).astype(np.float32)
    x = bs.direct(H, jnp.asarray(b))
    assert x.dtype == jnp.float32
    np.testing.assert_allclose(np.asarray(x).ravel(), np.linalg.solve(dense, b.ravel()),
                               rtol=1e-4, atol=1e-5)
    np.testing.assert_array_equal(np.asarray(bs.direct(H, jnp.zeros((7, 6)))), 0.0)


def test_transpose_solves_the_transposed_system():
    with jax.enable_x64(True):
        H, _ = random_blocks(4)
        rng = np.random.default_rng(5)
        H = H._replace(U=H.U + 0.1 * rng.normal(size=H.U.shape))  # no longer symmetric
        b = jnp.asarray(rng.normal(size=(7, 6)))
        x = bs.direct(H.transpose(), b)
        # x^T H y = b^T y for every y (on the movable nodes)
        y = jnp.where(H.movable[:, None], jnp.asarray(rng.normal(size=(7, 6))), 0.0)
        np.testing.assert_allclose(float(jnp.sum(jnp.where(H.movable[:, None], x, 0.0)
                                                 * bs.matvec(H, y))),
                                   float(jnp.sum(jnp.where(H.movable[:, None], b, 0.0) * y)),
                                   rtol=1e-10)


def test_vmap_solves_each_system_and_calls_give_the_same_bits():
    with jax.enable_x64(True):
        systems = [random_blocks(s) for s in (6, 7)]
        H = jax.tree.map(lambda *a: jnp.stack(a), *(h for h, _ in systems))
        b = jnp.asarray(np.random.default_rng(8).normal(size=(2, 7, 6)))
        both = jax.jit(jax.vmap(bs.direct))(H, b)
        for k, (h, _) in enumerate(systems):
            np.testing.assert_array_equal(np.asarray(both[k]), np.asarray(bs.direct(h, b[k])))
        again = jax.jit(jax.vmap(bs.direct))(H, b)
        np.testing.assert_array_equal(np.asarray(again), np.asarray(both))


def test_pcg_agrees_with_the_direct_solve():
    with jax.enable_x64(True):
        H, _ = random_blocks(9)
        b = jnp.where(H.movable[:, None], jnp.asarray(np.random.default_rng(10).normal(
            size=(7, 6))), 0.0)
        x = bs.pcg(lambda v: bs.matvec(H, v), b, bs.block_jacobi(H.D, H.movable), 1e-13, 500)
        np.testing.assert_allclose(np.asarray(x), np.asarray(bs.direct(H, b)), atol=1e-9)


def test_an_exactly_singular_system_gives_nan_on_its_movable_nodes():
    with jax.enable_x64(True):
        H, _ = random_blocks(11)
        H = H._replace(D=H.D.at[5].set(0.0), U=jnp.zeros_like(H.U), L=jnp.zeros_like(H.L))
        x = np.asarray(bs.direct(H, jnp.ones((7, 6))))
        assert np.isnan(x[np.asarray(H.movable)]).all() and (x[3] == 1.0).all()


def test_symmetric_solves_by_cholesky_agree_with_the_dense_solve_and_reuse_the_analysis():
    with jax.enable_x64(True):
        H, dense = random_blocks(12)
        rng = np.random.default_rng(13)
        bs._ANALYSES.clear()
        for _ in range(2):  # the second system: same pattern, new values, one analysis
            b = rng.normal(size=(7, 6))
            x = np.asarray(jax.jit(partial(bs.direct, symmetric=True))(H, jnp.asarray(b)))
            np.testing.assert_allclose(x.ravel(), np.linalg.solve(dense, b.ravel()),
                                       rtol=1e-10, atol=1e-12)
            np.testing.assert_array_equal(x[3], b[3])
            H = H._replace(D=H.D * 2.0, U=H.U * 2.0, L=H.L * 2.0)
            dense = 2.0 * dense
            dense[18:24, 18:24] = np.eye(6)  # node 3: identity rows stay identity
        assert len(bs._ANALYSES) == 1
        again = np.asarray(bs.direct(H, jnp.asarray(b), symmetric=True))
        np.testing.assert_array_equal(again, np.asarray(bs.direct(H, jnp.asarray(b),
                                                                  symmetric=True)))


def test_symmetric_solves_take_the_symmetric_part_and_fall_back_where_not_definite():
    with jax.enable_x64(True):
        H, dense = random_blocks(14)
        rng = np.random.default_rng(15)
        skew = 1e-3 * rng.normal(size=H.D.shape)
        bent = H._replace(D=H.D + skew)  # 0.5 (H + H^T) is the original H
        b = rng.normal(size=(7, 6))
        x = np.asarray(bs.direct(bent, jnp.asarray(b), symmetric=True))
        sym = dense.copy()
        for k in range(7):
            if k != 3:
                sym[6 * k:6 * k + 6, 6 * k:6 * k + 6] += 0.5 * (skew[k] + skew[k].T)
        np.testing.assert_allclose(x.ravel(), np.linalg.solve(sym, b.ravel()), rtol=1e-9)
        # indefinite (a diagonal block negated): no Cholesky, the LU still solves it
        flipped = H._replace(D=H.D.at[5].multiply(-1.0))
        dense_f = dense.copy()
        dense_f[30:36, 30:36] *= -1.0
        x = np.asarray(bs.direct(flipped, jnp.asarray(b), symmetric=True))
        np.testing.assert_allclose(x.ravel(), np.linalg.solve(dense_f, b.ravel()), rtol=1e-8)
