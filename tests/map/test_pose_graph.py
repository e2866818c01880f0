"""The pose graph (``backend.pose_graph``): it recovers consistent graphs, closes a drifting
loop, shrugs off a false loop, its edge Jacobians match finite differences and jax.jacfwd
(at exactly zero residual too), its implicit derivative matches finite differences of
re-running it, padding and vmap change nothing, and fixed nodes stay put; the direct solve
(the default) and the conjugate gradients agree, and 1,000 keyframes converge. float64
(``jax.enable_x64``) unless a test says otherwise; most float64 runs share one padded shape
(64 nodes, 64 edges) and one set of options, so they share one compiled program."""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from edgevo_jax.geometry import Pose, exp_np, inverse_np, log_np
from edgevo_jax.map import pose_graph as pg
from edgevo_jax.map.pose_graph import PoseGraph, graph, optimise
from edgevo_jax.map.synthetic_graphs import cost as synthetic_cost
from edgevo_jax.map.synthetic_graphs import laps

#: converged to float64 precision (the derivative is checked against finite differences)
TIGHT = dict(iterations=60, step_tol=1e-12, cost_tol=0.0, cg_iterations=400, cg_tol=1e-12)
seeds = st.integers(0, 2**31 - 1)


def random_twist(rng: np.random.Generator, t: float, r: float) -> np.ndarray:
    return np.concatenate([rng.normal(size=3) * t, rng.normal(size=3) * r])


def spd(rng: np.random.Generator, sigma_t: float, sigma_r: float) -> np.ndarray:
    """An information matrix: the inverse of a mildly correlated covariance."""
    L = np.diag([sigma_t] * 3 + [sigma_r] * 3) @ (np.eye(6) + 0.2 * rng.normal(size=(6, 6)))
    return np.linalg.inv(L @ L.T)


def relative(truth: np.ndarray, a: int, b: int, noise: np.ndarray | None = None) -> np.ndarray:
    """Z_ab = T_a^-1 T_b exp(-noise): the edge whose error at the truth is ``noise``."""
    Z = inverse_np(truth[a]) @ truth[b]
    return Z if noise is None else Z @ exp_np(-noise)


def circle(n: int, radius: float, laps: float = 1.0) -> np.ndarray:
    """n poses around a circle (looking along it, a little tilt and height wobble)."""
    out = np.zeros((n, 4, 4))
    for k in range(n):
        a = 2.0 * np.pi * laps * k / n
        tilt = [0.05 * np.sin(3 * a), 0.03 * np.cos(2 * a), a + np.pi / 2]
        out[k] = exp_np(np.array([0.0, 0.0, 0.0, *tilt]))
        out[k, :3, 3] = [radius * np.cos(a), radius * np.sin(a), 0.1 * np.sin(2 * a)]
    return out


def perturbed(rng: np.random.Generator, poses: np.ndarray, t: float, r: float) -> np.ndarray:
    return np.stack([exp_np(random_twist(rng, t, r)) @ T for T in poses])


def position_error(poses, truth: np.ndarray) -> float:
    d = np.asarray(poses)[: len(truth), :3, 3] - truth[:, :3, 3]
    return float(np.sqrt(np.mean(np.sum(d * d, axis=1))))


def random_graph(seed: int, noise: float) -> tuple[PoseGraph, np.ndarray, int]:
    """A small random graph (3-6 nodes, a chain plus extra edges, one of them robust, node 0
    fixed), measurements off the truth by ``noise``, float64; also its truth and the robust
    edge's index."""
    rng = np.random.default_rng(seed)
    n = int(rng.integers(3, 7))
    truth = np.stack([exp_np(random_twist(rng, 1.0, 0.6)) for _ in range(n)])
    truth[0] = np.eye(4)
    pairs = [(k - 1, k) for k in range(1, n)] + [(0, n - 1), (int(rng.integers(0, n - 1)), n - 1)]
    edges = []
    for k, (a, b) in enumerate(pairs):
        robust = k == len(pairs) - 1
        info = spd(rng, 0.05, 0.03) if not robust else 4.0 * np.eye(6)
        # the robust edge's error is ~c, where its Cauchy kernel bends most
        r = random_twist(rng, noise, noise) * (30.0 if robust else 1.0)
        edges.append((a, b, relative(truth, a, b, r), info, robust))
    start = truth.copy()
    start[1:] = perturbed(rng, truth[1:], 0.05, 0.03)
    return graph(start, edges, fixed=[0], dtype=np.float64), truth, len(pairs) - 1


# -- 1-3, 7: what the solution is ----------------------------------------------------------


@given(seed=seeds)
@settings(max_examples=5, deadline=None)
def test_consistent_measurements_recover_the_truth(seed):
    with jax.enable_x64(True):
        rng = np.random.default_rng(seed)
        truth = circle(8, 1.0)
        truth = perturbed(rng, truth, 0.1, 0.1)
        pairs = [(k, k + 1) for k in range(7)] + [(7, 0), (2, 5), (1, 6)]
        edges = [(a, b, relative(truth, a, b), spd(rng, 0.01, 0.01), a == 2) for a, b in pairs]
        start = truth.copy()
        start[1:] = perturbed(rng, truth[1:], 0.1, 0.1)
        sol = optimise(graph(start, edges, fixed=[0], dtype=np.float64), **TIGHT)
        np.testing.assert_allclose(np.asarray(sol.poses[:8]), truth, atol=1e-9)
        assert np.all(np.asarray(sol.chi2) < 1e-16)
        assert float(sol.cost) < 1e-16
        np.testing.assert_array_equal(np.asarray(sol.weight), [1.0] * len(pairs) + [0.0] * 54)


def drifting_loop(robust: bool, dtype) -> tuple[PoseGraph, np.ndarray]:
    """20 nodes around a circle of radius 2 m; odometry edges carry a constant rotation drift
    (2 mrad of roll and 5 mrad of yaw per edge); a loop edge 19 -> 0 measures the true
    relative pose."""
    truth = circle(20, 2.0)
    drift = np.array([0.0, 0.0, 0.0, 0.002, 0.0, 0.005])
    info = np.diag([1e4] * 3 + [4e4] * 3)
    edges = [(k, k + 1, relative(truth, k, k + 1, drift), info, False) for k in range(19)]
    chain = [truth[0]]
    for _, _, Z, _, _ in edges:
        chain.append(chain[-1] @ Z)
    edges.append((19, 0, relative(truth, 19, 0), info, robust))
    return graph(np.stack(chain), edges, fixed=[0], dtype=dtype), truth


@pytest.mark.parametrize("robust", [False, True])
def test_a_loop_edge_spreads_the_drift(robust):
    with jax.enable_x64(True):
        g, truth = drifting_loop(robust, np.float64)
        sol = optimise(g, **TIGHT)
        before, after = position_error(g.poses, truth), position_error(sol.poses, truth)
        assert before > 0.1
        assert after < 0.1 * before
        # the loop closes: the odometry edges take the drift (its chi2 was ~1200 at the start)
        r = log_np(inverse_np(np.asarray(g.measured[19])) @ inverse_np(np.asarray(g.poses[19]))
                   @ np.asarray(g.poses[0]))
        assert float(sol.chi2[19]) < 0.01 * (r @ np.asarray(g.information[19]) @ r)


def test_a_loop_edge_spreads_the_drift_in_float32_with_the_defaults():
    g, truth = drifting_loop(True, np.float32)
    sol = optimise(g)
    assert sol.poses.dtype == jnp.float32
    assert position_error(sol.poses, truth) < 0.3 * position_error(g.poses, truth)
    with jax.enable_x64(True):
        ref = optimise(drifting_loop(True, np.float64)[0], **TIGHT)
    np.testing.assert_allclose(np.asarray(sol.poses), np.asarray(ref.poses), atol=1e-4)


def laps_with_loops(false_loop: bool | None) -> tuple[PoseGraph, np.ndarray]:
    """Three laps of 12 nodes around a circle with noisy odometry, a robust true loop edge
    every 3 nodes to the previous lap, and a false loop (robust if ``false_loop``, plain if
    False, none if None): nodes 3 and 9, 4 m apart, claimed to coincide."""
    rng = np.random.default_rng(7)
    truth = circle(36, 2.0, laps=3.0)
    odo = spd(rng, 0.01, 0.005)
    loop = np.diag([2500.0] * 3 + [1e4] * 3)  # 2 cm, 10 mrad
    edges = [(k, k + 1, relative(truth, k, k + 1, random_twist(rng, 0.01, 0.005)), odo, False)
             for k in range(35)]
    edges += [(k - 12, k, relative(truth, k - 12, k, random_twist(rng, 0.02, 0.01)), loop, True)
              for k in range(12, 36, 3)]
    if false_loop is not None:
        edges.append((3, 9, np.eye(4), loop, false_loop))
    chain = [truth[0]]
    for _, _, Z, _, _ in edges[:35]:
        chain.append(chain[-1] @ Z)
    return graph(np.stack(chain), edges, fixed=[0], dtype=np.float64), truth


def test_a_false_loop_loses_its_weight():
    with jax.enable_x64(True):
        g, truth = laps_with_loops(True)
        sol = optimise(g, **TIGHT)
        ref = np.asarray(optimise(laps_with_loops(None)[0], **TIGHT).poses)[:36]
        k = int(np.sum(np.asarray(g.valid))) - 1
        assert float(sol.weight[k]) < 0.05
        assert np.all(np.asarray(sol.weight[:k]) > 0.5)  # the true loops keep theirs
        assert position_error(sol.poses, ref) < 0.01
        # the same edge without the kernel bends the map
        plain = optimise(laps_with_loops(False)[0], **TIGHT)
        assert position_error(plain.poses, ref) > 0.3


def test_fixed_and_unconstrained_nodes_do_not_move():
    with jax.enable_x64(True):
        rng = np.random.default_rng(3)
        truth = circle(6, 1.0)
        start = perturbed(rng, truth, 0.05, 0.05)  # fixed nodes 0 and 2 are off the truth too
        edges = [(a, b, relative(truth, a, b), spd(rng, 0.01, 0.01), False)
                 for a, b in [(0, 1), (1, 2), (2, 3), (3, 4), (0, 4)]]  # node 5: no edge
        g = graph(start, edges, fixed=[0, 2], dtype=np.float64)
        sol = optimise(g, **TIGHT)
        poses, start_dev = np.asarray(sol.poses), np.asarray(g.poses)
        for k in (0, 2, 5, 6, 63):  # fixed, unconstrained, padding
            np.testing.assert_array_equal(poses[k], start_dev[k])
        for k in (1, 3, 4):
            assert np.abs(poses[k] - start_dev[k]).max() > 1e-3


def test_graph_checks_its_input():
    eye = np.eye(4)
    edge = (0, 1, eye, np.eye(6), False)
    with pytest.raises(ValueError, match="fixed"):
        graph(np.stack([eye, eye]), [edge], fixed=[])
    with pytest.raises(ValueError, match="outside"):
        graph(np.stack([eye, eye]), [(0, 2, eye, np.eye(6), False)], fixed=[0])
    with pytest.raises(ValueError, match="slots"):
        graph(np.stack([eye, eye]), [edge], fixed=[0], nodes=1)
    g = graph(np.stack([eye] * 70), [edge] * 3, fixed=[0])
    assert g.poses.shape == (128, 4, 4) and g.measured.shape == (64, 4, 4)
    assert g.poses.dtype == jnp.float32 and g.i.dtype == jnp.int32
    assert np.asarray(g.fixed)[70:].all() and not np.asarray(g.valid)[3:].any()


# -- 4: the edge Jacobians -----------------------------------------------------------------


def moved(T: Pose, d: jnp.ndarray) -> Pose:
    """exp(d) T to first order (``pose_graph._moved`` of one pose): the same derivative at
    d = 0 as ``T.retract(d)``, without ``Pose.exp`` in the program."""
    out = pg._moved(Pose(T.R[None], T.t[None]), d[None])
    return Pose(out.R[0], out.t[0])


@jax.jit
def jacobians(Ti: Pose, Tj: Pose, Z: Pose):
    """r = log(Z^-1 T_i^-1 T_j) and its derivative (6, 18) in left twists d = [d_i, d_j, d_Z]
    of T_i, T_j and Z by ``geometry`` (its ``log``) and jax.jacfwd; the module's r, A (its
    derivative in d_j) and its custom JVP's derivative."""

    def error(d):
        Ti_, Tj_, Z_ = (moved(T, d[6 * k:6 * k + 6]) for k, T in enumerate((Ti, Tj, Z)))
        return (Z_.inverse() @ (Ti_.inverse() @ Tj_)).log()

    def ours(d):
        return pg._edge_error(*(moved(T, d[6 * k:6 * k + 6]) for k, T in enumerate((Ti, Tj, Z))))

    zero = jnp.zeros(18, Ti.R.dtype)
    r = pg._edge_error(Ti, Tj, Z)
    return error(zero), jax.jacfwd(error)(zero), r, pg._jacobian(r, Tj), jax.jacfwd(ours)(zero)


def finite_differences(Ti: Pose, Tj: Pose, Z: Pose, h: float = 1e-6) -> np.ndarray:
    """The derivative (6, 18) of ``jacobians`` by central differences on the host twin."""
    Ti, Tj, Z = (np.asarray(T.as_matrix()) for T in (Ti, Tj, Z))

    def error(d):
        return log_np(inverse_np(exp_np(d[12:]) @ Z) @ inverse_np(exp_np(d[:6]) @ Ti)
                      @ exp_np(d[6:12]) @ Tj)

    steps = h * np.eye(18)
    return np.stack([(error(s) - error(-s)) / (2 * h) for s in steps], axis=1)


def check_jacobian(Ti: Pose, Tj: Pose, Z: Pose, atol_fd: float) -> None:
    r_ref, ref, r, A, jvp = (np.asarray(a) for a in jacobians(Ti, Tj, Z))
    fd = finite_differences(Ti, Tj, Z)
    assert np.all(np.isfinite(ref))
    np.testing.assert_allclose(r, r_ref, atol=1e-12)
    analytic = np.concatenate([-A, A], axis=1)
    np.testing.assert_allclose(analytic, ref[:, :12], atol=1e-10)
    np.testing.assert_allclose(analytic, fd[:, :12], atol=atol_fd)
    np.testing.assert_allclose(jvp, ref, atol=1e-10)  # d_Z too
    np.testing.assert_allclose(jvp, fd, atol=atol_fd)


@pytest.mark.parametrize("size", [1e-7, 0.05, 0.3, 1.0, 2.5])
@given(seed=seeds)
@settings(max_examples=4, deadline=None)
def test_edge_jacobian_matches_jacfwd_and_finite_differences(size, seed):
    """|w| of the error on both sides of the series' threshold (0.1 in float64)."""
    with jax.enable_x64(True):
        rng = np.random.default_rng(seed)
        Ti, Tj = (Pose.exp(jnp.asarray(random_twist(rng, 1.0, 1.0))) for _ in range(2))
        error = random_twist(rng, size, size)
        error[3:] *= size / np.linalg.norm(error[3:])  # |w| = size
        Z = Ti.inverse() @ Tj @ Pose.exp(jnp.asarray(-error))
        check_jacobian(Ti, Tj, Z, atol_fd=1e-7)


def exact_graph() -> PoseGraph:
    """Quarter turns and integer translations: every edge's Z^-1 T_i^-1 T_j is the identity
    exactly, at the start and at the solution."""
    quarter = np.array([[0.0, -1.0, 0.0, 1.0], [1.0, 0.0, 0.0, 2.0], [0.0, 0.0, 1.0, 0.0],
                        [0.0, 0.0, 0.0, 1.0]])
    poses = [np.eye(4)]
    for k in range(4):
        step = quarter.copy()
        step[:3, 3] = [1.0, k, -1.0]
        poses.append(poses[-1] @ step)
    poses = np.stack(poses)
    pairs = [(0, 1), (1, 2), (2, 3), (3, 4), (0, 4), (1, 3)]
    rng = np.random.default_rng(0)
    edges = [(a, b, inverse_np(poses[a]) @ poses[b], spd(rng, 0.05, 0.03), a == 1 and b == 3)
             for a, b in pairs]
    return graph(poses, edges, fixed=[0], dtype=np.float64)


def test_exactly_zero_residuals_have_finite_jacobians_and_derivatives():
    with jax.enable_x64(True):
        g = exact_graph()
        x = Pose(g.poses[:, :3, :3], g.poses[:, :3, 3])
        Z = Pose(g.measured[:, :3, :3], g.measured[:, :3, 3])
        for k in range(6):
            Ti, Tj = (Pose(x.R[n], x.t[n]) for n in (int(g.i[k]), int(g.j[k])))
            Zk = Pose(Z.R[k], Z.t[k])
            np.testing.assert_array_equal(np.asarray(jacobians(Ti, Tj, Zk)[0]), 0.0)
            check_jacobian(Ti, Tj, Zk, atol_fd=1e-8)
        sol = optimise(g, **TIGHT)
        np.testing.assert_array_equal(np.asarray(sol.chi2), 0.0)
        np.testing.assert_array_equal(np.asarray(sol.poses), np.asarray(g.poses))
        rng = np.random.default_rng(1)
        u = jnp.asarray(rng.normal(size=(64, 4, 4)))
        xi = random_twist(rng, 0.3, 0.3)
        for k in (0, 5):
            _, d_m, d_o = probe_grad(g.poses, g, u, jnp.asarray(xi), k, 0.0, 0.0)
            assert np.isfinite(float(d_m)) and float(d_o) == 0.0  # no error, no information
            fd = (run_probe(g, u, xi, k, 1e-4, 0.0) - run_probe(g, u, xi, k, -1e-4, 0.0)) / 2e-4
            np.testing.assert_allclose(float(d_m), fd, rtol=1e-4, atol=1e-8)


# -- 5: the implicit derivative ------------------------------------------------------------


def probe(poses, g: PoseGraph, u, xi, k, s_m, s_o, solver="direct"):
    """sum(u * optimised poses) with edge k's measurement moved by exp(s_m xi) on the right
    and its information scaled by 1 + s_o (the LM's steps and the adjoint by ``solver``)."""
    measured = g.measured.at[k].set(g.measured[k] @ Pose.exp(s_m * xi).as_matrix())
    information = g.information.at[k].multiply(1.0 + s_o)
    sol = optimise(g._replace(poses=poses, measured=measured, information=information),
                   linear_solver=solver, **TIGHT)
    return jnp.sum(u * sol.poses)


probe_grad = jax.jit(jax.grad(probe, argnums=(0, 5, 6)))
probe_grad_cg = jax.jit(jax.grad(partial(probe, solver="cg"), argnums=(0, 5, 6)))


@given(seed=seeds, noise=st.sampled_from([0.0, 0.05]), on_robust=st.booleans())
@settings(max_examples=8, deadline=None)
def test_implicit_derivative_matches_finite_differences(seed, noise, on_robust):
    with jax.enable_x64(True):
        g, truth, robust = random_graph(seed, noise)
        n = len(truth)
        rng = np.random.default_rng(seed + 1)
        u = np.zeros((64, 4, 4))
        u[:n] = rng.normal(size=(n, 4, 4))
        xi = random_twist(rng, 0.3, 0.3)
        k = robust if on_robust else int(rng.integers(0, robust))
        args = (jnp.asarray(u), jnp.asarray(xi), k)
        d_poses, d_m, d_o = probe_grad(g.poses, g, *args, 0.0, 0.0)
        np.testing.assert_array_equal(np.asarray(d_poses), 0.0)  # the start is a constant
        h = 1e-4
        for d, (plus, minus) in ((d_m, ((h, 0.0), (-h, 0.0))), (d_o, ((0.0, h), (0.0, -h)))):
            fd = (run_probe(g, u, xi, k, *plus) - run_probe(g, u, xi, k, *minus)) / (2 * h)
            np.testing.assert_allclose(float(d), fd, rtol=1e-4, atol=1e-8)


def run_probe(g: PoseGraph, u, xi, k, s_m, s_o) -> float:
    """``probe`` by a plain ``optimise`` call (the float64 program the other tests compile)."""
    measured = np.array(g.measured)
    measured[k] = measured[k] @ exp_np(s_m * xi)
    information = np.array(g.information)
    information[k] *= 1.0 + s_o
    sol = optimise(g._replace(measured=jnp.asarray(measured), information=jnp.asarray(information)),
                   **TIGHT)
    return float(np.sum(u * np.asarray(sol.poses)))


# -- 6: padding and batching ---------------------------------------------------------------


@pytest.mark.parametrize("solver", ["direct", "cg"])
def test_padding_and_vmap_change_nothing(solver):
    """Two graphs padded further (80 nodes, 100 edges) and solved in one vmapped call give
    the runs of each alone at the default padding, by either linear solver (the host's LU
    one graph after another, the device's PCG batched)."""
    with jax.enable_x64(True):
        rng = np.random.default_rng(11)
        truth = circle(10, 1.5)
        start = perturbed(rng, truth, 0.05, 0.05)
        start[0] = truth[0]

        def edges(seed):
            r = np.random.default_rng(seed)
            pairs = [(k, k + 1) for k in range(9)] + [(9, 0), (2, 7)]
            return [(a, b, relative(truth, a, b, random_twist(r, 0.02, 0.01)), spd(r, 0.01, 0.01),
                     a == 9) for a, b in pairs]

        alone = [optimise(graph(start, edges(s), fixed=[0], dtype=np.float64),
                          linear_solver=solver, **TIGHT) for s in (1, 2)]
        assert float(alone[0].cost) != float(alone[1].cost)
        padded = [graph(start, edges(s), fixed=[0], nodes=80, edge_slots=100, dtype=np.float64)
                  for s in (1, 2)]
        both = jax.vmap(lambda g: optimise(g, linear_solver=solver, **TIGHT))(
            jax.tree.map(lambda *a: jnp.stack(a), *padded))
        for b, s in enumerate(alone):
            np.testing.assert_allclose(np.asarray(both.poses[b, :64]), np.asarray(s.poses),
                                       atol=1e-12)
            np.testing.assert_array_equal(np.asarray(both.poses[b, 64:]),
                                          np.eye(4)[None].repeat(16, 0))
            np.testing.assert_allclose(np.asarray(both.chi2[b, :64]), np.asarray(s.chi2),
                                       atol=1e-12)
            np.testing.assert_array_equal(np.asarray(both.chi2[b, 64:]), 0.0)
            np.testing.assert_allclose(float(both.cost[b]), float(s.cost), rtol=1e-12)


# -- 8: the direct solve against the conjugate gradients, and at scale -----------------------


@pytest.mark.parametrize("seed", [3, 4])
def test_the_direct_solve_and_the_conjugate_gradients_agree(seed):
    """The same optimum, and the same implicit derivative, by either linear solver."""
    with jax.enable_x64(True):
        g, truth, robust = random_graph(seed, 0.05)
        direct, cg = (optimise(g, linear_solver=s, **TIGHT) for s in ("direct", "cg"))
        np.testing.assert_allclose(np.asarray(direct.poses), np.asarray(cg.poses), atol=1e-9)
        np.testing.assert_allclose(float(direct.cost), float(cg.cost), rtol=1e-12)
        np.testing.assert_allclose(np.asarray(direct.weight), np.asarray(cg.weight), atol=1e-9)
        rng = np.random.default_rng(seed)
        u = np.zeros((64, 4, 4))
        u[:len(truth)] = rng.normal(size=(len(truth), 4, 4))
        args = (jnp.asarray(u), jnp.asarray(random_twist(rng, 0.3, 0.3)))
        for k in (0, robust):
            ours = probe_grad(g.poses, g, *args, k, 0.0, 0.0)
            ref = probe_grad_cg(g.poses, g, *args, k, 0.0, 0.0)
            for a, b in zip(ours[1:], ref[1:], strict=True):
                np.testing.assert_allclose(float(a), float(b), rtol=1e-7, atol=1e-10)


def test_a_thousand_keyframes_converge_in_float32_the_same_bits_every_call():
    """The laps of 1,000 keyframes (scripts/pose_graph_time.py's) with the defaults: well
    inside the LM budget, at the float64 optimum's cost, ATE down, and bit for bit again."""
    g, truth, _ = laps(1000)
    sol = optimise(g)
    assert int(sol.iterations) < 15  # of 30
    again = optimise(g)
    for a, b in zip(sol, again, strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    with jax.enable_x64(True):
        ref = optimise(laps(1000, dtype=np.float64)[0], iterations=60, step_tol=1e-10, cost_tol=0.0)
        assert int(ref.iterations) < 60
        best = synthetic_cost(g, ref.poses)
    assert synthetic_cost(g, sol.poses) < best * (1 + 1e-6)
    assert position_error(sol.poses, truth) < 0.3 * position_error(g.poses, truth)
