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
   pixel whose noise makes it look nearest (a biased, winner's-curse choice:
   ``docs/decisions.md``).

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
import numpy as np

from ..camera import Intrinsics, unproject
from ..config import Config
from ..determinism import full_precision
from ..geometry import Pose
from ..hostmem import to_host
from ..image.preprocess import Frame
from ..programs import program
from .residuals import point_jacobian, warp


class KeyframeEdges(NamedTuple):
    """Fixed-size edge set of a keyframe (struct of arrays): uv (2, K) level-0 pixels,
    rho (K,) inverse depth (1/m), grad (2, K) normalised image gradient, valid (K,) bool
    (padding slots are False and hold rho = 1), and mag (K,) the gradient magnitude (0 in
    padding slots; None when not known: only the per-edge weighting model reads it);
    depth_pts (3, M) and depth_normals (3, M): the keyframe's depth points for the optional
    depth residual (``depth.depth_points``; None without it); disc (K,) each edge's depth
    discontinuity (``depth_discontinuity``; 0 in padding slots; None when not known: only
    the weighting model reads it)."""

    uv: jnp.ndarray
    rho: jnp.ndarray
    grad: jnp.ndarray
    valid: jnp.ndarray
    mag: jnp.ndarray | None = None
    depth_pts: jnp.ndarray | None = None
    depth_normals: jnp.ndarray | None = None
    disc: jnp.ndarray | None = None


class Candidates(NamedTuple):
    """Culled edges of one keyframe (numpy, struct of arrays): uv (2, N), rho (N,),
    grad (2, N), mag (N,)."""

    uv: np.ndarray
    rho: np.ndarray
    grad: np.ndarray
    mag: np.ndarray

    def subset(self, idx: np.ndarray) -> Candidates:
        """The candidates ``idx``."""
        return Candidates(self.uv[:, idx], self.rho[idx], self.grad[:, idx], self.mag[idx])


def cull(frame: Frame, config: Config) -> np.ndarray:
    """Indices of the frame's edges with valid depth and magnitude >= canny_high."""
    keep = (frame.edge_depth > 0) & (frame.edge_mag >= config.canny_high)
    return np.flatnonzero(keep)


#: Side of the square window of ``depth_discontinuity`` (pixels).
DISCONTINUITY_WINDOW = 5


def depth_discontinuity(depth: np.ndarray | None, uv: np.ndarray, z: np.ndarray) -> np.ndarray:
    """(max - min) / z of the valid depths (m) in the ``DISCONTINUITY_WINDOW`` square around
    each edge pixel uv (2, N) of depth z (N,) m: ~0.01-0.05 on a smooth surface, ~0.1-1 where
    the edge lies on an occluding contour (its depth may be the background's or the
    foreground's), at most 1000. Missing depth (0, negative or not finite) is left out; zeros
    (N,) without a depth image."""
    if depth is None or uv.shape[1] == 0:
        return np.zeros(uv.shape[1], np.float32)
    d = np.asarray(depth, np.float32)
    h, w = d.shape
    r = DISCONTINUITY_WINDOW // 2
    steps = np.arange(-r, r + 1)
    du, dv = np.tile(steps, steps.size)[:, None], np.repeat(steps, steps.size)[:, None]
    u = np.clip(np.rint(uv[0]).astype(int)[None, :] + du, 0, w - 1)
    v = np.clip(np.rint(uv[1]).astype(int)[None, :] + dv, 0, h - 1)
    window = d[v, u]  # (window pixels, N): only the edges asked about, not the whole image
    ok = np.isfinite(window) & (window > 0)
    high = np.max(np.where(ok, window, 0.0), axis=0)
    low = np.min(np.where(ok, window, np.inf), axis=0)
    spread = np.maximum(high - np.minimum(low, z), 0.0).astype(np.float64)
    return np.minimum(spread / np.asarray(z, np.float64), 1e3).astype(np.float32)


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
    uv_c, pts = warp(intr, Pose.from_matrix(T_prior, orthonormalise="quaternion"), pts_k)
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


def _mix32(x: jnp.ndarray) -> jnp.ndarray:
    """MurmurHash3's 32-bit finaliser: a well-mixing function of uint32."""
    x = (x ^ (x >> 16)) * jnp.uint32(0x85EBCA6B)
    x = (x ^ (x >> 13)) * jnp.uint32(0xC2B2AE35)
    return x ^ (x >> 16)


def order_half_bits(n: int) -> int:
    """h of ``random_order``'s domain [0, 4^h) for n items: the smallest h >= 1 with
    4^h >= n."""
    return max(1, -(-max(n - 1, 1).bit_length() // 2))


def random_order(key: jax.Array, n: int) -> jnp.ndarray:
    """A pseudo-random order of 0..n-1 drawn from ``key``, in O(n) and without a sort (XLA's
    CPU sort or top_k of a few thousand keys costs about as much as the whole greedy): a
    4-round Feistel network keyed by ``key`` on [0, 4^h), 4^h >= n, whose round function
    is MurmurHash3's finaliser; a Feistel network is a bijection whatever its round function
    (Luby-Rackoff: four rounds of a good one look like a random permutation). Values >= n
    are left to the caller to skip. Returns (4^h,) int32, a permutation of 0..4^h-1."""
    half = order_half_bits(n)
    mask = jnp.uint32((1 << half) - 1)
    round_keys = jax.random.bits(key, (4,), jnp.uint32)
    x = jnp.arange(1 << (2 * half), dtype=jnp.uint32)
    left, right = x >> half, x & mask
    for k in range(4):
        left, right = right, left ^ (_mix32(right ^ round_keys[k]) & mask)
    return ((left << half) | right).astype(jnp.int32)


def first_usable(perm: jnp.ndarray, usable: jnp.ndarray, k: int
                 ) -> tuple[jnp.ndarray, jnp.ndarray]:
    """The first ``k`` entries of ``perm`` (indices, possibly >= len(usable)) that are usable,
    in their order (a binary search in the running count: no scatter, no sort), and a mask of
    the slots that found one."""
    n = usable.shape[0]
    u = (perm < n) & usable[jnp.minimum(perm, n - 1)]
    running = jnp.cumsum(u)
    at = jnp.searchsorted(running, jnp.arange(1, k + 1), side="left")
    return jnp.minimum(perm[jnp.minimum(at, perm.shape[0] - 1)], n - 1), at < perm.shape[0]


@full_precision
@partial(jax.jit, static_argnames=("num_edges", "lam", "max_per_cell"))
def partition_greedy(
    J: jnp.ndarray, p: jnp.ndarray, ok: jnp.ndarray, starts: jnp.ndarray,
    counts: jnp.ndarray, key: jax.Array, *, num_edges: int, lam: float, max_per_cell: int,
) -> tuple[jnp.ndarray, jnp.ndarray]:
    """Stochastic partition greedy (EdgeVO Algorithm 1).

    J (6, N) Jacobians, p (N,) re-observation probabilities, ok (N,) usable candidates, all in
    partition order; partition i holds candidates starts[i] .. starts[i] + counts[i] - 1 (P,),
    of which the first M = ``max_per_cell`` compete (counts 0 = padding). Partitions with a
    usable candidate are visited in a random order drawn from ``key``; each contributes the
    edge maximising p_e * logdet(H(S) + H(e) + lam I). Returns (num_edges,) indices and
    validity.
    """
    counts = jnp.minimum(counts, max_per_cell)
    running = jnp.concatenate([jnp.zeros(1, jnp.int32), jnp.cumsum(ok.astype(jnp.int32))])
    has_any = running[starts + counts] > running[starts]  # a usable candidate, no gather of M
    # a random order of the partitions, usable ones first
    steps, live = first_usable(random_order(key, has_any.shape[0]), has_any, num_edges)
    # gather every visited partition's candidates at once: the scan keeps only the sequence
    slot = jnp.arange(max_per_cell)
    cand = jnp.minimum(starts[steps][:, None] + slot, ok.shape[0] - 1)  # (num_edges, M)
    valid = (slot < counts[steps][:, None]) & ok[cand] & live[:, None]
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


@full_precision
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


def partition_order(cell_id: np.ndarray, max_per_cell: int, seed: int
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points grouped by partition: ``order`` (N,) sorts them by cell (a seeded shuffle within
    a cell when one holds more than ``max_per_cell``, whose first M then form its subset);
    ``starts`` and ``counts`` (P,) give each non-empty partition's range in that order."""
    if cell_id.size == 0:
        return np.zeros(0, np.intp), np.zeros(0, np.intp), np.zeros(0, np.intp)
    key = cell_id.astype(np.uint16 if cell_id.max() < 1 << 16 else np.int64)  # radix sort
    shuffle = None
    if np.bincount(cell_id).max() > max_per_cell:
        shuffle = np.random.default_rng(seed).permutation(cell_id.size)
        key = key[shuffle]
    order = np.argsort(key, kind="stable")
    if shuffle is not None:
        order = shuffle[order]
    sorted_ids = cell_id[order]
    starts = np.flatnonzero(np.r_[True, sorted_ids[1:] != sorted_ids[:-1]])
    counts = np.diff(np.r_[starts, cell_id.size])
    return order, starts, counts


def partition_mean(values: np.ndarray, starts: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """Each value replaced by the mean over its partition (values in partition order, the
    partitions' ranges ``starts`` + ``counts``)."""
    return np.repeat(np.add.reduceat(values, starts) / counts, counts).astype(values.dtype)


@partial(program, static_argnames=("width", "height", "mode", "num_edges", "max_per_cell",
                                   "lam", "a", "samples"))
def _select_device(
    points: jnp.ndarray, ranges: jnp.ndarray, T_prior: jnp.ndarray, intr: jnp.ndarray,
    seed: jnp.ndarray, *, width: int, height: int, mode: str, num_edges: int,
    max_per_cell: int, lam: float, a: float, samples: int,
):
    """One device call: information and visibility, the re-observation probabilities, then
    the greedy of ``mode``. points (6, N): u, v, partition-mean rho, gx, gy, magnitude of the
    candidates in partition order, padded to N; ranges (2N + 1,): the
    number of real candidates, then the partitions' starts and counts (zero padded)."""
    size = points.shape[1]
    uv, rho, grad, mag = points[0:2], points[2], points[3:5], points[5]
    n, starts, counts = ranges[0], ranges[1:size + 1], ranges[size + 1:]
    live = jnp.arange(size) < n
    J, visible = edge_information(uv, rho, grad, T_prior, Intrinsics(*intr), width, height)
    p = reobservation_probability(mag, a)
    ok = live & visible
    key = jax.random.key(seed)
    if mode == "spg":
        return partition_greedy(J, p, ok, starts, counts, key, num_edges=num_edges, lam=lam,
                                max_per_cell=max_per_cell)
    return stochastic_greedy(J, p, ok, key, num_edges=num_edges, lam=lam, samples=samples)


def _bucket(n: int, cap: int) -> int:
    """Padded size for n points: the next power of two, at least 1024, at most ``cap``: a few
    shapes, each compiled once, and no frame pays for thousands of empty slots."""
    return min(cap, max(1024, 1 << max(n - 1, 0).bit_length()))


def select(
    cands: Candidates, config: Config, *, T_prior: np.ndarray, intr: Intrinsics,
    width: int, height: int, seed: int, reobs_a: float | None = None,
) -> np.ndarray:
    """Indices into ``cands`` chosen by ``config.selection`` (at most ``edge_slots``);
    reobs_a: the re-observation offset a (default ``config.canny_high``)."""
    n = cands.rho.size
    rng = np.random.default_rng(seed)
    if n > config.max_edges:  # more candidates than slots: a seeded subset (fixed shapes)
        keep = np.sort(rng.choice(n, config.max_edges, replace=False))
        cands = cands.subset(keep)
        return keep[select(cands, config, T_prior=T_prior, intr=intr, width=width,
                           height=height, seed=seed, reobs_a=reobs_a)]
    if config.selection in ("all", "random") or n == 0:
        k = min(n, config.edge_slots)
        return np.arange(n) if k == n else np.sort(rng.choice(n, k, replace=False))
    cell_id, _ = partition_ids(cands.uv, width, height, config.cell_size)
    order, starts, counts = partition_order(cell_id, config.max_per_cell, seed)
    size = candidate_size(n, config)  # partitions <= points: one size for both
    points = np.zeros((6, size), np.float32)  # one buffer, one transfer
    points[2] = 1.0
    points[0:2, :n] = cands.uv[:, order]
    points[2, :n] = partition_mean(cands.rho[order], starts, counts)
    points[3:5, :n] = cands.grad[:, order]
    points[5, :n] = cands.mag[order]
    ranges = np.zeros(2 * size + 1, np.int32)
    ranges[0] = n
    ranges[1:1 + starts.size] = starts
    ranges[1 + size:1 + size + counts.size] = counts
    idx, taken = to_host(_run_device(points, ranges, T_prior, intr, seed, config, width=width,
                                     height=height, reobs_a=reobs_a))
    return np.sort(order[idx[taken]])


def _run_device(points: np.ndarray, ranges: np.ndarray, T_prior: np.ndarray, intr: Intrinsics,
                seed: int, config: Config, *, width: int, height: int,
                reobs_a: float | None):
    """``_select_device`` with the static options of ``config`` (device arrays out)."""
    size = points.shape[1]
    # (N / k) log(1 / eps) samples per greedy step (N: the padded size, a static number)
    samples = math.ceil(size / config.num_edges * math.log(1 / config.greedy_epsilon))
    return _select_device(
        points, ranges, np.asarray(T_prior, np.float32), np.asarray(intr, np.float32),
        np.uint32(seed & 0xFFFFFFFF), width=width, height=height, mode=config.selection,
        num_edges=config.num_edges, max_per_cell=config.max_per_cell,
        lam=float(config.logdet_lambda),
        a=float(config.canny_high if reobs_a is None else reobs_a), samples=samples,
    )


def _buckets(cap: int) -> list[int]:
    """Every size ``_bucket`` gives under ``cap``, ascending."""
    sizes, n = [], 1
    while not sizes or sizes[-1] < cap:
        sizes.append(_bucket(n, cap))
        n = sizes[-1] + 1
    return sizes


def candidate_size(n: int, config: Config) -> int:
    """Padded size of the selection's candidate buffers for n candidates: ``_bucket``; with
    ``spg``, the largest bucket whose partitions are visited in the same random order
    (``random_order`` over the same domain, ``order_half_bits``). Padding partitions hold no
    candidate and are skipped where they fall in that order, so the choice is the one of
    the smaller bucket, bit for bit, with fewer programs to compile (3 instead of 5 by
    default). ``greedy`` samples over the whole buffer: its own bucket."""
    size = _bucket(n, config.max_edges)
    if config.selection != "spg":
        return size
    half = order_half_bits(size)
    return max(s for s in _buckets(config.max_edges) if order_half_bits(s) == half)


def bucket_sizes(config: Config) -> list[int]:
    """Every padded size of the selection's candidate buffers (``candidate_size``) a
    keyframe can meet."""
    sizes = _buckets(config.max_edges)
    if config.selection == "spg":
        return sorted({candidate_size(s, config) for s in sizes})
    return sizes


def warm_up(config: Config, *, intr: Intrinsics, width: int, height: int,
            reobs_a: float | None = None) -> None:
    """Compile (or load from the compilation cache) and run once the selection's device
    program for every candidate buffer size (``bucket_sizes``), on empty buffers: no
    keyframe of the run waits for a compilation. Nothing to do for ``all`` and ``random``."""
    if config.selection not in ("spg", "greedy"):
        return
    for size in bucket_sizes(config):
        points = np.zeros((6, size), np.float32)
        points[2] = 1.0
        jax.block_until_ready(_run_device(
            points, np.zeros(2 * size + 1, np.int32), np.eye(4), intr, 0, config,
            width=width, height=height, reobs_a=reobs_a))


def pack_edges(cands: Candidates, idx: np.ndarray, size: int,
               disc: np.ndarray | None = None) -> KeyframeEdges:
    """Edges ``idx`` of ``cands`` in ``size`` slots (numpy), padding with valid=False, with
    their depth discontinuities ``disc`` (idx.size,) (zeros when None)."""
    n = idx.size
    uv = np.zeros((2, size), np.float32)
    rho = np.ones(size, np.float32)
    grad = np.zeros((2, size), np.float32)
    valid = np.zeros(size, bool)
    mag = np.zeros(size, np.float32)
    disc_slots = np.zeros(size, np.float32)
    uv[:, :n] = cands.uv[:, idx]
    rho[:n] = cands.rho[idx]
    grad[:, :n] = cands.grad[:, idx]
    valid[:n] = True
    mag[:n] = cands.mag[idx]
    if disc is not None:
        disc_slots[:n] = disc
    return KeyframeEdges(uv=uv, rho=rho, grad=grad, valid=valid, mag=mag, disc=disc_slots)


def keyframe_edges(
    frame: Frame, config: Config, *, seed: int, T_prior: np.ndarray | None = None,
    intr: Intrinsics | None = None, reobs_a: float | None = None,
) -> KeyframeEdges:
    """The keyframe's tracked edges in fixed slots (numpy): ``num_edges`` for the selecting
    modes; for ``all``, the next power of two (>= 1024, <= ``max_edges``) above the number
    of edges, so that the baseline pays for the edges it tracks and not for empty slots
    (a handful of sizes, each compiled once).

    T_prior (4, 4): the expected T_next_kf (identity when unknown); intr is needed for the
    information-based modes (spg, greedy); reobs_a: the re-observation sigmoid's offset a
    (default ``config.canny_high``, the paper's; ``params.Params.reobs_a`` when learnt).
    """
    cands = candidates(frame, config)
    T_prior = np.eye(4) if T_prior is None else T_prior
    if intr is None and config.selection in ("spg", "greedy"):
        raise ValueError(f"selection={config.selection} needs the camera intrinsics")
    h, w = frame.shape
    idx = select(cands, config, T_prior=T_prior, intr=intr, width=w, height=h, seed=seed,
                 reobs_a=reobs_a)
    slots = _bucket(idx.size, config.max_edges) if config.selection == "all" \
        else config.edge_slots
    # only the selected edges' discontinuity (a window each), from their own depths
    z = frame.edge_depth[cull(frame, config)[idx]]
    return pack_edges(cands, idx, slots, depth_discontinuity(frame.depth, cands.uv[:, idx], z))
