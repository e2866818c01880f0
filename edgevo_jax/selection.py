"""Which keyframe edges the tracker uses (EdgeVO, "Edge Culling" and Algorithm 1).

1. Culling: an edge is a candidate only with valid depth and a gradient magnitude of at least
   the Canny high threshold ``a``.
2. Information: H(e) = J_e^T J_e, with J_e (1 x 6) the distance residual's Jacobian at the prior
   motion (the constant-velocity guess for the next frame). At an edge the distance field's
   gradient is the edge normal, so J_e uses the normalised image gradient. Edges that leave the
   image under the prior motion are skipped.
3. Stochastic partition greedy: a grid of ``cell_size`` cells cuts the image into partitions;
   partitions with candidates are visited in a random order (explicit key); from each, the edge
   maximising p_e * logdet(H(S) + H(e) + lambda I) joins S, p_e = 1 / (1 + exp(a - m_e)) being
   the re-observation probability. H(e) has rank one, so by the matrix determinant lemma
   logdet(A + j j^T) = logdet(A) + log(1 + j^T A^-1 j) with A = H(S) + lambda I: the gains of a
   whole partition are one batched quadratic form, and A^-1 follows by Sherman-Morrison.
   The Jacobians use the mean inverse depth of each partition's candidates: neighbouring
   pixels of one edge differ in depth mostly by sensor noise, and ranking them by it picks the
   pixel whose noise makes it look nearest (a biased, winner's-curse choice; on fr3_teddy it
   raised ATE by ~30 %).

Modes (``Config.selection``): ``spg`` (above), ``greedy`` (stochastic greedy on the same
objective over all candidates, no partitions: it clusters), ``random`` (a uniform subset) and
``all`` (every culled edge, in ``max_edges`` slots). Output: a fixed number of slots with a
validity mask, so the tracker compiles once per configuration.
"""

from __future__ import annotations

import math
from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np

from .camera import Intrinsics, unproject
from .config import Config
from .preprocess import Frame
from .residuals import point_jacobian, warp
from .solve import KeyframeEdges


class Candidates(NamedTuple):
    """Culled edges of one keyframe (numpy, struct of arrays): uv (2, N), rho (N,),
    grad (2, N), mag (N,)."""

    uv: np.ndarray
    rho: np.ndarray
    grad: np.ndarray
    mag: np.ndarray


def cull(frame: Frame, config: Config) -> np.ndarray:
    """Indices of the frame's edges with valid depth and magnitude >= canny_high."""
    keep = (frame.edge_depth > 0) & (frame.edge_mag >= config.canny_high)
    return np.flatnonzero(keep)


def candidates(frame: Frame, config: Config) -> Candidates:
    """The culled edges of a frame."""
    idx = cull(frame, config)
    return Candidates(
        uv=frame.edge_uv[idx].T.copy(), rho=1.0 / frame.edge_depth[idx],
        grad=frame.edge_grad[idx].T.copy(), mag=frame.edge_mag[idx],
    )


def reobservation_probability(mag: jnp.ndarray, a: float) -> jnp.ndarray:
    """p_e = 1 / (1 + exp(a - m_e)) (EdgeVO): strong edges are likely to be seen again."""
    return jax.nn.sigmoid(mag - a)


def edge_information(
    uv: jnp.ndarray, rho: jnp.ndarray, grad: jnp.ndarray, T_prior: jnp.ndarray,
    intr: Intrinsics, width: int, height: int,
) -> tuple[jnp.ndarray, jnp.ndarray]:
    """Jacobians J_e (6, N) of the candidates' residuals at the prior motion T_prior (4, 4)
    (H(e) = J_e J_e^T), and their visibility (in front, inside the image) under it."""
    pts_k = unproject(intr, uv, rho)
    uv_c, pts = warp(intr, jaxlie.SE3.from_matrix(T_prior), pts_k)
    visible = (pts[2] > 1e-6) & (uv_c[0] >= 0) & (uv_c[0] <= width - 1) & (uv_c[1] >= 0) \
        & (uv_c[1] <= height - 1)
    return point_jacobian(intr, pts, grad), visible


def logdet_gains(
    J: jnp.ndarray, A_inv: jnp.ndarray, logdet_A: jnp.ndarray
) -> jnp.ndarray:
    """logdet(A + J_e J_e^T) for every column J_e of J (6, M), batched (determinant lemma)."""
    q = jnp.sum(J * jnp.sum(A_inv[:, :, None] * J[None], axis=1), axis=0)
    return logdet_A + jnp.log1p(jnp.maximum(q, 0.0))


def _add_edge(A_inv: jnp.ndarray, logdet_A: jnp.ndarray, j: jnp.ndarray):
    """A <- A + j j^T: Sherman-Morrison for the inverse, determinant lemma for the logdet.
    (Elementwise products, no dot: inside a scan XLA on CPU runs these ~4x faster.)"""
    Aj = jnp.sum(A_inv * j[None, :], axis=1)
    q = jnp.sum(j * Aj)
    return A_inv - Aj[:, None] * Aj[None, :] / (1.0 + q), logdet_A + jnp.log1p(q)


def _start(lam: float, dtype) -> tuple[jnp.ndarray, jnp.ndarray]:
    return jnp.eye(6, dtype=dtype) / lam, jnp.asarray(6.0 * math.log(lam), dtype)


@partial(jax.jit, static_argnames=("num_edges", "lam"))
def partition_greedy(
    J: jnp.ndarray, p: jnp.ndarray, ok: jnp.ndarray, table: jnp.ndarray, key: jax.Array,
    *, num_edges: int, lam: float,
) -> tuple[jnp.ndarray, jnp.ndarray]:
    """Stochastic partition greedy (EdgeVO Algorithm 1).

    J (6, N) Jacobians, p (N,) re-observation probabilities, ok (N,) usable candidates,
    table (P, M) candidate indices per partition (-1 = empty slot). Partitions with a usable
    candidate are visited in a random order drawn from ``key``; each contributes the edge
    maximising p_e * logdet(H(S) + H(e) + lam I). Returns (num_edges,) indices and validity.
    """
    slot_ok = (table >= 0) & ok[jnp.maximum(table, 0)]
    has_any = jnp.any(slot_ok, axis=1)
    # a random order of the partitions, usable ones first (top_k: XLA's CPU sort is slow)
    k = min(num_edges, has_any.shape[0])
    order = jax.lax.top_k(jax.random.uniform(key, has_any.shape) + 2.0 * has_any, k)[1]
    steps = jnp.resize(order, (num_edges,))
    live = jnp.arange(num_edges) < k
    # gather every visited partition's candidates at once: the scan keeps only the sequence
    cand = jnp.maximum(table[steps], 0)  # (num_edges, M)
    valid = slot_ok[steps] & live[:, None]
    Jc = jnp.moveaxis(J[:, cand], 0, -1)  # (num_edges, M, 6)

    def step(carry, xs):
        A_inv, logdet_A = carry
        Jm, pm, vm, cm = xs
        q = jnp.sum(jnp.sum(Jm[:, :, None] * A_inv[None], axis=1) * Jm, axis=1)
        score = jnp.where(vm, pm * (logdet_A + jnp.log1p(jnp.maximum(q, 0.0))), -jnp.inf)
        best = jnp.argmax(score)
        take = vm[best]
        A_new, ld_new = _add_edge(A_inv, logdet_A, Jm[best])
        carry = (jnp.where(take, A_new, A_inv), jnp.where(take, ld_new, logdet_A))
        return carry, (cm[best], take)

    xs = (Jc, p[cand], valid, cand)
    _, (idx, taken) = jax.lax.scan(step, _start(lam, J.dtype), xs)
    return idx, taken


@partial(jax.jit, static_argnames=("num_edges", "lam", "samples"))
def stochastic_greedy(
    J: jnp.ndarray, p: jnp.ndarray, ok: jnp.ndarray, key: jax.Array,
    *, num_edges: int, lam: float, samples: int,
) -> tuple[jnp.ndarray, jnp.ndarray]:
    """Stochastic greedy without partitions (Mirzasoleiman et al.): each step scores
    ``samples`` random candidates by p_e * logdet(H(S) + H(e) + lam I) and keeps the best."""
    n = J.shape[1]

    def step(carry, k):
        A_inv, logdet_A, taken_mask = carry
        cand = jax.random.randint(k, (samples,), 0, n)
        valid = ok[cand] & ~taken_mask[cand]
        score = jnp.where(valid, p[cand] * logdet_gains(J[:, cand], A_inv, logdet_A), -jnp.inf)
        best = jnp.argmax(score)
        take = valid[best]
        A_new, ld_new = _add_edge(A_inv, logdet_A, J[:, cand[best]])
        carry = (jnp.where(take, A_new, A_inv), jnp.where(take, ld_new, logdet_A),
                 taken_mask.at[cand[best]].set(taken_mask[cand[best]] | take))
        return carry, (cand[best], take)

    A_inv, logdet_A = _start(lam, J.dtype)
    init = (A_inv, logdet_A, jnp.zeros(n, bool))
    _, (idx, taken) = jax.lax.scan(step, init, jax.random.split(key, num_edges))
    return idx, taken


def partition_ids(uv: np.ndarray, width: int, height: int, cell: int) -> tuple[np.ndarray, int]:
    """Grid cell (partition) of each point uv (2, N), row-major, and the number of cells."""
    cols, rows = -(-width // cell), -(-height // cell)
    cu = np.clip(np.round(uv[0]).astype(int) // cell, 0, cols - 1)
    cv = np.clip(np.round(uv[1]).astype(int) // cell, 0, rows - 1)
    return cv * cols + cu, rows * cols


def partition_table(cell_id: np.ndarray, num_cells: int, max_per_cell: int, seed: int
                    ) -> np.ndarray:
    """(P, M) indices of the points in each of the P cells, -1 padded; a seeded subset when a
    cell holds more than M = ``max_per_cell``."""
    table = np.full((num_cells, max_per_cell), -1, np.int32)
    if cell_id.size == 0:
        return table
    shuffled = np.random.default_rng(seed).permutation(cell_id.size)
    order = shuffled[np.argsort(cell_id[shuffled], kind="stable")]
    sorted_ids = cell_id[order]
    first = np.searchsorted(sorted_ids, sorted_ids, side="left")
    rank = np.arange(order.size) - first
    keep = rank < max_per_cell
    table[sorted_ids[keep], rank[keep]] = order[keep]
    return table


def partition_mean(values: np.ndarray, cell_id: np.ndarray) -> np.ndarray:
    """Each point's value replaced by the mean over its partition."""
    total = np.bincount(cell_id, weights=values)
    count = np.bincount(cell_id)
    return (total / np.maximum(count, 1))[cell_id]


def select(
    cands: Candidates, config: Config, *, T_prior: np.ndarray, intr: Intrinsics,
    width: int, height: int, seed: int,
) -> np.ndarray:
    """Indices into ``cands`` chosen by ``config.selection`` (at most ``edge_slots``)."""
    n = cands.rho.size
    rng = np.random.default_rng(seed)
    if n > config.max_edges:  # more candidates than slots: a seeded subset (fixed shapes)
        keep = np.sort(rng.choice(n, config.max_edges, replace=False))
        cands = Candidates(cands.uv[:, keep], cands.rho[keep], cands.grad[:, keep],
                           cands.mag[keep])
        return keep[select(cands, config, T_prior=T_prior, intr=intr, width=width,
                           height=height, seed=seed)]
    if config.selection in ("all", "random") or n == 0:
        k = min(n, config.edge_slots)
        return np.arange(n) if k == n else np.sort(rng.choice(n, k, replace=False))
    cell_id, num_cells = partition_ids(cands.uv, width, height, config.cell_size)
    pad = config.max_edges - n  # one padded size: one compilation
    uv = np.pad(cands.uv, ((0, 0), (0, pad)))
    rho = np.pad(partition_mean(cands.rho, cell_id), (0, pad), constant_values=1.0)
    grad = np.pad(cands.grad, ((0, 0), (0, pad)))
    J, visible = _information_jit(uv.astype(np.float32), rho.astype(np.float32), grad,
                                  T_prior.astype(np.float32), intr, width, height)
    p = reobservation_probability(jnp.asarray(np.pad(cands.mag, (0, pad))), config.canny_high)
    ok = jnp.asarray(np.arange(config.max_edges) < n) & visible
    key = jax.random.key(seed)
    if config.selection == "spg":
        table = partition_table(cell_id, num_cells, config.max_per_cell, seed)
        idx, taken = partition_greedy(J, p, ok, table, key, num_edges=config.num_edges,
                                      lam=config.logdet_lambda)
    else:
        # (N / k) log(1 / eps) samples per step, N taken as the slot count: a static number
        ratio = config.max_edges / config.num_edges
        samples = math.ceil(ratio * math.log(1 / config.greedy_epsilon))
        idx, taken = stochastic_greedy(J, p, ok, key, num_edges=config.num_edges,
                                       lam=config.logdet_lambda, samples=samples)
    idx, taken = jax.device_get((idx, taken))
    return np.sort(idx[taken])


_information_jit = jax.jit(edge_information, static_argnames=("width", "height"))


def pack_edges(cands: Candidates, idx: np.ndarray, size: int) -> KeyframeEdges:
    """Edges ``idx`` of ``cands`` in ``size`` slots (numpy), padding with valid=False."""
    n = idx.size
    uv = np.zeros((2, size), np.float32)
    rho = np.ones(size, np.float32)
    grad = np.zeros((2, size), np.float32)
    valid = np.zeros(size, bool)
    uv[:, :n] = cands.uv[:, idx]
    rho[:n] = cands.rho[idx]
    grad[:, :n] = cands.grad[:, idx]
    valid[:n] = True
    return KeyframeEdges(uv=uv, rho=rho, grad=grad, valid=valid)


def keyframe_edges(
    frame: Frame, config: Config, *, seed: int, T_prior: np.ndarray | None = None,
    intr: Intrinsics | None = None,
) -> KeyframeEdges:
    """The keyframe's tracked edges in fixed slots (numpy): ``num_edges`` for the selecting
    modes; for ``all``, the next power of two (>= 1024, <= ``max_edges``) above the number
    of edges, so that the baseline pays for the edges it tracks and not for empty slots
    (a handful of sizes, each compiled once).

    T_prior (4, 4): the expected T_next_kf (identity when unknown); intr is needed for the
    information-based modes (spg, greedy).
    """
    cands = candidates(frame, config)
    T_prior = np.eye(4) if T_prior is None else T_prior
    if intr is None and config.selection in ("spg", "greedy"):
        raise ValueError(f"selection={config.selection} needs the camera intrinsics")
    h, w = frame.shape
    idx = select(cands, config, T_prior=T_prior, intr=intr, width=w, height=h, seed=seed)
    slots = config.edge_slots
    if config.selection == "all":
        slots = min(config.max_edges, max(1024, 1 << max(idx.size - 1, 0).bit_length()))
    return pack_edges(cands, idx, slots)
