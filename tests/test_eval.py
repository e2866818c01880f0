"""``edgevo_jax.ate`` / ``rpe`` against evo (``evo_ape`` / ``evo_rpe``) on real ground truth,
and ``edgevo eval``'s options.

The ground truth: the first 600 poses (6 s) of fr3_teddy_first200's groundtruth.txt. The
estimate: the same taken at a camera's rate (every third pose, 4 ms late), perturbed by a
seeded random walk in position and rotation, moved into another world frame and scaled by
0.8: every alignment has work to do. evo's numbers are computed live when evo is installed
(``pip install evo``; its pandas and seaborn keep it out of the ``dev`` extra) and were
recorded from evo 1.38.1 for when it is not (``EVO_RMSE``; ``test_against_evo``, run with evo
installed, checks the same cases).
"""

from __future__ import annotations

import copy
import json

import numpy as np
import pytest
from conftest import SHARED_TUM

from edgevo_jax import ate, cli, metrics, rpe
from edgevo_jax.io import matrices_to_poses7, poses7_to_matrices, read_trajectory, write_trajectory

TEDDY_GT = SHARED_TUM / "rgbd_dataset_freiburg3_teddy_first200" / "groundtruth.txt"
OFFSETS = (0.0, 0.013)  # 0.013 s: a wrong association (3 ground-truth poses off)
RPE_CASES = (("frames", 1, False), ("frames", 10, True), ("metres", 0.1, False),
             ("metres", 0.1, True))
STATS = ("rmse", "mean", "median", "std", "min", "max")

# evo 1.38.1: (offset, align) -> APE rmse (m); (align, unit, delta, all_pairs) -> RPE rmse of
# the translation part (m) and of the rotation angle (deg), offset 0
EVO_RMSE = {
    (0.0, 'none'): 1.5266322140867412,
    (0.0, 'origin'): 0.2723319334691142,
    (0.0, 'se3'): 0.12446312658159717,
    (0.0, 'sim3'): 0.016154285557988764,
    (0.013, 'none'): 1.5239246484569724,
    (0.013, 'origin'): 0.2706742082666432,
    (0.013, 'se3'): 0.12312840764585707,
    (0.013, 'sim3'): 0.014993724004252194,
    ('sim3', 'frames', 1, False): (0.003631656161105339, 0.20645461975288912),
    ('sim3', 'frames', 10, True): (0.012396795966032059, 0.5964344696100086),
    ('sim3', 'metres', 0.1, False): (0.010767744444910266, 0.5416640176318311),
    ('sim3', 'metres', 0.1, True): (0.012203103972764102, 0.5582816963950761),
    ('none', 'frames', 1, False): (0.0037601343290237714, 0.20645461975288895),
    ('none', 'frames', 10, True): (0.026621150409761526, 0.5964344696100086),
    ('none', 'metres', 0.1, False): (0.03165319139130773, 0.6538619483572864),
    ('none', 'metres', 0.1, True): (0.030311362777740433, 0.6291854155168151),
}


def _rotvec_to_matrix(v: np.ndarray) -> np.ndarray:
    """Rodrigues' formula for rotation vectors (N, 3) -> (N, 3, 3)."""
    angle = np.linalg.norm(v, axis=1)[:, None, None]
    k = np.zeros((v.shape[0], 3, 3))
    axis = v / np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-300)
    k[:, 0, 1], k[:, 0, 2], k[:, 1, 2] = -axis[:, 2], axis[:, 1], -axis[:, 0]
    k -= np.swapaxes(k, 1, 2)
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


def perturbed_estimate(gt: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """The test's estimate of ``gt`` (module doc), deterministic."""
    rng = np.random.default_rng(0)
    t, p = gt[0][::3] + 0.004, poses7_to_matrices(gt[1][::3])
    n = t.size
    p[:, :3, :3] = _rotvec_to_matrix(np.cumsum(rng.normal(scale=0.002, size=(n, 3)), 0)) \
        @ p[:, :3, :3]
    p[:, :3, 3] += np.cumsum(rng.normal(scale=0.002, size=(n, 3)), 0)
    world = np.eye(4)
    world[:3, :3] = _rotvec_to_matrix(np.array([[0.3, -0.2, 1.0]]))[0]
    world[:3, 3] = [1.0, 2.0, -0.5]
    p = world @ p
    p[:, :3, 3] *= 0.8
    return t, matrices_to_poses7(p)


@pytest.fixture(scope="module")
def teddy():
    if not TEDDY_GT.is_file():
        pytest.skip(f"../shared/data/tum not found: {TEDDY_GT}")
    t, p = read_trajectory(TEDDY_GT)
    gt = (t[:600], p[:600])
    return gt, perturbed_estimate(gt)


def _evo(gt, est, offset, align):
    """(evo's associated ground truth, estimate, the ape / rpe keywords of ``align``)."""
    sync = pytest.importorskip("evo.core.sync", reason="evo is not installed (pip install evo)")
    from evo.core.trajectory import PoseTrajectory3D

    def traj(t, p):
        return PoseTrajectory3D(p[:, :3], np.roll(p[:, 3:], 1, axis=1), t)

    ref, e = sync.associate_trajectories(traj(*gt), traj(*est), max_diff=0.02, offset_2=offset)
    return ref, e, {"align": align in ("se3", "sim3"), "correct_scale": align == "sim3",
                    "align_origin": align == "origin"}


def _close(ours: float, theirs: float) -> bool:
    return ours == pytest.approx(theirs, rel=1e-9, abs=1e-12)


@pytest.mark.parametrize("align", metrics.ALIGNMENTS)
def test_against_evo(teddy, align):
    """Every statistic of the APE and the RPE (translation and rotation angle) equals evo's,
    for each alignment, with the right and with a wrong association."""
    pytest.importorskip("evo", reason="evo is not installed (pip install evo)")
    from evo import main_ape, main_rpe
    from evo.core import metrics as em

    gt, est = teddy
    units = {"frames": em.Unit.frames, "metres": em.Unit.meters}
    rmse = {}
    for offset in OFFSETS:
        ref, e, kw = _evo(gt, est, offset, align)
        theirs = main_ape.ape(copy.deepcopy(ref), copy.deepcopy(e),
                              em.PoseRelation.translation_part, **kw)
        ours = ate(gt, est, align=align, offset=offset)
        assert ours["n"] == theirs.np_arrays["error_array"].size == 200
        assert all(_close(ours[k], theirs.stats[k]) for k in STATS), (ours, theirs.stats)
        rmse[offset] = ours["rmse"]
        if offset:
            continue
        for unit, delta, all_pairs in RPE_CASES:
            ours = rpe(gt, est, delta=delta, unit=unit, align=align, all_pairs=all_pairs)
            for prefix, relation in (("", em.PoseRelation.translation_part),
                                     ("rot_", em.PoseRelation.rotation_angle_deg)):
                theirs = main_rpe.rpe(copy.deepcopy(ref), copy.deepcopy(e), relation,
                                      delta=delta, delta_unit=units[unit], all_pairs=all_pairs,
                                      **kw)
                assert ours["n"] == theirs.np_arrays["error_array"].size
                assert all(_close(ours[prefix + k], theirs.stats[k]) for k in STATS), \
                    (unit, delta, all_pairs, prefix, ours, theirs.stats)
    assert rmse[0.0] != pytest.approx(rmse[0.013], rel=1e-4)  # the offset moved the result


@pytest.mark.parametrize("align", metrics.ALIGNMENTS)
def test_recorded_evo_numbers(teddy, align):
    """The same comparison without evo: its recorded RMSEs (module doc)."""
    gt, est = teddy
    for offset in OFFSETS:
        assert _close(ate(gt, est, align=align, offset=offset)["rmse"],
                      EVO_RMSE[(offset, align)])
    if align in ("none", "sim3"):
        for unit, delta, all_pairs in RPE_CASES:
            r = rpe(gt, est, delta=delta, unit=unit, align=align, all_pairs=all_pairs)
            assert (_close(r["rmse"], EVO_RMSE[(align, unit, delta, all_pairs)][0])
                    and _close(r["rot_rmse"], EVO_RMSE[(align, unit, delta, all_pairs)][1]))


def test_rpe_seconds_is_frames_on_a_steady_clock():
    """Pairs ``delta`` seconds apart are the pairs k frames apart when frames come every dt:
    delta = (k - 0.5) dt takes the k-th frame on (consecutive), k dt all pairs."""
    rng = np.random.default_rng(1)
    n, dt = 40, 1 / 30
    t = 100.0 + dt * np.arange(n)
    gt = (t, matrices_to_poses7(_walk(rng, n)))
    est = (t, matrices_to_poses7(_walk(rng, n)))
    for k in (1, 4):
        frames = rpe(gt, est, delta=k, unit="frames")
        assert rpe(gt, est, delta=(k - 0.5) * dt, unit="seconds") == pytest.approx(frames)
        frames = rpe(gt, est, delta=k, unit="frames", all_pairs=True)
        assert rpe(gt, est, delta=k * dt, unit="seconds", all_pairs=True) == pytest.approx(frames)
    none = rpe(gt, est, delta=2.0, unit="seconds")  # the clip spans 1.3 s
    assert none["n"] == 0 and np.isnan(none["rmse"])


def _walk(rng: np.random.Generator, n: int) -> np.ndarray:
    p = np.tile(np.eye(4), (n, 1, 1))
    p[:, :3, :3] = _rotvec_to_matrix(np.cumsum(rng.normal(scale=0.05, size=(n, 3)), 0))
    p[:, :3, 3] = np.cumsum(rng.normal(scale=0.05, size=(n, 3)), 0)
    return p


def test_bad_arguments_are_named():
    t = np.arange(5.0)
    traj = (t, matrices_to_poses7(np.tile(np.eye(4), (5, 1, 1))))
    with pytest.raises(ValueError, match="align must be one of se3, sim3, origin, none"):
        ate(traj, traj, align="rigid")
    with pytest.raises(ValueError, match="unit must be one of frames, seconds, metres"):
        rpe(traj, traj, unit="f")
    with pytest.raises(ValueError, match="whole number of frames"):
        rpe(traj, traj, delta=1.5)
    with pytest.raises(ValueError, match="estimate must be a .timestamps, poses7. pair"):
        ate(traj, t)


def test_cli_eval_options(teddy, tmp_path, capsys):
    """``edgevo eval``'s options are the API's keywords; files give what arrays give."""
    gt, est = teddy
    path = tmp_path / "est.txt"
    write_trajectory(path, *est)
    assert cli.ALIGN_CHOICES == metrics.ALIGNMENTS
    assert tuple(cli.DELTA_UNIT_CHOICES.values()) == metrics.DELTA_UNITS
    assert cli.main(["eval", str(TEDDY_GT), str(path), "--align", "sim3", "--delta", "0.1",
                     "--delta-unit", "m", "--all-pairs", "--delta-tol", "0.2", "--t-max-diff",
                     "0.01", "--t-offset", "0.013", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    common = {"align": "sim3", "max_diff": 0.01, "offset": 0.013}
    est_file = read_trajectory(path)
    assert out["ate"] == pytest.approx(ate(gt, est_file, **common))
    assert out["rpe"] == pytest.approx(rpe(gt, est_file, delta=0.1, unit="metres",
                                           all_pairs=True, delta_tol=0.2, **common))
    assert ate(TEDDY_GT, path) == ate(gt, est_file)
    assert cli.main(["eval", str(TEDDY_GT), str(path), "--t-max-diff", "0"]) == 2
    assert "--t-max-diff must be positive" in capsys.readouterr().err
