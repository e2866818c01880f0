"""Sources (edgevo_jax.datasets.source): ROS1 and ROS2 bags written with rosbags from real
frames track to the folder's trajectory; ETH3D calibration.txt; every bad bag gets a message
naming its topic; a RealSense replayed through pyrealsense2's interface; rerun recordings
that rerun itself verifies."""

from __future__ import annotations

import shutil
import subprocess
import sys
import types
from pathlib import Path

import numpy as np
import pytest
from conftest import load_script

from edgevo_jax import cli
from edgevo_jax.camera import Intrinsics
from edgevo_jax.cli import BUNDLED_CLIP
from edgevo_jax.config import Config
from edgevo_jax.datasets import load_sequence
from edgevo_jax.datasets.realsense import open_realsense
from edgevo_jax.datasets.source import Source, open_source
from edgevo_jax.datasets.tum import read_calibration
from edgevo_jax.runs.run import run_sequence

pytest.importorskip("rosbags", reason="the ros extra (pip install 'edgevo_jax[ros]')")
to_bag = load_script("tum_to_bag")
#: a small tracker: these tests compare sources, not accuracy
CONFIG = Config(num_edges=256, window_size=3)


@pytest.fixture(scope="module")
def clip():
    return load_sequence(BUNDLED_CLIP)


def _poses(seq: Source) -> np.ndarray:
    run = run_sequence(seq, CONFIG, progress=False)
    if hasattr(seq, "close"):  # a bag's reader, a camera
        seq.close()
    return np.stack([r.pose for r in run.results])


@pytest.fixture(scope="module")
def folder_poses(clip):
    return _poses(clip)


@pytest.mark.parametrize("ros2", [False, True], ids=["ros1", "ros2"])
def test_a_bag_tracks_like_its_folder(clip, folder_poses, tmp_path, ros2):
    """rgb8 / bgr8 colour, 32FC1 depth with NaN, camera_info with the fr1 K and D, named as
    the benchmark names its bags: the same images, camera, undistortion and rolling shutter
    as the folder, so the same trajectory."""
    bag = to_bag.write_bag(clip, tmp_path / (clip.name + ("" if ros2 else ".bag")), ros2=ros2,
                           rgb_encoding="bgr8" if ros2 else "rgb8")
    seq = open_source(bag, groundtruth=clip.root / "groundtruth.txt")  # the same start pose
    assert isinstance(seq, Source) and len(seq) == len(clip)
    assert seq.intrinsics == clip.intrinsics and np.allclose(seq.distortion, clip.distortion)
    assert seq.readout_s == clip.readout_s > 0
    assert np.allclose(seq.timestamps, clip.timestamps, atol=1e-6)
    rgb, depth = seq.rectify_frame(*seq.decode_frame(3))
    rgb_f, depth_f = clip.load_frame(3)
    assert np.array_equal(rgb, rgb_f) and np.array_equal(depth, depth_f)
    poses = _poses(seq)
    assert np.abs(poses[:, :3, 3] - folder_poses[:, :3, 3]).max() <= 1e-3


def test_millimetre_depth_and_ground_truth_file(clip, tmp_path):
    bag = to_bag.write_bag(clip, tmp_path / "mm.bag", frames=3, depth_encoding="16UC1")
    seq = open_source(bag, groundtruth=clip.root / "groundtruth.txt")
    rgb, raw = clip.decode_frame(1)
    rgb_mm, mm = seq.decode_frame(1)
    assert mm.dtype == np.uint16 and np.array_equal(mm, np.round(raw / 5.0))  # whole mm
    depth = seq.rectify_frame(rgb_mm, mm)[1]  # undistorted as the folder's, in metres
    expected = clip.rectify_frame(rgb, (mm * 5).astype(np.uint16))[1]
    assert depth.dtype == np.float32 and np.allclose(depth, expected, atol=1e-6)
    assert seq.groundtruth is not None and len(seq.groundtruth[0]) > 0


def _cli_error(capsys, *argv: str) -> str:
    assert cli.main(["run", *argv, "--no-progress"]) == 2
    return capsys.readouterr().err


def test_bad_bags_name_the_topic(clip, tmp_path, capsys):
    bag = to_bag.write_bag(clip, tmp_path / "ok.bag", frames=2)
    err = _cli_error(capsys, str(bag), "--rgb-topic", "/camera/rgb/image_raw")
    assert "no topic /camera/rgb/image_raw (rgb images)" in err
    assert "/camera/rgb/image_color" in err and "pass --rgb-topic" in err  # the topics it has
    with pytest.raises(ValueError, match=r"image_raw \(rgb images\).*: pass rgb_topic=$"):
        open_source(bag, rgb_topic="/camera/rgb/image_raw")  # the API names its argument
    err = _cli_error(capsys, str(bag), "--depth-topic", "/camera/rgb/camera_info")
    assert "/camera/rgb/camera_info" in err and "sensor_msgs/msg/CameraInfo" in err
    small = to_bag.write_bag(clip, tmp_path / "small.bag", frames=2, depth_size=(320, 240))
    err = _cli_error(capsys, str(small))
    assert "/camera/rgb/image_color is 640x480" in err and "/camera/depth/image is 320x240" in err
    blind = to_bag.write_bag(clip, tmp_path / "blind.bag", frames=2, camera_info=False)
    err = _cli_error(capsys, str(blind))
    assert "no camera_info topic /camera/rgb/camera_info" in err and "--intrinsics" in err
    with open_source(blind, intrinsics=clip.intrinsics) as seq:  # the camera given: it runs
        assert len(seq) == 2 and seq.distortion is None
    yuv = to_bag.write_bag(clip, tmp_path / "yuv.bag", frames=2, rgb_encoding="yuv422")
    err = _cli_error(capsys, str(yuv))
    assert "rgb topic /camera/rgb/image_color: encoding 'yuv422'" in err
    err = _cli_error(capsys, str(tmp_path / "missing.bag"))
    assert "ROS bag not found" in err
    (tmp_path / "junk.bag").write_bytes(b"not a bag")
    assert "cannot read the ROS bag" in _cli_error(capsys, str(tmp_path / "junk.bag"))


def test_calibration_txt_gives_the_camera(clip, tmp_path):
    """An ETH3D-style folder (no camera in its name) runs from its calibration.txt, as the
    folder run with those intrinsics given."""
    root = tmp_path / "mycamera"
    shutil.copytree(BUNDLED_CLIP, root)
    with pytest.raises(ValueError, match="cannot tell the camera"):
        load_sequence(root)
    (root / "calibration.txt").write_text("517.3 516.5 318.6 255.3\n")
    seq = load_sequence(root)
    assert seq.intrinsics == Intrinsics(517.3, 516.5, 318.6, 255.3) and seq.distortion is None
    given = load_sequence(BUNDLED_CLIP, intrinsics=seq.intrinsics)
    assert np.array_equal(_poses(seq), _poses(given))
    (root / "calibration.txt").write_text("# fx fy cx cy\n517.3 516.5 318.6\n")
    with pytest.raises(ValueError, match=r"calibration.txt: expected 4 numbers \(fx fy cx cy\) "
                       r"or 9 .*got 3"):
        read_calibration(root / "calibration.txt")


class _Replay:
    """pyrealsense2's interface (the calls ``open_realsense`` makes), replaying a clip's
    frames as a camera would deliver them: z16 depth in 1/5000 m units, rgb8 colour."""

    def __init__(self, seq, *, coeffs=(0.0,) * 5):
        self.seq, self.coeffs, self.stopped = seq, coeffs, False
        self.stream = types.SimpleNamespace(color="color", depth="depth")
        self.format = types.SimpleNamespace(rgb8="rgb8", z16="z16")

    def config(self):
        return types.SimpleNamespace(enable_stream=lambda *a: None,
                                     enable_device=lambda s: None)

    def pipeline(self):
        replay, frames = self, iter(range(len(self.seq)))
        intr = self.seq.intrinsics
        stream = types.SimpleNamespace(fx=intr.fx, fy=intr.fy, ppx=intr.cx, ppy=intr.cy,
                                       coeffs=list(self.coeffs), model="brown_conrady")
        profile = types.SimpleNamespace(
            get_device=lambda: types.SimpleNamespace(first_depth_sensor=lambda: types.
                                                     SimpleNamespace(get_depth_scale=lambda:
                                                                     1 / 5000)),
            get_stream=lambda s: types.SimpleNamespace(as_video_stream_profile=lambda: types.
                                                       SimpleNamespace(get_intrinsics=lambda:
                                                                       stream)))

        def wait_for_frames():
            i = next(frames)
            rgb, raw = replay.seq.decode_frame(i)
            frame = lambda a: types.SimpleNamespace(get_data=lambda: a)  # noqa: E731
            return types.SimpleNamespace(
                get_color_frame=lambda: frame(rgb), get_depth_frame=lambda: frame(raw),
                get_timestamp=lambda: replay.seq.timestamps[i] * 1e3)

        def stop():
            replay.stopped = True

        return types.SimpleNamespace(start=lambda config: profile,
                                     wait_for_frames=wait_for_frames, stop=stop)

    def align(self, to):
        return types.SimpleNamespace(process=lambda frames: frames)


def test_realsense_replay_tracks_like_the_folder(tmp_path):
    """Recorded frames through the RealSense interface: same trajectory within 1 mm."""
    seq = load_sequence(BUNDLED_CLIP, intrinsics=Intrinsics(517.3, 516.5, 318.6, 255.3))
    cam = open_realsense(rs=_Replay(seq), max_frames=len(seq))
    assert isinstance(cam, Source) and cam.intrinsics == seq.intrinsics
    poses, folder = _poses(cam), _poses(seq)  # a camera starts at the identity
    relative = np.linalg.inv(folder[0]) @ folder
    assert np.abs(poses[:, :3, 3] - relative[:, :3, 3]).max() <= 1e-3
    with pytest.raises(IndexError, match="in order"):
        cam.decode_frame(0)
    cam.close()
    assert cam.rs.stopped
    with pytest.raises(ValueError, match="lens distortion"):
        open_realsense(rs=_Replay(seq, coeffs=(0.1, 0, 0, 0, 0)), max_frames=2)


def test_rerun_recording_is_verified_by_rerun(tmp_path, capsys):
    pytest.importorskip("rerun", reason="the rerun extra (pip install 'edgevo_jax[rerun]')")
    beside = Path(sys.executable).parent / "rerun"  # rerun-sdk's command, in this venv
    rerun = str(beside) if beside.is_file() else shutil.which("rerun")
    if rerun is None:
        pytest.skip("rerun-sdk's rerun command is neither beside python nor on PATH")
    rrd = tmp_path / "run.rrd"
    assert cli.main(["run", "--no-progress", "--out", str(tmp_path / "t.txt"),
                     "--rerun", str(rrd), "--max-frames", "5"]) == 0
    assert f"rerun recording: {rrd}" in capsys.readouterr().out
    done = subprocess.run([rerun, "rrd", "verify", str(rrd)], capture_output=True, text=True,
                          env={"RERUN_ANALYTICS": "0", "PATH": str(Path(rerun).parent)})
    assert done.returncode == 0, done.stderr
    stats = subprocess.run([rerun, "rrd", "stats", str(rrd)], capture_output=True, text=True)
    assert stats.returncode == 0
