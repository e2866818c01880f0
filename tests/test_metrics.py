"""Tests for edgevo_jax.metrics: association, Horn alignment, ATE and RPE."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from edgevo_jax.io import matrices_to_poses7, quat_to_rotmat
from edgevo_jax.metrics import associate_timestamps, ate, horn_align, rpe_per_second


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=4)
    return quat_to_rotmat(q[None] / np.linalg.norm(q))[0]


def rot_z(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def make_poses7(rotations: np.ndarray, positions: np.ndarray) -> np.ndarray:
    mats = np.tile(np.eye(4), (len(positions), 1, 1))
    mats[:, :3, :3] = rotations
    mats[:, :3, 3] = positions
    return matrices_to_poses7(mats)


def reference_associate(first, second, offset=0.0, max_difference=0.02):
    """Direct transcription of the TUM benchmark's associate.py (quadratic)."""
    first_keys = list(first)
    second_keys = list(second)
    potential = sorted(
        (abs(a - (b + offset)), a, b)
        for a in first_keys
        for b in second_keys
        if abs(a - (b + offset)) < max_difference
    )
    matches = []
    for _, a, b in potential:
        if a in first_keys and b in second_keys:
            first_keys.remove(a)
            second_keys.remove(b)
            matches.append((a, b))
    return sorted(matches)


def reference_align(model, data):
    """Transcription of the TUM benchmark's align() (evaluate_ate.py), without np.matrix."""
    mz = model - model.mean(1, keepdims=True)
    dz = data - data.mean(1, keepdims=True)
    w = np.zeros((3, 3))
    for column in range(model.shape[1]):
        w += np.outer(mz[:, column], dz[:, column])
    u, _, vh = np.linalg.svd(w.T)
    s = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vh) < 0:
        s[2, 2] = -1
    rot = u @ s @ vh
    trans = data.mean(1) - rot @ model.mean(1)
    err = np.sqrt(np.sum((rot @ model + trans[:, None] - data) ** 2, 0))
    return rot, trans, err


# ----------------------------------------------------------------------------- association


def test_associate_hand_made_greedy_one_to_one():
    first = np.array([0.0, 0.10, 0.115, 0.30, 0.50])
    second = np.array([0.012, 0.108, 0.31, 0.49, 0.9])
    # 0.108 is a candidate for both 0.10 (diff 0.008) and 0.115 (diff 0.007): the closer one
    # takes it and 0.10 stays unmatched, though its own nearest is 0.108.
    pairs = associate_timestamps(first, second)
    assert pairs.tolist() == [[0, 0], [2, 1], [3, 2], [4, 3]]
    assert pairs.dtype.kind == "i" and pairs.shape == (4, 2)


def test_associate_greedy_by_global_order():
    # 1.000 has candidates 0.990 (0.010) and 1.008 (0.008); 1.010 takes 1.008 (0.002) first,
    # so 1.000 falls back to 0.990.
    first = np.array([1.000, 1.010])
    second = np.array([0.990, 1.008])
    assert associate_timestamps(first, second).tolist() == [[0, 0], [1, 1]]


def test_associate_strict_window_offset_and_empty():
    assert associate_timestamps(np.array([0.0]), np.array([0.5]), max_diff=0.5).shape == (0, 2)
    assert associate_timestamps(np.array([0.0]), np.array([0.5]), 0.5 + 1e-6).tolist() == [[0, 0]]
    # second + offset is compared with first.
    first = np.array([10.0, 11.0, 12.0])
    second = np.array([12.0, 10.0, 11.0]) - 5.0
    assert associate_timestamps(first, second, offset=5.0).tolist() == [[0, 1], [1, 2], [2, 0]]
    assert associate_timestamps(first, second).shape == (0, 2)
    assert associate_timestamps(np.array([]), second).shape == (0, 2)
    with pytest.raises(ValueError, match="max_diff"):
        associate_timestamps(first, second, max_diff=0.0)
    with pytest.raises(ValueError, match="finite"):
        associate_timestamps(np.array([np.nan]), second)


@settings(max_examples=60, deadline=None)
@given(
    first=st.lists(st.integers(0, 400), max_size=25, unique=True),
    second=st.lists(st.integers(0, 400), max_size=25, unique=True),
    offset=st.sampled_from([0.0, 0.013, -0.021]),
)
def test_associate_matches_tum_reference(first, second, offset):
    # Millisecond grid in a 0.4 s range: many overlapping candidate windows.
    a = np.asarray(first, np.float64) * 1e-3 + 1305031102.0
    b = np.asarray(second, np.float64) * 1e-3 + 1305031102.0
    pairs = associate_timestamps(a, b, 0.02, offset)
    got = sorted((a[i], b[j]) for i, j in pairs)
    assert got == reference_associate(a.tolist(), b.tolist(), offset, 0.02)
    assert np.all(np.diff(pairs[:, 0]) > 0) if len(pairs) > 1 else True
    assert len(set(pairs[:, 1].tolist())) == len(pairs)


def test_associate_large_is_fast():
    rng = np.random.default_rng(0)
    gt = 1341841873.0 + np.arange(8000) * 0.01 + rng.uniform(-1e-3, 1e-3, 8000)
    est = 1341841873.0 + np.sort(rng.uniform(0, 80, 1000))
    start = time.perf_counter()
    pairs = associate_timestamps(gt, est)
    elapsed = time.perf_counter() - start
    assert elapsed < 1.0, f"association of 8000 x 1000 took {elapsed:.2f} s"
    # At 100 Hz every estimate has a ground-truth stamp within 0.005 s, and the estimates
    # are ~80 ms apart so they never compete.
    assert len(pairs) >= 990
    assert np.all(np.abs(gt[pairs[:, 0]] - est[pairs[:, 1]]) < 0.02)


# ----------------------------------------------------------------------------- alignment


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(3, 40))
def test_horn_align_recovers_rigid_motion(seed, n):
    rng = np.random.default_rng(seed)
    model = rng.uniform(-3, 3, (3, n))
    # Skip near-degenerate (almost collinear) point sets, where the rotation is ill-posed.
    sv = np.linalg.svd(model - model.mean(1, keepdims=True), compute_uv=False)
    if sv[1] < 0.3:
        return
    r_true = random_rotation(rng)
    t_true = rng.uniform(-10, 10, 3)
    data = r_true @ model + t_true[:, None]
    r, t = horn_align(model, data)
    np.testing.assert_allclose(r, r_true, atol=1e-8)
    np.testing.assert_allclose(t, t_true, atol=1e-7)
    r_ref, t_ref, _ = reference_align(model, data)
    np.testing.assert_allclose(r, r_ref, atol=1e-9)
    np.testing.assert_allclose(t, t_ref, atol=1e-8)


def test_horn_align_never_returns_a_reflection():
    rng = np.random.default_rng(5)
    model = rng.normal(size=(3, 30))
    data = np.diag([1.0, 1.0, -1.0]) @ model  # mirror image: best proper rotation only
    r, t = horn_align(model, data)
    assert np.linalg.det(r) == pytest.approx(1.0)
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-12)
    r_ref, t_ref, _ = reference_align(model, data)
    np.testing.assert_allclose(r, r_ref, atol=1e-9)
    np.testing.assert_allclose(t, t_ref, atol=1e-9)


def test_horn_align_bad_input():
    with pytest.raises(ValueError, match=r"\(3, N\)"):
        horn_align(np.zeros((3, 4)), np.zeros((3, 5)))
    with pytest.raises(ValueError, match="at least 3"):
        horn_align(np.zeros((3, 2)), np.zeros((3, 2)))


# ----------------------------------------------------------------------------- ATE


def test_ate_hand_computed():
    # Ground truth on the three axes. The errors e (x-axis points +d z, z-axis points -d z,
    # y-axis points none) have zero mean and zero cross-covariance with the centred positions,
    # so the best alignment of est = R (gt + e) + t undoes exactly R, t and leaves e.
    d = 0.1
    gt_xyz = np.array([[1, 0, 0], [-1, 0, 0], [0, 2, 0], [0, -2, 0], [0, 0, 3], [0, 0, -3.0]])
    e = np.array([[0, 0, d], [0, 0, d], [0, 0, 0], [0, 0, 0], [0, 0, -d], [0, 0, -d]])
    rng = np.random.default_rng(7)
    r, t = random_rotation(rng), np.array([0.5, -2.0, 1.0])
    est_xyz = (gt_xyz + e) @ r.T + t
    gt_t = 100.0 + np.arange(6) * 0.1
    # Estimate stamps 4 ms late, plus two poses that associate with nothing (garbage).
    est_t = np.concatenate([gt_t + 0.004, [50.0, 200.0]])
    est_xyz = np.concatenate([est_xyz, [[9.0, 9.0, 9.0], [-9.0, 9.0, 9.0]]])
    quat = np.tile([0.0, 0.0, 0.0, 1.0], (8, 1))
    gt_poses = np.concatenate([gt_xyz, quat[:6]], axis=1)
    est_poses = np.concatenate([est_xyz, quat], axis=1)
    res = ate((gt_t, gt_poses), (est_t, est_poses))
    assert res["n"] == 6
    # |e| = d, d, 0, 0, d, d.
    assert res["rmse"] == pytest.approx(d * math.sqrt(4 / 6), abs=1e-12)
    assert res["mean"] == pytest.approx(4 * d / 6, abs=1e-12)
    assert res["median"] == pytest.approx(d, abs=1e-12)
    assert res["std"] == pytest.approx(d * math.sqrt(2) / 3, abs=1e-12)
    assert res["min"] == pytest.approx(0.0, abs=1e-12)
    assert res["max"] == pytest.approx(d, abs=1e-12)


def test_ate_random_orthogonal_errors():
    # Same construction with many random points: errors projected orthogonal to [1, gt_c].
    rng = np.random.default_rng(11)
    n = 60
    gt_xyz = rng.uniform(-2, 2, (n, 3))
    basis = np.concatenate([np.ones((n, 1)), gt_xyz - gt_xyz.mean(0)], axis=1)
    e = rng.normal(scale=0.05, size=(n, 3))
    e -= basis @ np.linalg.lstsq(basis, e, rcond=None)[0]
    r, t = random_rotation(rng), rng.normal(size=3)
    est_xyz = (gt_xyz + e) @ r.T + t
    ts = np.arange(n) / 30.0
    gt_poses = make_poses7(np.tile(np.eye(3), (n, 1, 1)), gt_xyz)
    est_poses = make_poses7(np.tile(np.eye(3), (n, 1, 1)), est_xyz)
    res = ate((ts, gt_poses), (ts, est_poses))
    norms = np.linalg.norm(e, axis=1)
    assert res["n"] == n
    assert res["rmse"] == pytest.approx(math.sqrt(np.mean(norms**2)), rel=1e-9)
    assert res["max"] == pytest.approx(norms.max(), rel=1e-9)
    assert res["median"] == pytest.approx(np.median(norms), rel=1e-9)


def test_ate_perfect_and_too_few_pairs():
    rng = np.random.default_rng(3)
    ts = np.arange(10) * 0.1
    gt_poses = make_poses7(np.tile(np.eye(3), (10, 1, 1)), rng.normal(size=(10, 3)))
    res = ate((ts, gt_poses), (ts, gt_poses))
    assert res["rmse"] == pytest.approx(0.0, abs=1e-12) and res["n"] == 10
    with pytest.raises(ValueError, match="at least 3 associated"):
        ate((ts, gt_poses), (ts[:2] + 0.001, gt_poses[:2]))
    with pytest.raises(ValueError, match="at least 3 associated"):
        ate((ts, gt_poses), (ts + 5.0, gt_poses))
    with pytest.raises(ValueError, match="shape"):
        ate((ts, gt_poses[:5]), (ts, gt_poses))


def test_ate_similarity_alignment_reads_a_scale_error():
    """The ground truth moved rigidly and shrunk by 2 %: scale 1 / 0.98, residual ~0; the
    rigid ATE of the same estimate is not ~0 (what the scale hides from it). The measure that
    showed occluding contours shortening the local window's translations."""
    rng = np.random.default_rng(0)
    ts = np.arange(40) * 0.03
    pos = np.cumsum(rng.normal(0, 0.02, (40, 3)), axis=0)
    quat = np.tile([0.0, 0.0, 0.0, 1.0], (40, 1))
    gt = (ts, np.concatenate([pos, quat], axis=1))
    rot = quat_to_rotmat(np.array([0.1, -0.2, 0.3, 0.9]))  # normalised there
    move = np.eye(4)
    move[:3, :3], move[:3, 3] = rot, [0.3, -0.1, 0.2]
    est = np.tile(np.eye(4), (40, 1, 1))
    est[:, :3, 3] = pos * 0.98
    est = np.einsum("ab,nbc->nac", move, est)
    sim = ate(gt, (ts, matrices_to_poses7(est)), align="sim3")
    assert abs(sim["scale"] - 1 / 0.98) < 1e-6 and sim["rmse"] < 1e-6
    assert ate(gt, (ts, matrices_to_poses7(est)))["rmse"] > 1e-3
    est[:, :3, 3] *= 1.02 / 0.98  # now 2 % too long: the scale reads 1 / 1.02
    assert abs(ate(gt, (ts, matrices_to_poses7(est)), align="sim3")["scale"] - 1 / 1.02) < 1e-6


def test_ate_matches_evo():
    evo_sync = pytest.importorskip("evo.core.sync")
    evo_metrics = pytest.importorskip("evo.core.metrics")
    evo_traj = pytest.importorskip("evo.core.trajectory")
    rng = np.random.default_rng(21)
    n = 50
    ts = 1000.0 + np.arange(n) / 30.0
    gt_xyz = np.cumsum(rng.normal(scale=0.05, size=(n, 3)), axis=0)
    rots = np.stack([random_rotation(rng) for _ in range(n)])
    gt_poses = make_poses7(rots, gt_xyz)
    r, t = random_rotation(rng), rng.normal(size=3)
    est_xyz = (gt_xyz + rng.normal(scale=0.02, size=(n, 3))) @ r.T + t
    est_poses = make_poses7(rots, est_xyz)
    ours = ate((ts, gt_poses), (ts + 0.003, est_poses))

    def to_evo(stamps, poses):
        wxyz = np.roll(poses[:, 3:], 1, axis=1)
        return evo_traj.PoseTrajectory3D(poses[:, :3], wxyz, stamps)

    ref, est = evo_sync.associate_trajectories(
        to_evo(ts, gt_poses), to_evo(ts + 0.003, est_poses), max_diff=0.02
    )
    est.align(ref, correct_scale=False)
    ape = evo_metrics.APE(evo_metrics.PoseRelation.translation_part)
    ape.process_data((ref, est))
    assert ours["rmse"] == pytest.approx(
        ape.get_statistic(evo_metrics.StatisticsType.rmse), rel=1e-6
    )


# ----------------------------------------------------------------------------- RPE


def smooth_gt(n: int, rate: float, rng: np.random.Generator):
    ts = 1305031102.0 + np.arange(n) / rate
    s = ts - ts[0]
    pos = np.stack([np.sin(s), 0.3 * s, np.cos(0.5 * s)], axis=1)
    rots = np.stack([rot_z(0.4 * k) @ random_rotation(rng) for k in s])
    return ts, rots, pos


def test_rpe_identical_is_zero():
    rng = np.random.default_rng(1)
    ts, rots, pos = smooth_gt(100, 25.0, rng)
    poses = make_poses7(rots, pos)
    res = rpe_per_second((ts, poses), (ts, poses))
    assert res["n"] == 87  # t_i <= 3.44 s has a partner >= 0.5 s later (the end is 3.96 s)
    assert res["trans_rmse_m_per_s"] == pytest.approx(0.0, abs=1e-9)
    assert res["rot_rmse_deg_per_s"] == pytest.approx(0.0, abs=1e-6)


def test_rpe_is_invariant_to_the_estimate_world_frame():
    rng = np.random.default_rng(2)
    ts, rots, pos = smooth_gt(60, 30.0, rng)
    w, tw = random_rotation(rng), np.array([3.0, -1.0, 2.0])
    est = make_poses7(w @ rots, pos @ w.T + tw)
    res = rpe_per_second((ts, make_poses7(rots, pos)), (ts + 0.002, est), delta=0.5)
    assert res["n"] > 0
    assert res["trans_rmse_m_per_s"] == pytest.approx(0.0, abs=1e-9)
    assert res["rot_rmse_deg_per_s"] == pytest.approx(0.0, abs=1e-6)


def test_rpe_constant_extra_velocity():
    # P_k = G_k with 0.1 m/s * t_k added along the estimate world's x: for every pair,
    # E = (G_i^-1 G_j)^-1 (P_i^-1 P_j) = [I, (R_i R_ij)^T v dt e_x], so |trans(E)| / dt = 0.1.
    rng = np.random.default_rng(4)
    ts, rots, pos = smooth_gt(100, 25.0, rng)
    est_t = ts + 0.003
    est_pos = pos + np.outer(0.1 * (est_t - est_t[0]), [1.0, 0.0, 0.0])
    res = rpe_per_second((ts, make_poses7(rots, pos)), (est_t, make_poses7(rots, est_pos)))
    assert res["n"] == 87
    assert res["trans_rmse_m_per_s"] == pytest.approx(0.1, rel=1e-9)
    assert res["rot_rmse_deg_per_s"] == pytest.approx(0.0, abs=1e-6)
    # Row order of the inputs does not matter.
    p, q = rng.permutation(100), rng.permutation(100)
    res2 = rpe_per_second((ts[q], make_poses7(rots, pos)[q]),
                          (est_t[p], make_poses7(rots, est_pos)[p]))
    assert res2 == pytest.approx(res)


def test_rpe_constant_extra_rotation_rate():
    # Ground truth moves along z without turning; the estimate also yaws at 5 deg/s about z
    # (which leaves z displacements unchanged): rotation RPE 5 deg/s, translation RPE 0.
    n = 90
    ts = np.arange(n) / 30.0
    pos = np.stack([np.zeros(n), np.zeros(n), 0.3 * ts], axis=1)
    yaw = np.stack([rot_z(math.radians(5.0) * t) for t in ts])
    res = rpe_per_second((ts, make_poses7(np.tile(np.eye(3), (n, 1, 1)), pos)),
                         (ts, make_poses7(yaw, pos)))
    assert res["n"] > 0
    assert res["rot_rmse_deg_per_s"] == pytest.approx(5.0, rel=1e-9)
    assert res["trans_rmse_m_per_s"] == pytest.approx(0.0, abs=1e-9)


def test_rpe_error_definition_by_hand():
    # One pair over 1 s: ground truth moves 1 m along x; the estimate moves the same 1 m in
    # its start frame but also turns 90 degrees about z. E = (G_0^-1 G_1)^-1 (P_0^-1 P_1)
    # = [Rz(90), 0]: no translation error, 90 deg/s. (The other order, (P_0^-1 P_1)
    # (G_0^-1 G_1)^-1 as in TUM's evaluate_rpe.py script, would give |(1, -1, 0)| = 1.414 m.)
    ts = np.array([0.0, 1.0])
    gt = make_poses7(np.stack([np.eye(3), np.eye(3)]), np.array([[0, 0, 0], [1.0, 0, 0]]))
    est = make_poses7(np.stack([np.eye(3), rot_z(math.pi / 2)]), np.array([[0, 0, 0], [1.0, 0, 0]]))
    res = rpe_per_second((ts, gt), (ts, est), delta=1.0)
    assert res["n"] == 1
    assert res["trans_rmse_m_per_s"] == pytest.approx(0.0, abs=1e-12)
    assert res["rot_rmse_deg_per_s"] == pytest.approx(90.0, rel=1e-12)
    # Over 2 s (est timestamps doubled) the same errors are halved per second.
    res = rpe_per_second((ts * 2, gt), (ts * 2, est), delta=2.0)
    assert res["rot_rmse_deg_per_s"] == pytest.approx(45.0, rel=1e-12)


def test_rpe_ignores_estimates_without_ground_truth():
    rng = np.random.default_rng(6)
    ts, rots, pos = smooth_gt(120, 30.0, rng)
    gt_keep = (ts - ts[0] < 1.5) | (ts - ts[0] > 2.5)  # a 1 s hole in the ground truth
    est = make_poses7(rots, pos)
    hole = ~gt_keep
    est[hole, :3] += rng.normal(scale=5.0, size=(int(hole.sum()), 3))  # garbage there
    res = rpe_per_second((ts[gt_keep], make_poses7(rots[gt_keep], pos[gt_keep])), (ts, est))
    assert res["n"] > 0
    assert res["trans_rmse_m_per_s"] == pytest.approx(0.0, abs=1e-9)


def test_rpe_shorter_than_delta_is_nan():
    rng = np.random.default_rng(8)
    ts, rots, pos = smooth_gt(10, 30.0, rng)  # 0.3 s long
    poses = make_poses7(rots, pos)
    res = rpe_per_second((ts, poses), (ts, poses), delta=1.0)
    assert res["n"] == 0
    assert math.isnan(res["trans_rmse_m_per_s"]) and math.isnan(res["rot_rmse_deg_per_s"])
    res = rpe_per_second((ts, poses), (ts + 10.0, poses))  # nothing associates
    assert res["n"] == 0 and math.isnan(res["trans_rmse_m_per_s"])
    with pytest.raises(ValueError, match="delta"):
        rpe_per_second((ts, poses), (ts, poses), delta=0.0)
