"""edgevo_jax.runs.measure: clips at a frame step, a peer's run from edgevo's first pose,
accuracy with its notes, statistics over warm frames and over seeds, ground truth at frame
times, and the silently diverged frames (on synthetic trajectories with injected jumps), and
a run's statistics of them."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from edgevo_jax.cli import BUNDLED_CLIP
from edgevo_jax.datasets import load_sequence
from edgevo_jax.geometry import inverse_np
from edgevo_jax.io import matrices_to_poses7
from edgevo_jax.runs import measure
from edgevo_jax.runs.run import initial_pose, summarise
from edgevo_jax.tracking.decision import DEPTH_DISAGREES
from edgevo_jax.tracking.results import FrameResult, FrameResults


def _rot(axis: str, deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    i, j = {"x": (1, 2), "y": (2, 0), "z": (0, 1)}[axis]
    m = np.eye(4)
    m[i, i], m[i, j], m[j, i], m[j, j] = c, -s, s, c
    return m


def _trans(x: float, y: float, z: float) -> np.ndarray:
    m = np.eye(4)
    m[:3, 3] = (x, y, z)
    return m


def _groundtruth(n: int = 20) -> np.ndarray:
    """T_world_cam moving 1 cm and turning 0.5 deg about y per frame (well under the
    thresholds)."""
    step = _trans(0.01, 0.002, 0.0) @ _rot("y", 0.5)
    poses = [_trans(0.3, -0.1, 1.2) @ _rot("x", 10.0)]
    for _ in range(n - 1):
        poses.append(poses[-1] @ step)
    return np.stack(poses)


def _jump(poses: np.ndarray, i: int, local: np.ndarray) -> np.ndarray:
    """The trajectory jumping at frame i by ``local`` (in frame i's camera coordinates) and
    staying there: P_m = G_i local G_i^-1 G_m for m >= i, so only the motion i-1 -> i is
    off, by exactly ``local``."""
    out = poses.copy()
    out[i:] = poses[i] @ local @ inverse_np(poses[i]) @ poses[i:]
    return out


JUMP_T, JUMP_R = 12, 7  # frames with a 6 cm jump and a 4 deg turn


def _injected(gt: np.ndarray) -> np.ndarray:
    return _jump(_jump(gt, JUMP_T, _trans(0.0, 0.06, 0.0)), JUMP_R, _rot("z", 4.0))


def test_diverged_frames_flags_jumps_on_ok_frames() -> None:
    gt = _groundtruth()
    assert measure.diverged_frames(gt, ["OK"] * len(gt), gt) == []
    assert measure.diverged_frames(_injected(gt), ["OK"] * len(gt), gt) == [JUMP_R, JUMP_T]
    # the motion errors are the injected ones
    trans, rot = measure.motion_errors(_injected(gt), gt)
    assert trans[JUMP_T - 1] == pytest.approx(0.06) and rot[JUMP_R - 1] == pytest.approx(4.0)
    assert trans.shape == rot.shape == (len(gt) - 1,)
    # under the thresholds (4 cm, 2 deg): nothing; over thresholds of one's own: flagged
    small = _jump(_jump(gt, JUMP_T, _trans(0.04, 0.0, 0.0)), JUMP_R, _rot("x", 2.0))
    assert measure.diverged_frames(small, ["OK"] * len(gt), gt) == []
    assert measure.diverged_frames(small, ["OK"] * len(gt), gt, trans_m=0.03,
                                   rot_deg=1.0) == [JUMP_R, JUMP_T]


@pytest.mark.parametrize("flag", ["LOST", "WEAK"])
def test_diverged_frames_ignores_jumps_on_flagged_frames(flag: str) -> None:
    gt = _groundtruth()
    states = ["OK"] * len(gt)
    states[JUMP_T] = states[JUMP_R] = flag
    assert measure.diverged_frames(_injected(gt), states, gt) == []
    # a flagged frame whose pose alone is off (a bad prediction while lost, then back on
    # track) blames neither itself nor the OK frame after it
    outlier = gt.copy()
    outlier[JUMP_T] = outlier[JUMP_T] @ _trans(0.2, 0.0, 0.0) @ _rot("y", 20.0)
    assert measure.diverged_frames(outlier, states, gt) == []
    assert measure.diverged_frames(outlier, ["OK"] * len(gt), gt) == [JUMP_T, JUMP_T + 1]


def test_silently_wrong_judges_an_ok_frame_after_any_frame() -> None:
    """An OK frame that jumps away from a flagged one is silently wrong (the user trusts it);
    diverged_frames does not judge it; a flagged frame itself never is."""
    gt = _groundtruth()
    states = ["OK"] * len(gt)
    states[JUMP_T - 1] = "WEAK"  # the frame before the 6 cm jump
    states[JUMP_R] = "LOST"  # the 4 deg turn lands on a flagged frame
    wrong = _injected(gt)
    assert measure.silently_wrong(wrong, states, gt) == [JUMP_T]
    assert measure.diverged_frames(wrong, states, gt) == []
    assert measure.silently_wrong(wrong, ["OK"] * len(gt), gt) == [JUMP_R, JUMP_T]
    assert measure.silently_wrong(gt, states, gt) == []
    assert measure.silently_wrong(wrong, states, gt, trans_m=0.07) == []


def test_diverged_frames_skips_frames_without_groundtruth() -> None:
    gt = _groundtruth()
    partial = gt.copy()
    partial[JUMP_T] = np.nan
    assert measure.diverged_frames(_injected(gt), ["OK"] * len(gt), partial) == [JUMP_R]
    with pytest.raises(ValueError, match="states"):
        measure.diverged_frames(gt, ["OK"] * 3, gt)
    with pytest.raises(ValueError, match="must both be"):
        measure.motion_errors(gt, gt[:-1])


def _trajectory(seconds: float, rate: float = 30.0):
    """Timestamps and T_world_cam of a camera circling at 0.2 m/s, turning 10 deg/s."""
    t = 1000.0 + np.arange(0.0, seconds, 1.0 / rate)
    poses = np.stack([_trans(0.5 * math.cos(0.4 * s), 0.5 * math.sin(0.4 * s), 1.0)
                      @ _rot("z", 10.0 * s) for s in t - t[0]])
    return t, poses


def test_accuracy_against_ground_truth() -> None:
    t, gt = _trajectory(2.0)
    groundtruth = (t, matrices_to_poses7(gt))
    exact = measure.accuracy(groundtruth, t, gt)
    assert exact["ate_rmse_m"] < 1e-9 and exact["rpe_m_per_s"] < 1e-9
    assert exact["rpe_deg_per_s"] < 1e-6 and "accuracy_note" not in exact
    # a rigid move of the whole trajectory is aligned away; 1 cm of noise is not
    moved = np.einsum("ab,nbc->nac", _trans(1.0, -2.0, 0.5) @ _rot("y", 30.0), gt)
    assert measure.accuracy(groundtruth, t, moved)["ate_rmse_m"] < 1e-6
    noise = np.random.default_rng(0).normal(0.0, 0.01, (len(t), 3))
    noisy = gt.copy()
    noisy[:, :3, 3] += noise
    bad = measure.accuracy(groundtruth, t, noisy)
    rms = math.sqrt(np.mean(np.sum(noise**2, axis=1)))
    assert bad["ate_rmse_m"] == pytest.approx(rms, rel=0.1)
    assert bad["rpe_m_per_s"] > 0.005 and bad["rpe_deg_per_s"] < 1e-6


def test_accuracy_notes() -> None:
    t, gt = _trajectory(2.0)
    groundtruth = (t, matrices_to_poses7(gt))
    none = measure.accuracy(None, t, gt, no_groundtruth="no groundtruth.txt")
    assert none["accuracy_note"] == "no groundtruth.txt" and math.isnan(none["ate_rmse_m"])
    short = measure.accuracy(groundtruth, t[:10], gt[:10])  # 0.3 s
    assert short["ate_rmse_m"] < 1e-9 and math.isnan(short["rpe_m_per_s"])
    assert math.isnan(short["rpe_deg_per_s"]) and "1 s" in short["accuracy_note"]
    apart = measure.accuracy(groundtruth, t[:5] + 100.0, gt[:5])  # no time in common
    assert math.isnan(apart["ate_rmse_m"]) and apart["accuracy_note"]


def test_frame_and_finite_stats() -> None:
    s = measure.frame_stats([100.0, 50.0, 1.0, 2.0, 3.0, 4.0])  # the first two are warm-up
    assert s == pytest.approx({"median": 2.5, "p90": 3.7, "mean": 2.5, "max": 4.0})
    assert measure.frame_stats([5.0, 1.0, 3.0], skip=0)["median"] == 3.0
    assert all(math.isnan(v) for v in measure.frame_stats([1.0, 2.0]).values())
    f = measure.finite_stats([0.01, None, math.nan, 0.03, math.inf])
    assert f == pytest.approx({"mean": 0.02, "std": math.sqrt(2) * 0.01, "min": 0.01,
                               "max": 0.03, "median": 0.02})
    assert math.isnan(measure.finite_stats([0.5])["std"])
    assert all(math.isnan(v) for v in measure.finite_stats([None, math.nan]).values())


def test_groundtruth_at() -> None:
    t, gt = _trajectory(1.0, rate=100.0)
    seq = SimpleNamespace(groundtruth=(t, matrices_to_poses7(gt)))
    at = measure.groundtruth_at(seq, [t[3] + 0.004, t[50], t[-1] + 0.5])
    np.testing.assert_allclose(at[0], gt[3], atol=1e-9)  # the nearest pose
    np.testing.assert_allclose(at[1], gt[50], atol=1e-9)
    assert np.isnan(at[2]).all()  # beyond 0.02 s of any
    mid = measure.groundtruth_at(seq, [0.5 * (t[3] + t[4])], interpolate=True)[0]
    np.testing.assert_allclose(mid[:3, 3], 0.5 * (gt[3, :3, 3] + gt[4, :3, 3]), atol=1e-9)
    assert np.isnan(measure.groundtruth_at(SimpleNamespace(groundtruth=None), [t[0]])).all()


def test_load_clip_at_a_frame_step() -> None:
    full = measure.load_clip(BUNDLED_CLIP)
    assert len(full) == 9 and len(measure.load_clip(BUNDLED_CLIP, frame_step=2)) == 5
    cut = measure.load_clip(BUNDLED_CLIP, max_frames=4)
    assert cut.name == f"{full.name}_frames0-4"
    np.testing.assert_array_equal(cut.timestamps, full.timestamps[:4])
    every2 = measure.load_clip(BUNDLED_CLIP, frame_step=2)
    half = measure.load_clip(BUNDLED_CLIP, frame_step=2, max_frames=4)  # the first 4's time
    assert 0 < len(half) < len(every2) and half.timestamps[-1] <= full.timestamps[3]
    assert every2.timestamps[len(half)] > full.timestamps[3]
    assert len(measure.load_clip(BUNDLED_CLIP, max_frames=100)) == 9
    with pytest.raises(ValueError, match="positive"):
        measure.load_clip(BUNDLED_CLIP, max_frames=0)


def test_run_peer_starts_at_edgevos_first_pose(monkeypatch) -> None:
    class Still:
        description = "still"

        def step(self, rgb, depth):
            return np.eye(4)

    made = []
    monkeypatch.setattr(measure, "make_peer",
                        lambda method, intr, w, h: made.append((method, w, h)) or Still())
    seq = measure.load_clip(BUNDLED_CLIP)
    track = measure.run_peer("cv2_rgb", seq, max_frames=3)
    assert made == [("cv2_rgb", seq.width, seq.height)] and track.description == "still"
    assert len(track.frame_ms) == 3 and track.states == ["OK"] * 3
    for pose in track.poses:
        np.testing.assert_allclose(pose, initial_pose(seq))
    assert len(measure.run_peer("cv2_rgb", seq).frame_ms) == len(seq)


def test_a_runs_stats_count_the_second_opinion_and_the_silently_wrong() -> None:
    """``summarise``: frames OK / WEAK / LOST, the frames the second opinion checked and
    those it made WEAK, and with ground truth the OK frames silently wrong (indices)."""
    seq = load_sequence(BUNDLED_CLIP)
    gt = measure.groundtruth_at(seq, seq.timestamps)
    poses = gt.copy()
    poses[4:] = _trans(0.06, 0.0, 0.0) @ poses[4:]  # frame 4 jumps 6 cm, the rest follow it

    def result(i: int, state: str = "OK", reason: str | None = None,
               agreement: float | None = None) -> FrameResult:
        return FrameResult(float(seq.timestamps[i]), poses[i], state, reason, 100, None, None,
                           0, None, None, 0.0, 0.0, 0.0, depth_agreement=agreement)

    class Run(FrameResults):
        config, num_keyframes = None, 1
        results = [result(0), result(1, agreement=0.9),
                   result(2, "WEAK", f"{DEPTH_DISAGREES}: 30 %", 0.3),
                   result(3, "LOST", "too few inliers"),
                   *(result(i) for i in range(4, len(seq)))]

    stats = summarise(Run(), seq)
    assert stats["ok"] == len(seq) - 2 and stats["weak"] == 1 and stats["lost"] == 1
    assert stats["second_opinion"] == {"checked": 2, "weak": 1}
    assert stats["silently_wrong"] == [4]
