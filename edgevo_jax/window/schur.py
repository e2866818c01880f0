"""The Schur complement, written once: eliminating a diagonal block (the window's inverse
depths: an edge's depth enters only its own residuals) from a quadratic, for the damped
solve of the window and for marginalising keyframes and edges, and ``marginalize``, the
dense Schur complement onto kept variables.

A quadratic 0.5 x^T H x + b^T x over x = [c, p] with H = [[H_cc, H_cp], [H_cp^T, diag(d)]]:
minimising over p leaves 0.5 c^T S c + r^T c with

    S = H_cc - H_cp D^-1 H_cp^T,   r = b_c - H_cp D^-1 b_p,

and the minimiser p = -D^-1 (b_p + H_cp^T c).
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
import numpy as np


class Eliminated(NamedTuple):
    """What eliminating the diagonal block leaves: S (m, m) (symmetrised), r (m,), and
    inv (n,) = 1 / d, 0 where d <= min_h (those variables are dropped: delta 0)."""

    S: jnp.ndarray
    r: jnp.ndarray
    inv: jnp.ndarray


def eliminate_diagonal(
    H_cc: jnp.ndarray, H_cp: jnp.ndarray, d: jnp.ndarray, b_c: jnp.ndarray, b_p: jnp.ndarray,
    *, min_h: float = 1e-12,
) -> Eliminated:
    """Eliminate the diagonal block diag(d) (n,) from [[H_cc, H_cp], [H_cp^T, diag(d)]]
    (H_cc (m, m), H_cp (m, n)) and b = [b_c (m,), b_p (n,)]: S = 0.5 (S' + S'^T) with
    S' = H_cc - W H_cp^T, r = b_c - W b_p, W = H_cp D^-1 (module doc). Entries with
    d <= min_h (padding slots, unobserved depths; their H_cp columns are zero too) count as
    absent: 1 / d is taken as 0 there. O(m^2 n), no inverse but 1 / d."""
    seen = d > min_h
    inv = jnp.where(seen, 1.0 / jnp.where(seen, d, 1.0), 0.0)
    W = H_cp * inv
    S = H_cc - W @ H_cp.T
    return Eliminated(0.5 * (S + S.T), b_c - W @ b_p, inv)


def schur_solve(
    H_cc: jnp.ndarray, H_cp: jnp.ndarray, h_pp: jnp.ndarray, b_c: jnp.ndarray,
    b_p: jnp.ndarray, damping: float | jnp.ndarray, *, min_h: float = 1e-12,
) -> tuple[jnp.ndarray, jnp.ndarray]:
    """Solve (H + damping diag(H)) delta = -b for H = [[H_cc, H_cp], [H_cp^T, diag(h_pp)]]
    by eliminating the diagonal depth block (``eliminate_diagonal``):

        S = A_cc - H_cp D^-1 H_cp^T,  S delta_c = -(b_c - H_cp D^-1 b_p),
        delta_p = -D^-1 (b_p + H_cp^T delta_c),

    with A_cc = H_cc + damping diag(H_cc), D = (1 + damping) h_pp. Depths with D <= min_h
    (padding slots, unobserved edges; their H_cp columns are then zero too) get delta 0.
    Returns delta_c (m,), delta_p (n,).
    """
    A_cc = H_cc + damping * jnp.diag(jnp.diag(H_cc))
    e = eliminate_diagonal(A_cc, H_cp, (1.0 + damping) * h_pp, b_c, b_p, min_h=min_h)
    delta_c = -jnp.linalg.solve(e.S, e.r)
    delta_p = -e.inv * (b_p + H_cp.T @ delta_c)
    return delta_c, delta_p


def _index(idx: np.ndarray | jnp.ndarray, size: int) -> np.ndarray:
    idx = np.asarray(idx)
    if idx.dtype == bool:
        if idx.shape != (size,):
            raise ValueError(f"a boolean index needs shape ({size},), got {idx.shape}")
        return np.flatnonzero(idx)
    return idx.astype(np.int64).reshape(-1)


def marginalize(
    H: jnp.ndarray, b: jnp.ndarray, keep: np.ndarray, drop: np.ndarray, *,
    rtol: float | None = None,
) -> tuple[jnp.ndarray, jnp.ndarray]:
    """Schur complement of the quadratic 0.5 x^T H x + b^T x onto the kept variables:

        H' = H_kk - H_kd H_dd^+ H_dk,   b' = b_k - H_kd H_dd^+ b_d.

    keep, drop: static index arrays (or boolean masks) into H (the result follows keep's
    order). H_dd^+ is the pseudo-inverse of the Jacobi-scaled block (eigenvalues under rtol
    times the largest treated as zero; rtol defaults to jnp.linalg.pinv's), so a singular
    H_dd (padding slots, unobserved depths: zero rows) contributes nothing along its null
    space. Dense: O(k d + d^3).
    """
    size = H.shape[0]
    keep, drop = _index(keep, size), _index(drop, size)
    H = 0.5 * (H + H.T)
    Hkk, Hkd, Hdd = H[np.ix_(keep, keep)], H[np.ix_(keep, drop)], H[np.ix_(drop, drop)]
    dg = jnp.diag(Hdd)
    s = jnp.where(dg > 0, 1.0 / jnp.sqrt(jnp.where(dg > 0, dg, 1.0)), 0.0)
    Hdd_inv = s[:, None] * jnp.linalg.pinv(s[:, None] * Hdd * s[None, :], rtol=rtol,
                                           hermitian=True) * s[None, :]
    K = Hkd @ Hdd_inv
    Hm = Hkk - K @ Hkd.T
    return 0.5 * (Hm + Hm.T), b[keep] - K @ b[drop]


class EliminatedBlocks(NamedTuple):
    """What eliminating N dense diagonal blocks leaves (``eliminate_blocks``): S (m, m)
    (symmetrised) and r (m,) of the kept variables; ``per_pair`` (N, m), each block's share
    of r (b_c,i - H_cp,i H_pp,i^-1 b_p,i); and what back-substitution needs."""

    S: jnp.ndarray
    r: jnp.ndarray
    per_pair: jnp.ndarray
    inv: jnp.ndarray
    H_cp: jnp.ndarray
    b_p: jnp.ndarray

    def back(self, delta_c: jnp.ndarray) -> jnp.ndarray:
        """The eliminated variables' minimiser (N, b) given the kept ones' delta_c (m,):
        p_i = -H_pp,i^-1 (b_p,i + H_cp,i^T delta_c)."""
        rhs = self.b_p + jnp.einsum("nmb,m->nb", self.H_cp, delta_c)
        return -jnp.einsum("nab,nb->na", self.inv, rhs)


def eliminate_blocks(
    H_cc: jnp.ndarray, H_cp: jnp.ndarray, H_pp: jnp.ndarray, b_c: jnp.ndarray,
    b_p: jnp.ndarray,
) -> EliminatedBlocks:
    """The module's elimination with a block-diagonal D of N dense (b, b) blocks, each
    variable block coupled only to the kept variables (the camera's calibration: each
    pair's pose). Per block i: H_cc,i (N, m, m), H_cp,i (N, m, b), H_pp,i (N, b, b),
    b_c,i (N, m), b_p,i (N, b), summed over i after eliminating:
    S = sum_i H_cc,i - H_cp,i H_pp,i^-1 H_cp,i^T, r = sum_i b_c,i - H_cp,i H_pp,i^-1 b_p,i.
    A block with a singular H_pp,i (a pair with too few residuals) gets the pseudo-inverse
    (nothing along its null space)."""
    inv = jnp.linalg.pinv(0.5 * (H_pp + jnp.swapaxes(H_pp, -1, -2)), hermitian=True)
    W = H_cp @ inv
    S_i = H_cc - W @ jnp.swapaxes(H_cp, -1, -2)
    per_pair = b_c - jnp.einsum("nmb,nb->nm", W, b_p)
    S = jnp.sum(S_i, axis=0)
    return EliminatedBlocks(0.5 * (S + S.T), jnp.sum(per_pair, axis=0), per_pair, inv, H_cp,
                            b_p)
