"""The pose graph's linear systems (``pose_graph``): block-sparse matrices of 6x6 blocks, one
block row and column per node, and their two solvers.

A ``Blocks`` matrix H (6N, 6N) holds its diagonal blocks D (N, 6, 6) and, per edge (i, j),
the block U at (row i, column j) and L at (row j, column i); edges sharing a pair add up.
Only the ``movable`` nodes' rows and columns count: the system is solved on them, and a node
off ``movable`` keeps its right-hand side (identity rows and columns: the caller's zeros
stay zeros). Invalid (padding) edges are ignored.

- ``direct``: SciPy's sparse LU (SuperLU, a fill-reducing minimum-degree ordering of
  H + H^T, diagonal pivots preferred) of the movable part, on the host in float64 through
  ``jax.pure_callback``; ``jax.vmap`` solves the graphs of a batch one after the other.
  Deterministic: SuperLU is sequential, so the same inputs give the same bits.
- ``pcg``: preconditioned conjugate gradients of an operator (symmetric positive definite),
  on the device, with the 6x6 block-Jacobi preconditioner ``block_jacobi``: no host round
  trip, but its iterations grow with the graph (a chain of N nodes asks O(N)).
"""

from __future__ import annotations

from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np


class Blocks(NamedTuple):
    """A block-sparse H (module doc): D (N, 6, 6) its diagonal blocks; U, L (E, 6, 6) edge
    e's blocks at (i_e, j_e) and (j_e, i_e); i, j (E,) int32 the edges' nodes; valid (E,)
    bool (False: padding, ignored); movable (N,) bool (the nodes solved for)."""

    D: jnp.ndarray
    U: jnp.ndarray
    L: jnp.ndarray
    i: jnp.ndarray
    j: jnp.ndarray
    valid: jnp.ndarray
    movable: jnp.ndarray

    def transpose(self) -> Blocks:
        """H^T: each block transposed, U and L swapped."""
        t = lambda a: jnp.swapaxes(a, -1, -2)  # noqa: E731
        return self._replace(D=t(self.D), U=t(self.L), L=t(self.U))


def _csc(D, U, L, i, j, valid, movable):
    """The movable part of H as a SciPy CSC matrix (6m, 6m) in float64, and the movable
    nodes (m,) in index order (host arrays in, module doc)."""
    import scipy.sparse

    nodes = np.flatnonzero(movable)
    m = nodes.size
    slot = np.cumsum(movable) - 1  # a movable node's block row
    keep = valid & movable[i] & movable[j]
    bi, bj = slot[i[keep]], slot[j[keep]]
    blocks = np.concatenate([D[nodes], U[keep], L[keep]]).astype(np.float64)
    brow = np.concatenate([np.arange(m), bi, bj])
    bcol = np.concatenate([np.arange(m), bj, bi])
    a = np.arange(6)
    rows = np.broadcast_to(6 * brow[:, None, None] + a[None, :, None], blocks.shape)
    cols = np.broadcast_to(6 * bcol[:, None, None] + a[None, None, :], blocks.shape)
    H = scipy.sparse.coo_matrix((blocks.ravel(), (rows.ravel(), cols.ravel())),
                                shape=(6 * m, 6 * m)).tocsc()  # duplicates summed
    return H, nodes


def _host_solve(D, U, L, i, j, valid, movable, b):
    """x (N, 6) with H x = b on the movable nodes, x = b elsewhere (module doc), by SuperLU
    in float64 (x of b's dtype); NaN on the movable nodes where H's movable part is
    exactly singular. Host arrays in and out."""
    import scipy.sparse.linalg

    x = np.array(b, copy=True)
    nodes = np.flatnonzero(movable)
    if nodes.size and b[nodes].any():  # (a zero right-hand side: x = 0, nothing to factor)
        H, nodes = _csc(D, U, L, i, j, valid, movable)
        try:
            lu = scipy.sparse.linalg.splu(H, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                                          options=dict(SymmetricMode=True))
            x[nodes] = lu.solve(b[nodes].astype(np.float64).ravel()).reshape(-1, 6)
        except RuntimeError:  # exactly singular: no solution to give
            x[nodes] = np.nan
    return x


def _bits(a: jnp.ndarray) -> jnp.ndarray:
    """A float array's bits as uint32 (float64: a trailing axis of 2): the callback's thread
    may not share a ``jax.enable_x64`` context, and JAX would cast float64 down there."""
    return jax.lax.bitcast_convert_type(a, jnp.uint32)


def _from_bits(dtype: np.dtype, *args):
    """``_host_solve`` on the floats that ``_bits`` encoded (D, U, L and b), its x as bits."""
    D, U, L, i, j, valid, movable, b = (np.asarray(a) for a in args)
    D, U, L, b = (np.ascontiguousarray(a).view(dtype).reshape(a.shape[:-1] if
                  dtype == np.float64 else a.shape) for a in (D, U, L, b))
    x = _host_solve(D, U, L, i, j, valid, movable, b)
    return x.astype(dtype).view(np.uint32).reshape(args[-1].shape)


def direct(H: Blocks, b: jnp.ndarray) -> jnp.ndarray:
    """x (N, 6) with H x = b on H's movable nodes (b's rows elsewhere), by a sparse LU on the
    host (module doc); of b's dtype (float32 or float64, H's too). Traceable (a
    ``jax.pure_callback``), vmap-able (one graph after another); not differentiable (callers
    give their own derivative)."""
    bits = _bits(b)
    args = (*(_bits(a) for a in H[:3]), *H[3:], bits)
    out = jax.ShapeDtypeStruct(bits.shape, bits.dtype)
    x = jax.pure_callback(partial(_from_bits, np.dtype(b.dtype)), out, *args,
                          vmap_method="sequential")
    return jax.lax.bitcast_convert_type(x, b.dtype)


def matvec(H: Blocks, v: jnp.ndarray) -> jnp.ndarray:
    """H v (N, 6) on the movable nodes (v (N, 6) zeroed off them first), v elsewhere."""
    mov = H.movable[:, None]
    v0 = jnp.where(mov, v, 0.0)
    ok = H.valid[:, None]
    out = jnp.einsum("nab,nb->na", H.D, v0)
    out = out.at[H.i].add(jnp.where(ok, jnp.einsum("eab,eb->ea", H.U, v0[H.j]), 0.0))
    out = out.at[H.j].add(jnp.where(ok, jnp.einsum("eab,eb->ea", H.L, v0[H.i]), 0.0))
    return jnp.where(mov, out, v)


def block_jacobi(blocks: jnp.ndarray, movable: jnp.ndarray):
    """v -> blocks^-1 v per node (the block-Jacobi preconditioner), identity off ``movable``;
    blocks (N, 6, 6), movable (N,), v (N, 6)."""
    eye = jnp.eye(6, dtype=blocks.dtype)
    inv = jnp.linalg.inv(jnp.where(movable[:, None, None], blocks, eye))
    return lambda v: jnp.einsum("nab,nb->na", inv, v)


def pcg(op, b: jnp.ndarray, precond, tol: float, maxiter: int) -> jnp.ndarray:
    """x with op(x) = b (op symmetric positive definite) by preconditioned conjugate gradients
    from 0, until |b - op(x)| <= tol |b| or after ``maxiter`` iterations."""
    bound = (tol * tol) * jnp.sum(b * b)

    def cond(c):
        return (c[0] < maxiter) & (jnp.sum(c[2] * c[2]) > bound)

    def body(c):
        k, x, r, p, rz = c
        q = op(p)
        alpha = rz / jnp.sum(p * q)
        x, r = x + alpha * p, r - alpha * q
        z = precond(r)
        rz_new = jnp.sum(r * z)
        return k + 1, x, r, z + (rz_new / rz) * p, rz_new

    z = precond(b)
    init = (jnp.asarray(0, jnp.int32), jnp.zeros_like(b), b, z, jnp.sum(b * z))
    return jax.lax.while_loop(cond, body, init)[1]
