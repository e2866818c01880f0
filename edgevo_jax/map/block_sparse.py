"""The pose graph's linear systems (``pose_graph``): block-sparse matrices of 6x6 blocks, one
block row and column per node, and their two solvers.

A ``Blocks`` matrix H (6N, 6N) holds its diagonal blocks D (N, 6, 6) and, per edge (i, j),
the block U at (row i, column j) and L at (row j, column i); edges sharing a pair add up.
Only the ``movable`` nodes' rows and columns count: the system is solved on them, and a node
off ``movable`` keeps its right-hand side (identity rows and columns: the caller's zeros
stay zeros). Invalid (padding) edges are ignored.

- ``direct``: a sparse factorisation of the movable part on the host in float64, through
  ``jax.pure_callback``; ``jax.vmap`` solves the graphs of a batch one after the other.
  A symmetric positive definite H (``symmetric=True``: the LM's damped systems) by
  CHOLMOD's supernodal Cholesky (CVXOPT's binding) of 0.5 (H + H^T), its pattern analysed
  once (fill-reducing ordering, supernodes; the last 8 patterns are kept) and refactored
  numerically per system; otherwise, or where H is not positive definite, SciPy's sparse
  LU (SuperLU, a minimum-degree ordering of H + H^T, diagonal pivots preferred).
  Deterministic: the same inputs give the same bits, call after call
  (tests/map/test_block_sparse.py).
- ``pcg``: preconditioned conjugate gradients of an operator (symmetric positive definite),
  on the device, with the 6x6 block-Jacobi preconditioner ``block_jacobi``: no host round
  trip, but its iterations grow with the graph (a chain of N nodes asks O(N)).
"""

from __future__ import annotations

import hashlib
import threading
from collections import OrderedDict
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


def _pattern(i, j, valid, movable):
    """Where H's blocks stand in its movable part (host arrays in, module doc): the movable
    nodes (m,), the edges kept (E,) bool (valid, both nodes movable), and the scalar rows
    and columns (m + 2k, 6, 6) of D's movable blocks, then the kept edges' U, then their L."""
    nodes = np.flatnonzero(movable)
    slot = np.cumsum(movable) - 1  # a movable node's block row
    keep = valid & movable[i] & movable[j]
    bi, bj = slot[i[keep]], slot[j[keep]]
    diagonal = np.arange(nodes.size)
    a = np.arange(6)
    brow, bcol = np.concatenate([diagonal, bi, bj]), np.concatenate([diagonal, bj, bi])
    shape = (brow.size, 6, 6)
    return (nodes, keep, np.broadcast_to(6 * brow[:, None, None] + a[None, :, None], shape),
            np.broadcast_to(6 * bcol[:, None, None] + a[None, None, :], shape))


def _csc(D, U, L, i, j, valid, movable):
    """The movable part of H as a SciPy CSC matrix (6m, 6m) in float64, and the movable
    nodes (m,) in index order (host arrays in, module doc)."""
    import scipy.sparse

    nodes, keep, rows, cols = _pattern(i, j, valid, movable)
    n = 6 * nodes.size
    blocks = np.concatenate([D[nodes], U[keep], L[keep]]).astype(np.float64)
    H = scipy.sparse.coo_matrix((blocks.ravel(), (rows.ravel(), cols.ravel())),
                                shape=(n, n)).tocsc()  # duplicates summed
    return H, nodes


class _Analysis:
    """One sparsity pattern's symbolic work, done once: the CSC structure (6m, 6m) of the
    lower triangle of the movable part, where each scalar of D's movable blocks and the kept
    edges' U and L lands in it (``dest``: entry (r, c) of H adds ``weight`` x its value to
    (max(r, c), min(r, c)), 0.5 off the diagonal: 0.5 (H + H^T)), and CHOLMOD's symbolic
    factorisation of it (its fill-reducing ordering, supernodes), refactored numerically
    per system under ``lock``."""

    def __init__(self, i, j, valid, movable):
        from cvxopt import cholmod, matrix, spmatrix

        self.nodes, self.keep, rows, cols = _pattern(i, j, valid, movable)
        n = 6 * self.nodes.size
        rows, cols = rows.ravel(), cols.ravel()
        lower = np.maximum(cols, rows) + n * np.minimum(cols, rows)  # column-major: CSC order
        unique, self.dest = np.unique(lower, return_inverse=True)
        self.weight = np.where(rows == cols, 1.0, 0.5)
        self.size = unique.size
        self.matrix = spmatrix(1.0, matrix((unique % n).astype(np.int64)),
                               matrix((unique // n).astype(np.int64)), (n, n))
        self.factor = cholmod.symbolic(self.matrix)  # its lower triangle (uplo "L")
        self.lock = threading.Lock()

    def solve(self, D, U, L, rhs: np.ndarray) -> np.ndarray | None:
        """x with 0.5 (H + H^T) x = rhs by CHOLMOD's Cholesky of its lower triangle, or None
        where it is not positive definite (H from its blocks, module doc)."""
        from cvxopt import cholmod, matrix

        values = np.concatenate([D[self.nodes].ravel(), U[self.keep].ravel(),
                                 L[self.keep].ravel()]).astype(np.float64)
        data = np.bincount(self.dest, weights=values * self.weight, minlength=self.size)
        x = matrix(rhs)
        with self.lock:
            self.matrix.V = matrix(data)
            try:
                cholmod.numeric(self.matrix, self.factor)
            except ArithmeticError:
                return None
            cholmod.solve(self.factor, x)
        return np.array(x).ravel()


_ANALYSES: OrderedDict[bytes, _Analysis] = OrderedDict()
_ANALYSES_LOCK = threading.Lock()
_ANALYSES_KEPT = 8  # patterns remembered (a solve's tries share one; the map's next differs)


def _analysis(i, j, valid, movable) -> _Analysis:
    """The pattern's ``_Analysis``, from the cache (the last ``_ANALYSES_KEPT`` patterns)."""
    key = hashlib.blake2b(b"".join(np.ascontiguousarray(a).tobytes() for a in
                                   (i, j, valid, movable)), digest_size=16).digest()
    with _ANALYSES_LOCK:
        found = _ANALYSES.get(key)
        if found is not None:
            _ANALYSES.move_to_end(key)
            return found
    found = _Analysis(i, j, valid, movable)
    with _ANALYSES_LOCK:
        _ANALYSES[key] = found
        while len(_ANALYSES) > _ANALYSES_KEPT:
            _ANALYSES.popitem(last=False)
    return found


def _cholesky_solve(D, U, L, i, j, valid, movable, b) -> np.ndarray | None:
    """x on the movable nodes (m, 6) of the symmetrised H x = b by CHOLMOD (module doc), or
    None where H is not positive definite (or the solution is not finite)."""
    a = _analysis(i, j, valid, movable)
    x = a.solve(D, U, L, b[a.nodes].astype(np.float64).ravel())
    return x.reshape(-1, 6) if x is not None and np.all(np.isfinite(x)) else None


def _host_solve(D, U, L, i, j, valid, movable, b, symmetric=False):
    """x (N, 6) with H x = b on the movable nodes, x = b elsewhere (module doc), in float64
    (x of b's dtype): symmetric, by CHOLMOD's Cholesky of 0.5 (H + H^T), else (or where
    that fails: not positive definite) by SuperLU; NaN on the movable nodes where H's
    movable part is exactly singular. Host arrays in and out."""
    import scipy.sparse.linalg

    x = np.array(b, copy=True)
    nodes = np.flatnonzero(movable)
    if not (nodes.size and b[nodes].any()):  # a zero right-hand side: x = 0, nothing to factor
        return x
    found = _cholesky_solve(D, U, L, i, j, valid, movable, b) if symmetric else None
    if found is not None:
        x[nodes] = found
        return x
    H, nodes = _csc(D, U, L, i, j, valid, movable)
    if symmetric:
        H = 0.5 * (H + H.T)
    try:
        lu = scipy.sparse.linalg.splu(H.tocsc(), permc_spec="MMD_AT_PLUS_A",
                                      diag_pivot_thresh=0.0, options=dict(SymmetricMode=True))
        x[nodes] = lu.solve(b[nodes].astype(np.float64).ravel()).reshape(-1, 6)
    except RuntimeError:  # exactly singular: no solution to give
        x[nodes] = np.nan
    return x


def _bits(a: jnp.ndarray) -> jnp.ndarray:
    """A float array's bits as uint32 (float64: a trailing axis of 2): the callback's thread
    may not share a ``jax.enable_x64`` context, and JAX would cast float64 down there."""
    return jax.lax.bitcast_convert_type(a, jnp.uint32)


def _from_bits(dtype: np.dtype, symmetric: bool, *args):
    """``_host_solve`` on the floats that ``_bits`` encoded (D, U, L and b), its x as bits."""
    D, U, L, i, j, valid, movable, b = (np.asarray(a) for a in args)
    D, U, L, b = (np.ascontiguousarray(a).view(dtype).reshape(a.shape[:-1] if
                  dtype == np.float64 else a.shape) for a in (D, U, L, b))
    x = _host_solve(D, U, L, i, j, valid, movable, b, symmetric)
    return x.astype(dtype).view(np.uint32).reshape(args[-1].shape)


def direct(H: Blocks, b: jnp.ndarray, *, symmetric: bool = False) -> jnp.ndarray:
    """x (N, 6) with H x = b on H's movable nodes (b's rows elsewhere), by a sparse
    factorisation on the host (module doc); of b's dtype (float32 or float64, H's too).
    symmetric: H is symmetric up to rounding (0.5 (H + H^T) is solved, by LDL^T), else LU.
    Traceable (a ``jax.pure_callback``), vmap-able (one graph after another); not
    differentiable (callers give their own derivative)."""
    bits = _bits(b)
    args = (*(_bits(a) for a in H[:3]), *H[3:], bits)
    out = jax.ShapeDtypeStruct(bits.shape, bits.dtype)
    x = jax.pure_callback(partial(_from_bits, np.dtype(b.dtype), symmetric), out, *args,
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
