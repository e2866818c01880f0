"""Tests for edgevo_jax.datasets.tum: lists, cameras, association and frame loading."""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from edgevo_jax.camera import CAMERAS, Camera, Intrinsics
from edgevo_jax.datasets import (
    camera_from_name,
    groundtruth_pose_at,
    load_sequence,
    read_file_list,
    subsequence,
)
from edgevo_jax.datasets.source import UnknownCameraError

FR1_XYZ = "rgbd_dataset_freiburg1_xyz_first10"
FR1_DESK = "rgbd_dataset_freiburg1_desk_clip9"
FR3_TEDDY = "rgbd_dataset_freiburg3_teddy_first200"


def write_list(path: Path, rows: list[tuple[float, str]], header: str = "# list\n") -> None:
    path.write_text(header + "".join(f"{t:.6f} {name}\n" for t, name in rows))


def make_sequence(
    root: Path,
    rgb_t: list[float],
    depth_t: list[float],
    size: tuple[int, int] = (8, 6),
    gt: str | None = None,
) -> Path:
    """A tiny sequence: rgb pixel (0,0) encodes the rgb index, depth = 1000 * (index + 1)."""
    w, h = size
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    for k, t in enumerate(rgb_t):
        bgr = np.zeros((h, w, 3), np.uint8)
        bgr[..., 0], bgr[..., 1], bgr[..., 2] = 10, 20, 30  # B, G, R
        bgr[0, 0] = k
        cv2.imwrite(str(root / "rgb" / f"{t:.6f}.png"), bgr)
    for k, t in enumerate(depth_t):
        depth = np.full((h, w), 1000 * (k + 1), np.uint16)
        cv2.imwrite(str(root / "depth" / f"{t:.6f}.png"), depth)
    write_list(root / "rgb.txt", [(t, f"rgb/{t:.6f}.png") for t in rgb_t])
    write_list(root / "depth.txt", [(t, f"depth/{t:.6f}.png") for t in depth_t])
    if gt is not None:
        (root / "groundtruth.txt").write_text(gt)
    return root


# ----------------------------------------------------------------------------- file lists


def test_read_file_list_comments_blank_lines_and_separators(tmp_path):
    path = tmp_path / "rgb.txt"
    path.write_text(
        "# color images\n"
        "# timestamp filename\n"
        "\n"
        "1305031102.175304 rgb/1305031102.175304.png\n"
        "   \n"
        "1305031102.211214\trgb/1305031102.211214.png\n"
        "# a comment in the middle\n"
        "1305031102.243211,rgb/1305031102.243211.png\n"
    )
    ts, names = read_file_list(path)
    np.testing.assert_array_equal(ts, [1305031102.175304, 1305031102.211214, 1305031102.243211])
    assert ts.dtype == np.float64
    assert names == [
        "rgb/1305031102.175304.png",
        "rgb/1305031102.211214.png",
        "rgb/1305031102.243211.png",
    ]


def test_read_file_list_missing(tmp_path):
    with pytest.raises(FileNotFoundError, match="depth.txt"):
        read_file_list(tmp_path / "depth.txt")


@pytest.mark.parametrize(
    ("third", "why"),
    [("1.5 c.png", "increasing"), ("2.0 c.png", "increasing")],  # unsorted; duplicate
)
def test_read_file_list_not_increasing(tmp_path, third, why):
    path = tmp_path / "rgb.txt"
    path.write_text(f"# header\n1.0 a.png\n\n2.0 b.png\n{third}\n3.0 d.png\n")
    with pytest.raises(ValueError, match=rf"rgb\.txt:5\b.*{why}"):
        read_file_list(path)


@pytest.mark.parametrize("bad", ["x1.0 a.png", "2.0", "nan a.png", "1e999 a.png"])
def test_read_file_list_bad_line_names_file_and_line(tmp_path, bad):
    path = tmp_path / "depth.txt"
    path.write_text(f"# header\n1.0 a.png\n{bad}\n")
    with pytest.raises(ValueError, match=r"depth\.txt:3\b"):
        read_file_list(path)


# ----------------------------------------------------------------------------- cameras


@pytest.mark.parametrize(
    ("name", "cam"),
    [
        ("rgbd_dataset_freiburg1_xyz", "fr1"),
        ("rgbd_dataset_freiburg2_desk", "fr2"),
        ("rgbd_dataset_freiburg3_teddy_first200", "fr3"),
        ("fr1_desk", "fr1"),
        ("tum-fr2-pioneer", "fr2"),
        ("TUM_FR3", "fr3"),
    ],
)
def test_camera_from_name(name, cam):
    assert camera_from_name(name) == CAMERAS[cam].camera


def test_camera_table_values():
    """TUM's published calibrations (file_formats page), 20 ms readout for each."""
    assert camera_from_name("freiburg1") == Camera(
        Intrinsics(517.3, 516.5, 318.6, 255.3), (0.2624, -0.9531, -0.0054, 0.0026, 1.1633),
        0.020)
    assert camera_from_name("freiburg2") == Camera(
        Intrinsics(520.9, 521.0, 325.1, 249.7), (0.2312, -0.7849, -0.0033, -0.0001, 0.9172),
        0.020)
    assert camera_from_name("freiburg3") == Camera(Intrinsics(535.4, 539.2, 320.1, 247.6),
                                                   None, 0.020)
    assert CAMERAS["kinect"].camera == Camera(Intrinsics(525.0, 525.0, 319.5, 239.5), None,
                                              0.020)


@pytest.mark.parametrize("name", ["my_sequence", "frame_fr12", "freiburg4", "freiburg1_vs_fr2"])
def test_camera_from_name_unknown(name):
    with pytest.raises(UnknownCameraError, match=r"pass camera= .*or intrinsics="):
        camera_from_name(name)


# ----------------------------------------------------------------------------- hand-made


def test_load_sequence_hand_made_association(tmp_path):
    # 0.108 is the nearest depth for both 0.100 and 0.115: 0.115 (7 ms) wins over 0.100 (8 ms),
    # which is left without a depth; 0.700 has no depth within 20 ms.
    rgb_t = [10.000, 10.100, 10.115, 10.300, 10.700]
    depth_t = [10.012, 10.108, 10.290, 10.500]
    gt = "# gt\n10.0 1 2 3 0 0 0 1\n10.11 4 5 6 0 0 1 0\n"
    root = make_sequence(tmp_path / "rgbd_dataset_freiburg3_fake", rgb_t, depth_t, gt=gt)
    seq = load_sequence(root)
    assert len(seq) == 3
    np.testing.assert_array_equal(seq.timestamps, [10.000, 10.115, 10.300])
    assert [p.name for p in seq.rgb_files] == ["10.000000.png", "10.115000.png", "10.300000.png"]
    assert [p.name for p in seq.depth_files] == ["10.012000.png", "10.108000.png", "10.290000.png"]
    assert seq.intrinsics == CAMERAS["fr3"].camera.intrinsics and seq.distortion is None
    assert (seq.width, seq.height) == (8, 6)
    assert seq.name == "rgbd_dataset_freiburg3_fake"
    assert seq.groundtruth is not None and seq.groundtruth[1].shape == (2, 7)

    rgb, depth = seq.load_frame(1)
    assert rgb.dtype == np.uint8 and rgb.shape == (6, 8, 3)
    assert rgb[0, 0].tolist() == [2, 2, 2]  # rgb index 2 (10.115)
    assert rgb[3, 3].tolist() == [30, 20, 10]  # RGB order
    assert depth.dtype == np.float32 and depth.shape == (6, 8)
    assert depth[2, 2] == np.float32(2000 / 5000.0)  # depth index 1 (10.108)
    with pytest.raises(IndexError):
        seq.load_frame(3)

    np.testing.assert_array_equal(groundtruth_pose_at(seq, 10.04), [1, 2, 3, 0, 0, 0, 1])
    np.testing.assert_array_equal(groundtruth_pose_at(seq, 10.3), [4, 5, 6, 0, 0, 1, 0])
    assert groundtruth_pose_at(seq, 10.3, max_diff=0.02) is None


def test_load_sequence_options_and_errors(tmp_path):
    root = make_sequence(tmp_path / "my_clip", [1.0, 2.0], [1.001, 2.001])
    with pytest.raises(UnknownCameraError, match="camera="):
        load_sequence(root)  # no camera in the name
    intr = Intrinsics(500.0, 500.0, 4.0, 3.0)
    seq = load_sequence(root, intrinsics=intr, depth_factor=1000.0)
    assert seq.intrinsics == intr and seq.distortion is None and seq.groundtruth is None
    assert groundtruth_pose_at(seq, 1.0) is None
    assert seq.load_frame(0)[1][0, 0] == np.float32(1.0)  # 1000 / 1000
    seq = load_sequence(root, camera=Camera(intr, (0.1, 0.0, 0.0, 0.0, 0.0)))
    assert seq.distortion == (0.1, 0.0, 0.0, 0.0, 0.0) and seq.readout_s == 0.0
    with pytest.raises(ValueError, match="camera= or intrinsics=, not both"):
        load_sequence(root, camera=Camera(intr), intrinsics=intr)
    with pytest.raises(ValueError, match=r"camera='fr9' is not a preset.*fr1, fr2, fr3"):
        load_sequence(root, camera="fr9")
    with pytest.raises(ValueError, match="distortion must be 4, 5, 8, 12 or 14"):
        load_sequence(root, camera=Camera(intr, (0.1, 0.0, 0.0)))
    with pytest.raises(ValueError, match="focal"):
        load_sequence(root, intrinsics=Intrinsics(-1.0, 500.0, 4.0, 3.0))
    with pytest.raises(ValueError, match="depth_factor"):
        load_sequence(root, intrinsics=intr, depth_factor=0.0)
    with pytest.raises(ValueError, match="no rgb/depth pair"):
        load_sequence(root, intrinsics=intr, max_diff=0.0005)
    with pytest.raises(FileNotFoundError, match="nowhere"):
        load_sequence(tmp_path / "nowhere")
    (root / "depth.txt").unlink()
    with pytest.raises(FileNotFoundError, match="depth.txt"):
        load_sequence(root, intrinsics=intr)


def test_load_sequence_explicit_camera_overrides_name(tmp_path):
    root = make_sequence(tmp_path / "rgbd_dataset_freiburg1_fake", [1.0], [1.001])
    fr1 = CAMERAS["fr1"].camera
    seq = load_sequence(root)
    assert (seq.intrinsics, seq.distortion, seq.readout_s) == fr1[:3]
    own = Camera(Intrinsics(500.0, 500.0, 4.0, 3.0))  # these images are 8x6
    seq = load_sequence(root, camera=own)
    assert (seq.intrinsics, seq.distortion, seq.readout_s) == own[:3]
    assert load_sequence(root, camera=own, readout_s=0.01).readout_s == 0.01


def test_load_frame_errors_hand_made(tmp_path):
    root = make_sequence(tmp_path / "fr3_bad", [1.0, 2.0, 3.0, 4.0], [1.0, 2.0, 3.0, 4.0])
    seq = load_sequence(root)
    # 0: depth of another size; 1: missing rgb; 2: 3-channel 16-bit depth; 3: 8-bit depth.
    cv2.imwrite(str(seq.depth_files[0]), np.ones((5, 7), np.uint16))
    seq.rgb_files[1].unlink()
    cv2.imwrite(str(seq.depth_files[2]), np.ones((6, 8, 3), np.uint16))
    cv2.imwrite(str(seq.depth_files[3]), np.ones((6, 8), np.uint8))
    with pytest.raises(ValueError, match=r"8x6.*7x5"):
        seq.load_frame(0)
    with pytest.raises(FileNotFoundError, match=r"2\.000000\.png"):
        seq.load_frame(1)
    with pytest.raises(ValueError, match=r"3\.000000\.png.*3 channels"):
        seq.load_frame(2)
    with pytest.raises(ValueError, match=r"4\.000000\.png.*8-bit"):
        seq.load_frame(3)


# ----------------------------------------------------------------------------- real clips


def test_fr1_xyz_first10(shared_clip):
    seq = load_sequence(shared_clip(FR1_XYZ))
    rgb_t, _ = read_file_list(seq.root / "rgb.txt")
    depth_t, _ = read_file_list(seq.root / "depth.txt")
    assert rgb_t.size == 10 and depth_t.size == 10
    # Only 9 pairs: rgb 1305031102.243211 loses depth .226738 to rgb .211214 (15.5 ms vs
    # 16.5 ms) and its other neighbour .262886 goes to rgb .275326 (12.4 ms).
    assert len(seq) == 9
    assert 1305031102.243211 not in seq.timestamps.tolist()
    assert np.all(np.diff(seq.timestamps) > 0)
    assert all(p.is_file() for p in seq.rgb_files + seq.depth_files)
    assert (seq.width, seq.height) == (640, 480)
    assert (seq.intrinsics, seq.distortion) == CAMERAS["fr1"].camera[:2]
    # The ground truth covers every frame of this clip at 100 Hz.
    for t in seq.timestamps:
        assert groundtruth_pose_at(seq, t, max_diff=0.01) is not None

    rgb, depth = seq.load_frame(0)
    assert rgb.shape == (480, 640, 3) and rgb.dtype == np.uint8
    assert depth.shape == (480, 640) and depth.dtype == np.float32
    valid = depth[depth > 0]
    assert valid.size > 0.5 * depth.size
    assert 0.5 < float(np.median(valid)) < 5.0
    assert float(valid.max()) < 10.0


def test_fr1_undistortion(shared_clip):
    root = shared_clip(FR1_XYZ)
    seq = load_sequence(root)
    raw_seq = load_sequence(root, intrinsics=seq.intrinsics)
    rgb, depth = seq.load_frame(2)
    rgb_raw, depth_raw = raw_seq.load_frame(2)
    # The raw frame is the file as it is.
    bgr = cv2.imread(str(seq.rgb_files[2]), cv2.IMREAD_COLOR)
    np.testing.assert_array_equal(rgb_raw, bgr[..., ::-1])
    raw16 = cv2.imread(str(seq.depth_files[2]), cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(depth_raw, raw16.astype(np.float32) / 5000.0)
    # Undistortion moves pixels ...
    changed = np.mean(np.any(rgb != rgb_raw, axis=-1))
    assert changed > 0.3
    assert np.mean(depth != depth_raw) > 0.1
    # ... and picks depth by nearest neighbour: no blended values (0 = outside the image).
    assert set(np.unique(depth).tolist()) <= set(np.unique(depth_raw).tolist()) | {0.0}
    # Same maps for every frame (cached), still correct on another frame.
    rgb5, _ = seq.load_frame(5)
    assert np.mean(np.any(rgb5 != raw_seq.load_frame(5)[0], axis=-1)) > 0.3


def test_fr3_teddy_has_no_distortion(shared_clip):
    seq = load_sequence(shared_clip(FR3_TEDDY))
    assert seq.distortion is None
    assert seq.intrinsics == CAMERAS["fr3"].camera.intrinsics
    # 200 rgb and 200 depth listed; the depth list runs 0.17 s longer, 193 pairs associate.
    assert len(seq) == 193
    rgb, depth = seq.load_frame(0)
    bgr = cv2.imread(str(seq.rgb_files[0]), cv2.IMREAD_COLOR)
    np.testing.assert_array_equal(rgb, bgr[..., ::-1])
    raw16 = cv2.imread(str(seq.depth_files[0]), cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(depth, raw16.astype(np.float32) / 5000.0)
    assert 0.5 < float(np.median(depth[depth > 0])) < 5.0
    # Ground truth starts 0.14 s after the first frame.
    assert seq.groundtruth is not None
    assert groundtruth_pose_at(seq, seq.timestamps[0], max_diff=0.02) is None
    assert groundtruth_pose_at(seq, seq.timestamps[-1], max_diff=0.02) is not None


def test_fr1_desk_clip9(shared_clip):
    seq = load_sequence(shared_clip(FR1_DESK))
    assert len(seq) == 9
    assert (seq.width, seq.height) == (640, 480)


def _copy_clip(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst, ignore=shutil.ignore_patterns("groundtruth.txt"))
    return dst


def test_real_corrupt_png(shared_clip, tmp_path):
    root = _copy_clip(shared_clip(FR1_XYZ), tmp_path / FR1_XYZ)
    seq = load_sequence(root)
    seq.rgb_files[3].write_bytes(np.random.default_rng(0).bytes(5000))
    with pytest.raises(ValueError, match=str(seq.rgb_files[3].name).replace(".", r"\.")):
        seq.load_frame(3)
    # A truncated depth PNG is refused too.
    data = seq.depth_files[4].read_bytes()
    seq.depth_files[4].write_bytes(data[: len(data) // 2])
    with pytest.raises(ValueError, match=r"depth.*" + seq.depth_files[4].name.replace(".", r"\.")):
        seq.load_frame(4)
    seq.load_frame(5)  # the others still load


def test_real_8bit_depth(shared_clip, tmp_path):
    root = _copy_clip(shared_clip(FR1_XYZ), tmp_path / FR1_XYZ)
    seq = load_sequence(root)
    raw16 = cv2.imread(str(seq.depth_files[0]), cv2.IMREAD_UNCHANGED)
    cv2.imwrite(str(seq.depth_files[0]), (raw16 // 256).astype(np.uint8))
    with pytest.raises(ValueError, match="8-bit"):
        seq.load_frame(0)


def test_subsequence_is_a_slice_of_the_frames():
    from edgevo_jax.cli import BUNDLED_CLIP

    seq = load_sequence(BUNDLED_CLIP)
    part = subsequence(seq, 3, 7)
    assert len(part) == 4 and part.name.endswith("_frames3-7")
    np.testing.assert_array_equal(part.timestamps, seq.timestamps[3:7])
    assert part.rgb_files == seq.rgb_files[3:7] and part.depth_files == seq.depth_files[3:7]
    assert part.groundtruth is seq.groundtruth and part.intrinsics == seq.intrinsics
    np.testing.assert_array_equal(part.load_frame(0)[0], seq.load_frame(3)[0])
    assert len(subsequence(seq, 5, 100)) == len(seq) - 5  # clipped to the sequence
    with pytest.raises(ValueError, match="no frames"):
        subsequence(seq, 7, 7)


def test_subsequence_with_a_step_lowers_the_frame_rate():
    from edgevo_jax.cli import BUNDLED_CLIP

    seq = load_sequence(BUNDLED_CLIP)
    every2 = subsequence(seq, 0, len(seq), step=2)
    assert len(every2) == (len(seq) + 1) // 2 and every2.name.endswith("_every2")
    np.testing.assert_array_equal(every2.timestamps, seq.timestamps[::2])
    assert every2.depth_files == seq.depth_files[::2]
    np.testing.assert_array_equal(every2.load_frame(1)[1], seq.load_frame(2)[1])
    with pytest.raises(ValueError, match="step must be a positive integer"):
        subsequence(seq, 0, 5, step=0)


def test_frame_step_keeps_every_kth_line_before_associating(tmp_path):
    """As a benchmark list at 1/k of the frame rate would be: every k-th line of rgb.txt and
    of depth.txt, then association (where the lists have gaps, pairs drop out)."""
    from edgevo_jax.cli import BUNDLED_CLIP

    full = load_sequence(BUNDLED_CLIP)
    every2 = load_sequence(BUNDLED_CLIP, frame_step=2)
    assert every2.name == f"{full.name}_every2" and every2.intrinsics == full.intrinsics
    rgb_t, _ = read_file_list(BUNDLED_CLIP / "rgb.txt")
    depth_t, _ = read_file_list(BUNDLED_CLIP / "depth.txt")
    kept = set(np.round(rgb_t[::2], 6)) & set(np.round(every2.timestamps, 6))
    assert len(kept) == len(every2) and 0 < len(every2) < len(full)
    # a gap in depth.txt shifts which depth lines are kept: those frames drop out
    root = tmp_path / "rgbd_dataset_freiburg1_xyz_gap"
    root.mkdir()
    for name in ("rgb", "depth"):
        (root / name).symlink_to(BUNDLED_CLIP / name)
    (root / "rgb.txt").write_text((BUNDLED_CLIP / "rgb.txt").read_text())
    depth_lines = (BUNDLED_CLIP / "depth.txt").read_text().splitlines(keepends=True)
    first = next(i for i, line in enumerate(depth_lines) if not line.startswith("#"))
    (root / "depth.txt").write_text("".join(depth_lines[:first] + depth_lines[first + 1:]))
    shifted = load_sequence(root, frame_step=2)
    assert len(shifted) < len(load_sequence(root))
    with pytest.raises(ValueError, match="frame_step must be a positive integer"):
        load_sequence(BUNDLED_CLIP, frame_step=0)
