"""Tests for edgevo_jax.io: TUM trajectory files and pose conversions."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from edgevo_jax.io import (
    TrajectoryWriter,
    matrices_to_poses7,
    poses7_to_matrices,
    quat_to_rotmat,
    read_trajectory,
    rotmat_to_quat,
    write_trajectory,
)

finite = st.floats(-10.0, 10.0, allow_nan=False, allow_infinity=False)


def random_poses7(rng: np.random.Generator, n: int) -> np.ndarray:
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q *= np.sign(q[:, 3:4])
    return np.concatenate([rng.uniform(-5, 5, (n, 3)), q], axis=1)


def test_write_read_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    ts = 1305031102.175304 + np.arange(20) * 0.033
    poses = random_poses7(rng, 20)
    path = tmp_path / "sub" / "traj.txt"
    write_trajectory(path, ts, poses)
    assert path.is_file()
    assert not (tmp_path / "sub" / "traj.txt.part").exists()
    first = path.read_text().splitlines()[0].split()
    assert first[0] == f"{ts[0]:.6f}" and len(first) == 8
    t2, p2 = read_trajectory(path)
    np.testing.assert_allclose(t2, ts, atol=1e-6, rtol=0)
    np.testing.assert_allclose(p2, poses, atol=1e-7, rtol=0)
    assert t2.dtype == np.float64 and p2.shape == (20, 7)


def test_read_skips_comments_blank_and_accepts_commas(tmp_path):
    path = tmp_path / "gt.txt"
    path.write_text(
        "# ground truth trajectory\n"
        "\n"
        "1.5 1 2 3 0 0 0 1\n"
        "   \n"
        "# another comment\n"
        "2.5,4,5,6,0,0,1,0\n"
        "3.5\t7 8 9 0.5 0.5 0.5 0.5\n"
    )
    t, p = read_trajectory(path)
    np.testing.assert_array_equal(t, [1.5, 2.5, 3.5])
    np.testing.assert_array_equal(p[1], [4, 5, 6, 0, 0, 1, 0])
    np.testing.assert_array_equal(p[2], [7, 8, 9, 0.5, 0.5, 0.5, 0.5])


def test_read_empty_file_gives_empty_arrays(tmp_path):
    path = tmp_path / "empty.txt"
    path.write_text("# nothing\n")
    t, p = read_trajectory(path)
    assert t.shape == (0,) and p.shape == (0, 7)


def test_read_missing_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.txt"):
        read_trajectory(tmp_path / "nope.txt")


@pytest.mark.parametrize(
    "bad",
    ["1 2 3 4 5 6 7", "1 2 3 4 5 6 7 8 9", "1 2 3 x 5 6 7 8", "1 2 3 nan 5 6 7 8",
     "1 2 3 4 5 6 inf 8"],
)
def test_read_bad_line_names_file_and_line(tmp_path, bad):
    path = tmp_path / "traj.txt"
    path.write_text(f"# header\n0 0 0 0 0 0 0 1\n{bad}\n")
    with pytest.raises(ValueError, match=r"traj\.txt:3\b"):
        read_trajectory(path)


def test_write_rejects_non_finite_and_bad_shapes(tmp_path):
    path = tmp_path / "traj.txt"
    poses = random_poses7(np.random.default_rng(1), 3)
    poses[1, 2] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        write_trajectory(path, np.arange(3.0), poses)
    with pytest.raises(ValueError, match="shape|expected"):
        write_trajectory(path, np.arange(2.0), poses)
    assert not path.exists()


def test_writer_renames_on_success(tmp_path):
    path = tmp_path / "deep" / "dir" / "est.txt"
    poses = random_poses7(np.random.default_rng(2), 3)
    with TrajectoryWriter(path) as w:
        for k in range(3):
            w.write(10.0 + k, poses[k])
        part = tmp_path / "deep" / "dir" / "est.txt.part"
        # Each line is flushed as it is written.
        assert len(part.read_text().splitlines()) == 3
        assert not path.exists()
    assert path.is_file() and not part.exists()
    t, p = read_trajectory(path)
    np.testing.assert_array_equal(t, [10.0, 11.0, 12.0])
    np.testing.assert_allclose(p, poses, atol=1e-7)


def test_writer_keeps_part_file_on_exception(tmp_path):
    path = tmp_path / "est.txt"
    poses = random_poses7(np.random.default_rng(3), 2)
    with pytest.raises(RuntimeError, match="tracking lost"), TrajectoryWriter(path) as w:
        w.write(1.0, poses[0])
        w.write(2.0, poses[1])
        raise RuntimeError("tracking lost")
    assert not path.exists()
    part = tmp_path / "est.txt.part"
    t, p = read_trajectory(part)
    np.testing.assert_array_equal(t, [1.0, 2.0])
    np.testing.assert_allclose(p, poses, atol=1e-7)


def test_writer_close_without_with(tmp_path):
    path = tmp_path / "est.txt"
    w = TrajectoryWriter(path)
    w.write(1.0, [0, 0, 0, 0, 0, 0, 1])
    w.close()
    w.close()  # idempotent
    assert read_trajectory(path)[0].tolist() == [1.0]
    with pytest.raises(ValueError, match="closed"):
        w.write(2.0, [0, 0, 0, 0, 0, 0, 1])


@pytest.mark.parametrize("bad_index", [0, 3, 6])
def test_writer_rejects_nan_pose(tmp_path, bad_index):
    path = tmp_path / "est.txt"
    with TrajectoryWriter(path) as w:
        w.write(1.0, [0, 0, 0, 0, 0, 0, 1])
        pose = np.array([0, 0, 0, 0, 0, 0, 1.0])
        pose[bad_index] = np.nan
        with pytest.raises(ValueError, match="non-finite"):
            w.write(2.0, pose)
        with pytest.raises(ValueError, match="non-finite"):
            w.write(math.inf, [0, 0, 0, 0, 0, 0, 1])
        with pytest.raises(ValueError, match=r"\(7,\)"):
            w.write(3.0, [0, 0, 0, 1])
    # Only the good line reached the file.
    assert read_trajectory(path)[0].tolist() == [1.0]


def test_quat_to_rotmat_known_values():
    # 90 degrees about z: x -> y.
    s = math.sqrt(0.5)
    r = quat_to_rotmat(np.array([[0, 0, s, s]]))[0]
    np.testing.assert_allclose(r, [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)
    # 180 degrees about x; an unnormalised quaternion is normalised first.
    r = quat_to_rotmat(np.array([[3.0, 0, 0, 0]]))[0]
    np.testing.assert_allclose(r, np.diag([1.0, -1.0, -1.0]), atol=1e-12)
    with pytest.raises(ValueError):
        quat_to_rotmat(np.zeros((1, 4)))


def test_rotmat_to_quat_near_pi_and_sign():
    # Rotations by ~pi about each axis exercise every pivot of Shepperd's method.
    for axis in np.eye(3):
        for angle in (np.pi, np.pi - 1e-9, 2.0, 0.0):
            q = np.concatenate([axis * np.sin(angle / 2), [np.cos(angle / 2)]])
            q2 = rotmat_to_quat(quat_to_rotmat(q[None]))[0]
            assert q2[3] >= 0
            if q[3] > 1e-6:
                np.testing.assert_allclose(q2, q, atol=1e-8)
            else:  # qw ~ 0: q and -q are both valid
                assert abs(float(q2 @ q)) == pytest.approx(1.0, abs=1e-8)


@settings(max_examples=50, deadline=None)
@given(
    q=arrays(np.float64, (5, 4), elements=finite).filter(
        lambda a: np.all(np.linalg.norm(a, axis=1) > 1e-3)
    ),
    t=arrays(np.float64, (5, 3), elements=finite),
)
def test_poses7_matrices_round_trip(q, t):
    poses = np.concatenate([t, q], axis=1)
    mats = poses7_to_matrices(poses)
    r = mats[:, :3, :3]
    np.testing.assert_allclose(r @ np.swapaxes(r, 1, 2), np.broadcast_to(np.eye(3), r.shape),
                               atol=1e-9)
    np.testing.assert_allclose(np.linalg.det(r), 1.0, atol=1e-9)
    np.testing.assert_array_equal(mats[:, 3], np.broadcast_to([0, 0, 0, 1.0], (5, 4)))
    back = matrices_to_poses7(mats)
    qn = q / np.linalg.norm(q, axis=1, keepdims=True)
    # Same rotation: q and -q; the output is the qw >= 0 representative and unit norm.
    np.testing.assert_allclose(np.abs(np.sum(back[:, 3:] * qn, axis=1)), 1.0, atol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(back[:, 3:], axis=1), 1.0, atol=1e-12)
    assert np.all(back[:, 6] >= 0)
    np.testing.assert_allclose(back[:, :3], t, atol=1e-12)
    np.testing.assert_allclose(poses7_to_matrices(back), mats, atol=1e-9)


def test_conversions_reject_bad_shapes():
    with pytest.raises(ValueError, match="7"):
        poses7_to_matrices(np.zeros((3, 6)))
    with pytest.raises(ValueError, match="4, 4"):
        matrices_to_poses7(np.zeros((3, 3, 3)))
    with pytest.raises(ValueError, match="finite"):
        poses7_to_matrices(np.array([[0, 0, np.nan, 0, 0, 0, 1.0]]))
