"""Loops closed: the pose graph over the keyframe map in the tracker's hands (``Loops``).

Edges. A keyframe made from a frame tracked against another keyframe (its ``parent``) is
tied to it by their relative pose as the window refined it (``measure``, when its refinement
is taken), with the information of the solve that tracked the frame. A loop edge ties a new
keyframe to an older keyframe of the map that the graph does not tie to it within twice
``window_size`` edges (``tied``), found by what the camera sees: recognition's candidates,
each placed by its landmarks matched to the new keyframe's frame (PnP, no pose of the
chain's), refined by the edge alignment, verified and confirmed by a keyframe beside the
old one (``tracking.places.Places.loop``), on the worker; the search is taken
``Config.loop_lag`` frames later (``found``). One search is in flight at a time
(``searches``).

Information. The solve's covariance (J^T W J)^-1 counts the pixels' noise only: it gives a
keyframe's pose to a tenth of a millimetre where the tracker's bias moves it by millimetres.
Each edge's covariance is the solve's plus a floor of ``FLOOR_M`` and ``FLOOR_DEG`` (the
drift of one keyframe to the next, a few millimetres and tenths of a degree), so that the
graph's chi-square and its robust kernel speak of the error a keyframe really has.

Correction. A loop edge that disagrees with the map (chi-square over the kernel's scale
squared) submits the graph to a worker at the lowest priority (``submit``): the map's
anchored keyframes whose pose is final, the oldest of each connected part held
(``pose_graph.optimise``: a Cauchy kernel on loop edges). A loop edge left with a
robust weight under ``MIN_WEIGHT`` is rejected (dropped, and the graph solved again without
it) unless the graph solved as plain squares explains it as drift, every edge within
``SPREAD_CHI2`` (a loop after real drift, which the kernel hears faintly from the drifted
chain: ``_spread``). The solution is taken ``loop_lag`` frames after it was submitted (the
tracker waits for it if need be), so when it lands never depends on the machine; loops found
meanwhile wait for the next solve. Each keyframe of the graph takes its correction, each
keyframe not in it its parent's (``corrections``); the driver moves the window and the
frames.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any, NamedTuple

import numpy as np

from ..config import Config
from ..geometry import inverse_np, log_np, orthonormalise_np
from ..workers import Worker
from . import pose_graph

#: the floor of an edge's standard deviation (m, degrees): a keyframe's drift from the last
#: (the tracker's bias), not the pixels' noise its solve's covariance counts
FLOOR_M, FLOOR_DEG = 0.002, 0.2
#: a loop edge whose Cauchy weight at the solution is under this is rejected: its whitened
#: error is over three times the kernel's scale, ~12 standard deviations
MIN_WEIGHT = 0.1
#: a loop the kernel left faint is kept when the graph solved as plain squares leaves every
#: edge's chi-square under this: chi-square's 99.9 % quantile with 6 degrees of freedom, so
#: each keyframe moved within its own uncertainty (drift spread, not a chain bent)
SPREAD_CHI2 = 22.46


def information(covariance: np.ndarray) -> np.ndarray:
    """An edge's information (6, 6) from its solve's covariance (6, 6) of a twist [v, w]:
    the inverse of the covariance plus the floor (module doc)."""
    floor = np.diag([FLOOR_M ** 2] * 3 + [np.radians(FLOOR_DEG) ** 2] * 3)
    cov = 0.5 * (np.asarray(covariance, np.float64) + np.asarray(covariance, np.float64).T)
    return np.linalg.inv(cov + floor)


class Edge(NamedTuple):
    """An edge of the pose graph: keyframes ``i`` (the older) and ``j``, the measured
    T_i_j (4, 4; None until measured), its information (6, 6) (of r in T_i^-1 T_j =
    Z exp(r)), whether it closes a loop, and how it was found."""

    i: int
    j: int
    measured: np.ndarray | None
    information: np.ndarray
    loop: bool = False
    note: str = ""


class Closed(NamedTuple):
    """A pose graph solved: the correction C = T_world_new_world_old of each keyframe it
    moved (id -> C (4, 4): its optimised pose times the inverse of its pose when submitted;
    none for the held ones, and none at all when the solve failed: ``finite``), the loop
    edges it kept and rejected, its size and its time on the worker (ms)."""

    moves: dict[int, np.ndarray]
    nodes: frozenset[int]
    kept: tuple[Edge, ...]
    rejected: tuple[Edge, ...]
    ms: float
    finite: bool = True

    @property
    def keyframes(self) -> int:
        """The graph's size (keyframes)."""
        return len(self.nodes)


class Loops:
    """The pose graph of one tracker (module doc)."""

    def __init__(self, config: Config) -> None:
        self.config = config
        self._odometry: dict[int, Edge] = {}  # child id -> its edge from its parent
        self.loops: list[Edge] = []  # loop edges not rejected, in the order found
        self.rejected: list[Edge] = []
        self._near: dict[int, set[int]] = {}  # the graph's adjacency
        self._worker = Worker("loops")
        self._pending = self._worker.queue(config.loop_lag)  # solves
        self._searches = self._worker.queue(config.loop_lag)  # tagged with the keyframe
        self._unsolved: list[Edge] = []  # loop edges no solve has held yet
        self.solved: list[Closed] = []  # every solve taken, in order
        self._warmed: set[int] = set()  # node slots whose program is compiled (or asked)
        self._count = 0  # keyframes told

    # -- what the tracker tells it --------------------------------------------------------
    def load(self, keys, edges: list[Edge]) -> None:
        """Start from a saved map's graph (``map.archive``): its keyframes ``keys`` (ids) and
        its measured ``edges``, each keyframe's from its parent and the loops kept; a loop
        between the saved keyframes and the new ones then moves both."""
        self._count += len(keys)
        for e in edges:
            if e.loop:
                self.loops.append(e)
            else:
                self._odometry[e.j] = e
            self._link(e.i, e.j)
        self._warm()

    def edges(self, keys) -> list[Edge]:
        """The measured edges between keyframes of ``keys`` (ids): each keyframe's from its
        parent, then the loops kept, in the order found (what a saved map keeps)."""
        keys = set(keys)
        return [e for e in (*self._odometry.values(), *self.loops)
                if e.measured is not None and e.i in keys and e.j in keys]

    def keyframe(self, key: int, parent: int | None, covariance: np.ndarray | None) -> None:
        """Keyframe ``key`` was made from a frame tracked against ``parent`` with this
        solve covariance (None, None: the first, or one made at a loss's guess)."""
        self._count += 1
        self._warm()
        if parent is None or covariance is None:
            return
        self._odometry[key] = Edge(parent, key, None, information(covariance))
        self._link(parent, key)

    def stats(self, kmap) -> dict:
        """``closed`` and ``rejected``, the loop edges kept and rejected (the two keyframes'
        ids and timestamps in ``kmap``, the measured T_older_newer, how the loop was found),
        and ``solves``: each solve taken (its keyframes, loops kept and rejected, time on the
        worker, ms, whether it was finite), in order."""
        def edge(e: Edge) -> dict:
            return {"older": e.i, "newer": e.j, "older_t": kmap[e.i].timestamp,
                    "newer_t": kmap[e.j].timestamp, "measured": e.measured.tolist(),
                    "note": e.note}
        return {"closed": [edge(e) for e in self.loops],
                "rejected": [edge(e) for e in self.rejected],
                "solves": [{"keyframes": c.keyframes, "kept": len(c.kept),
                            "rejected": len(c.rejected), "ms": c.ms, "finite": c.finite}
                           for c in self.solved]}

    def measure(self, key: int, poses) -> None:
        """Keyframe ``key``'s pose is final (refined): its edge from its parent takes their
        relative pose; ``poses``: the map (id -> entry with ``pose``)."""
        edge = self._odometry.get(key)
        if edge is None or edge.measured is not None or edge.i not in poses:
            return
        Z = inverse_np(poses[edge.i].pose) @ poses[key].pose
        self._odometry[key] = edge._replace(measured=Z)

    def tied(self, key: int) -> set[int]:
        """The keyframes the graph ties to ``key`` within twice ``window_size`` edges (itself
        included): not loop candidates. A loop is a place the graph reaches only by a long
        way round; nearer, the chain's own edges tie the two, and an alignment across the
        chain's wide baselines is where it is least sure."""
        seen, frontier = {key}, {key}
        for _ in range(2 * self.config.window_size):
            frontier = {n for k in frontier for n in self._near.get(k, ())} - seen
            seen |= frontier
        return seen

    def searches(self) -> bool:
        """Whether a new keyframe looks for a loop: when no search is in flight (one at a
        time, as the worker is one thread: a place needs one loop edge, not one per
        keyframe, and each search costs a few alignments of the worker's time)."""
        return not self._searches

    def search(self, key: int, verify: Callable[[], Any], frame_index: int) -> None:
        """Run the loop search of keyframe ``key`` (``tracking.places.Places.loop``: a
        ``Placed`` or None) on the worker; what it finds joins the graph at ``frame_index +
        loop_lag`` (``found``)."""
        self._searches.submit(frame_index, key, verify)

    def found(self, frame_index: int | None) -> list[Edge]:
        """The loops found by the searches due at ``frame_index`` (None: all; waited for), in
        the order asked, as edges of the graph (``add``)."""
        out = []
        for key, placed in self._searches.due(frame_index):
            if placed is not None:
                out.append(self.add(placed.keyframe.id, key, placed.result.T_c_k,
                                    placed.result.covariance, placed.note))
        return out

    def add(self, older: int, newer: int, T_new_old: np.ndarray, covariance: np.ndarray,
            note: str) -> Edge:
        """A verified loop: keyframe ``newer`` aligned to ``older`` with the solve T_new_old
        and its covariance (of a left twist in ``newer``'s frame). The edge is solved in
        the next graph that holds both (``submit``)."""
        edge = Edge(older, newer, inverse_np(np.asarray(T_new_old, np.float64)),
                    information(np.asarray(covariance, np.float64)), loop=True, note=note)
        self.loops.append(edge)
        self._unsolved.append(edge)
        self._link(older, newer)
        self._warm()
        return edge

    def submit(self, kmap, frame_index: int) -> bool:
        """Solve the graph of ``kmap`` (the keyframe map) on the worker when no solve is
        pending and a loop edge waits whose keyframes are both in it and that disagrees with
        the map (its chi-square at the map's poses over the robust kernel's scale squared: a
        loop the map already agrees with changes nothing, and joins the next solve); it is
        due at ``frame_index + loop_lag``. The graph holds the anchored keyframes whose pose
        is final (their edge from their parent measured; those without a parent); the others
        move with their parents (``corrections``). Whether it did."""
        if self._pending or not self._unsolved:
            return False
        nodes = [k for k in kmap.ids if kmap[k].anchored and (
            k not in self._odometry or self._odometry[k].measured is not None)]
        index = {k: n for n, k in enumerate(nodes)}
        held = [e for e in self._unsolved if e.i in index and e.j in index]
        if not held:
            return False
        self._unsolved = [e for e in self._unsolved if not (e.i in index and e.j in index)]
        if max(chi2(e, kmap) for e in held) <= pose_graph.ROBUST_SCALE ** 2:
            return False
        edges = [e for e in (*self._odometry.values(), *self.loops)
                 if e.measured is not None and e.i in index and e.j in index]
        poses = np.stack([kmap[k].pose for k in nodes])
        self._pending.submit(frame_index, None, _solve, nodes, poses, edges,
                             _oldest_of_parts(nodes, edges), _slots(len(nodes)))
        return True

    def due(self, frame_index: int | None) -> Closed | None:
        """The solve due at ``frame_index`` (None: any submitted), waited for; None when none
        is due. Rejected loop edges leave the graph."""
        taken = self._pending.due(frame_index)
        if not taken:
            return None
        (_, closed), = taken  # one solve in flight at a time
        for edge in closed.rejected:
            self.loops = [e for e in self.loops if e is not edge]
            self.rejected.append(edge)
            self._near[edge.i].discard(edge.j)
            self._near[edge.j].discard(edge.i)
        self.solved.append(closed)
        return closed

    def corrections(self, closed: Closed, keys) -> dict[int, np.ndarray]:
        """C = T_world_new_world_old of each keyframe of ``keys`` (ids) that moves: a
        keyframe of the graph by its own, a keyframe made since it was submitted (not in it)
        by its parent's (none without a parent that moved)."""
        out: dict[int, np.ndarray] = {}
        for key in sorted(keys):
            if key in closed.moves:
                out[key] = closed.moves[key]
            elif key not in closed.nodes:
                edge = self._odometry.get(key)
                if edge is not None and edge.i in out:
                    out[key] = out[edge.i]
        return out

    def close(self) -> None:
        """Stop the worker (searches and a solve not taken are dropped)."""
        self._pending.clear()
        self._searches.clear()
        self._worker.close()

    def _warm(self) -> None:
        """Once a loop is found, compile (or load) on the worker the program of the graph's
        size, and of the next size once the map fills half of this one's (``_slots``): a
        run that finds no loop pays nothing, and no later solve waits for a compilation."""
        if not self.loops:
            return
        slots = _slots(self._count)
        for size in (slots, 4 * slots if self._count >= slots // 2 else slots):
            if size not in self._warmed:
                self._warmed.add(size)
                self._worker.run(_compile, size)

    def _link(self, a: int, b: int) -> None:
        self._near.setdefault(a, set()).add(b)
        self._near.setdefault(b, set()).add(a)


def chi2(edge: Edge, kmap) -> float:
    """An edge's chi-square r^T Omega r at the poses of ``kmap`` (id -> entry with ``pose``),
    r = log(Z^-1 T_i^-1 T_j) as in ``pose_graph``."""
    r = log_np(inverse_np(edge.measured) @ inverse_np(kmap[edge.i].pose) @ kmap[edge.j].pose)
    return float(r @ edge.information @ r)


def _oldest_of_parts(nodes: list[int], edges: list[Edge]) -> list[int]:
    """The first node (by position) of each connected part of the graph: its gauge."""
    parent = list(range(len(nodes)))
    index = {k: n for n, k in enumerate(nodes)}

    def root(n: int) -> int:
        while parent[n] != n:
            parent[n] = parent[parent[n]]
            n = parent[n]
        return n

    for e in edges:
        a, b = root(index[e.i]), root(index[e.j])
        if a != b:
            parent[max(a, b)] = min(a, b)
    return sorted({root(n) for n in range(len(nodes))})


def _slots(n: int) -> int:
    """The graph's padded size (node slots) for ``n`` keyframes: a power of four, at least
    256 (a program compiles in seconds: few sizes, each compiled once); its edge slots are
    twice as many (each keyframe brings an edge from its parent and at most one loop)."""
    slots = 256
    while slots < n:
        slots *= 4
    return slots


def _compile(slots: int) -> None:
    """Compile (or load) the program of graphs of ``slots`` nodes: one solve of an empty
    graph of that size."""
    eye = np.eye(4)[None]
    pose_graph.optimise(pose_graph.graph(eye, [], fixed=[0], nodes=slots,
                                         edge_slots=2 * slots)).poses.block_until_ready()


def _faint(edges: list[Edge], solution) -> list[int]:
    """The loop edges (their positions in ``edges``) the solution's Cauchy kernel left under
    ``MIN_WEIGHT``."""
    weight = np.asarray(solution.weight)[:len(edges)]
    return [n for n, (e, w) in enumerate(zip(edges, weight, strict=True))
            if e.loop and w < MIN_WEIGHT]


def _spread(poses: np.ndarray, edges: list[Edge], index: dict[int, int], fixed: list[int],
            slots: int):
    """A loop after real drift: from the drifted chain, the kernel hears a loop that is
    metres or tens of degrees off so faintly that it leaves it open. Solved as plain squares
    the loop spreads its error over the chain; where every edge then stays within
    ``SPREAD_CHI2`` (each keyframe moved within its uncertainty: drift), the robust solve
    from there is the solution; else (a wrong loop bends the chain past what drift
    explains) None."""
    plain = _optimised(poses, edges, index, fixed, slots, robust=False)
    chi2 = np.asarray(plain.chi2)[:len(edges)]
    start = np.asarray(plain.poses, np.float64)[:len(index)]
    if not (np.isfinite(start).all() and np.isfinite(chi2).all()) \
            or chi2.max() > SPREAD_CHI2:
        return None
    return _optimised(start, edges, index, fixed, slots, robust=True)


def _optimised(poses: np.ndarray, edges: list[Edge], index: dict[int, int], fixed: list[int],
               slots: int, *, robust: bool):
    """``pose_graph.optimise`` of the graph from ``poses`` (n, 4, 4) in ``slots`` node slots;
    ``robust``: loop edges under the Cauchy kernel (else every edge plain squares)."""
    graph = pose_graph.graph(
        poses, [(index[e.i], index[e.j], e.measured, e.information, e.loop and robust)
                for e in edges], fixed=fixed, nodes=slots, edge_slots=2 * slots)
    return pose_graph.optimise(graph)


def _solve(nodes: list[int], poses: np.ndarray, edges: list[Edge], fixed: list[int],
           slots: int) -> Closed:
    """Optimise the graph in ``slots`` node slots; a loop edge left under ``MIN_WEIGHT`` is
    rejected (the worst first) and the graph solved again without it, unless its error is
    drift the graph can spread (``_spread``) (module doc)."""
    t0 = time.perf_counter()
    index = {k: n for n, k in enumerate(nodes)}
    rejected: list[Edge] = []
    while True:
        solution = _optimised(poses, edges, index, fixed, slots, robust=True)
        bad = _faint(edges, solution)
        if bad:
            spread = _spread(poses, edges, index, fixed, slots)
            if spread is not None:
                solution = spread
                bad = _faint(edges, solution)
        if not bad:
            break
        weight = np.asarray(solution.weight)[:len(edges)]
        worst = min(bad, key=lambda n: weight[n])  # one at a time, worst first
        rejected.append(edges[worst])
        edges = edges[:worst] + edges[worst + 1:]
    out = np.asarray(solution.poses, np.float64)[:len(nodes)]
    finite = bool(np.isfinite(out).all())
    held = set(fixed) | (set(range(len(nodes))) - {index[k] for e in edges for k in (e.i, e.j)})
    moves = {} if not finite else {
        k: orthonormalise_np(out[n]) @ inverse_np(poses[n]) for k, n in index.items()
        if n not in held}
    return Closed(moves, frozenset(nodes), tuple(e for e in edges if e.loop), tuple(rejected),
                  (time.perf_counter() - t0) * 1e3, finite)
