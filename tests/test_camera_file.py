"""The camera file (edgevo_jax.camera_file, docs/camera_file.md): TOML written and read back,
its errors, the camera's depth fields checked by ``Camera.validate`` and applied by the TUM
reader, refused by the sources that cannot apply them, and ``edgevo run --calibration
FILE.toml`` reaching the reader (without tracking)."""

from __future__ import annotations

import re
from pathlib import Path

import cv2
import numpy as np
import pytest

from edgevo_jax import cli
from edgevo_jax.camera import CAMERAS, Camera, Intrinsics
from edgevo_jax.camera_file import (
    CameraFile,
    read_camera_file,
    read_camera_toml,
    write_camera_toml,
)
from edgevo_jax.cli import BUNDLED_CLIP
from edgevo_jax.datasets import load_sequence, read_calibration
from edgevo_jax.datasets.bag import load_bag
from edgevo_jax.datasets.realsense import open_realsense
from edgevo_jax.datasets.source import depth_lags
from edgevo_jax.datasets.tum import read_file_list
from edgevo_jax.depth_registration import register_depth

FR1 = CAMERAS["fr1"].camera
DOC = Path(__file__).resolve().parents[1] / "docs" / "camera_file.md"


def _pose(rotation_deg, translation_m) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(np.deg2rad(np.asarray(rotation_deg, np.float64)))[0]
    T[:3, 3] = translation_m
    return T


POSE = _pose([0.5, -0.2, 0.1], [0.01, -0.002, 0.0005])
FULL = FR1._replace(depth_scale=1.03, depth_time_offset_s=-0.012, T_color_depth=POSE)


def _same(a: Camera, b: Camera, atol: float = 0.0) -> bool:
    if (a.T_color_depth is None) != (b.T_color_depth is None):
        return False
    pose = a.T_color_depth is None or np.allclose(a.T_color_depth, b.T_color_depth, rtol=0,
                                                  atol=atol)
    return a[:5] == b[:5] and bool(pose)


def _write(tmp_path, text: str) -> Path:
    p = tmp_path / "camera.toml"
    p.write_text(text)
    return p


def test_round_trip_with_every_field_and_table(tmp_path):
    source = {"clip": "rgbd_dataset_freiburg1_xyz", "frames": 798, "note": 'a "quoted"\nline',
              "robust": True, "window_s": [0.5, 1.0]}
    uncertainty = {"fx": 0.4, "depth_scale": 0.002, "rotation_deg": (0.1, 0.1, 0.2),
                   "distortion": (0.01, 0.02, 0.001, 0.001, 0.05)}
    observable = {"readout_s": "no fast rotation in the clip"}
    path = write_camera_toml(tmp_path / "c.toml", FULL, source=source,
                             uncertainty=uncertainty, observable=observable)
    back = read_camera_file(path)
    assert isinstance(back, CameraFile)
    assert _same(back.camera, FULL, atol=1e-15)
    assert back.source == source
    assert back.uncertainty == uncertainty
    assert back.not_observable == observable
    text = path.read_text()
    assert "rotation_deg = [0.5, -0.2, 0.1]" in text  # as a person would write it
    assert "fx = 517.3  # pixels" in text
    assert _same(read_camera_toml(path), FULL, atol=1e-15)
    assert _same(read_calibration(path), FULL, atol=1e-15)  # '.toml': a camera file


def test_defaults_read_as_the_plain_camera(tmp_path):
    p = _write(tmp_path, "fx = 525\nfy = 525.0\ncx = 319.5\ncy = 239.5\n")
    cam = read_camera_toml(p)
    assert cam == Camera(Intrinsics(525.0, 525.0, 319.5, 239.5))
    assert cam.depth_fields() == [] and cam.T_color_depth is None
    assert read_camera_file(p)[1:] == ({}, {}, {})
    again = read_camera_toml(write_camera_toml(tmp_path / "again.toml", cam))
    assert again == cam


def test_the_documented_example_reads(tmp_path):
    """The complete example of docs/camera_file.md is a camera file."""
    block = re.search(r"```toml\n(.*?)```", DOC.read_text(), re.DOTALL)
    assert block, "docs/camera_file.md has no ```toml example"
    f = read_camera_file(_write(tmp_path, block.group(1)))
    assert f.camera.T_color_depth is not None and f.camera.depth_scale != 1.0
    assert f.source and f.uncertainty and f.not_observable


@pytest.mark.parametrize("text, match", [
    ("fx = 1\nfy = 1\ncx = 1\ncy = 1\nfocal = 2\nk1 = 0\n",
     r"unknown keys focal, k1 in the camera file; the known keys are fx, fy, cx, cy, "
     r"distortion"),
    ("fx = 1\nfy = 1\ncx = 1\ncy = 1\n[depth_pose]\nrotation_deg = [0, 0, 0]\n"
     "translation_m = [0, 0, 0]\nscale = 1\n",
     r"unknown key scale in \[depth_pose\]; the known keys are rotation_deg, translation_m"),
    ("fx = 1\nfy = 1\ncx = 1\ncy = 1\n[uncertainty]\nfocal = 1\n",
     r"unknown key focal in \[uncertainty\]; the known keys are fx"),
    ("fx = 1\nfy = 1\ncx = 1\n", "missing cy"),
    ("fx = '525'\nfy = 1\ncx = 1\ncy = 1\n", "fx must be a number"),
    ("fx = 1\nfy = 1\ncx = 1\ncy = 1\ndistortion = 0.1\n", "distortion must be a list"),
    ("fx = 1\nfy = 1\ncx = 1\ncy = 1\ndistortion = [0.1, 0.2]\n", "distortion must be 4, 5"),
    ("fx = 1\nfy = 1\ncx = 1\ncy = 1\ndepth_scale = 0\n", "depth_scale must be finite and > 0"),
    ("fx = 1\nfy = 1\ncx = 1\ncy = 1\ndepth_time_offset_s = nan\n",
     "depth_time_offset_s must be finite"),
    ("fx = 1\nfy = 1\ncx = 1\ncy = 1\n[depth_pose]\nrotation_deg = [0, 0, 0]\n",
     "translation_m missing"),
    ("fx = 1\nfy = 1\ncx = 1\ncy = 1\n[depth_pose]\nrotation_deg = [0, 0]\n"
     "translation_m = [0, 0, 0]\n", "depth_pose.rotation_deg must have 3 numbers"),
    ("fx = 1\nfy = 1\ncx = 1\ncy = 1\n[uncertainty]\nfx = -1\n", "uncertainty.fx must be"),
    ("fx = 1\nfy = 1\ncx = 1\ncy = 1\n[not_observable]\nfx = 1\n", "the reason"),
    ("fx = 1\nfy = 1\ncx = 1\ncy = 1\n[uncertainty]\ntranslation_m = [0.1]\n",
     "uncertainty.translation_m must have 3 numbers"),
    ("fx = 1\nfy = 1\ncx = 1\ncy = 1\ndistortion = [0, 0, 0, 0]\n[uncertainty]\n"
     "distortion = [0.1, 0.1, 0.1, 0.1, 0.1]\n", "uncertainty.distortion must have 4 numbers"),
    ("fx = 1\nfy = 1\ncx = 1\ncy = 1\nsource = 3\n", r"source must be a table"),
    ("fx = 1 fy = 2\n", "not a TOML camera file"),
])
def test_errors_name_the_file_and_the_problem(tmp_path, text, match):
    p = _write(tmp_path, text)
    with pytest.raises(ValueError, match=match) as err:
        read_camera_file(p)
    assert str(p) in str(err.value)


def test_missing_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="camera file not found"):
        read_camera_toml(tmp_path / "none.toml")
    with pytest.raises(FileNotFoundError):
        read_calibration(tmp_path / "none.toml")


def test_writer_refuses_what_the_reader_would(tmp_path):
    with pytest.raises(ValueError, match="unknown key focal"):
        write_camera_toml(tmp_path / "c.toml", FR1, uncertainty={"focal": 1.0})
    with pytest.raises(ValueError, match="cannot write a dict"):
        write_camera_toml(tmp_path / "c.toml", FR1, source={"nested": {"a": 1}})
    with pytest.raises(ValueError, match="depth_scale"):
        write_camera_toml(tmp_path / "c.toml", FR1._replace(depth_scale=-1.0))
    assert not (tmp_path / "c.toml").exists()


def test_validate_checks_the_depth_fields():
    assert FR1.validate() == FR1 and FR1.validate().T_color_depth is None
    cam = FULL.validate()
    assert cam.depth_fields() == ["depth_scale", "depth_time_offset_s", "T_color_depth"]
    assert cam.T_color_depth is not POSE and not cam.T_color_depth.flags.writeable
    for bad, match in ((dict(depth_scale=0.0), "depth_scale"),
                       (dict(depth_scale=float("inf")), "depth_scale"),
                       (dict(depth_time_offset_s=float("nan")), "depth_time_offset_s"),
                       (dict(T_color_depth=np.eye(3)), "T_color_depth must be a 4x4"),
                       (dict(T_color_depth=np.diag([1.0, 1.0, 2.0, 1.0])), "rotation")):
        with pytest.raises(ValueError, match=match):
            FR1._replace(**bad).validate()


def test_the_tum_reader_applies_the_depth_fields():
    base = load_sequence(BUNDLED_CLIP)
    rgb0, depth0 = base.load_frame(3)
    same = load_sequence(BUNDLED_CLIP, camera=FR1._replace(depth_scale=1.0))
    rgb, depth = same.load_frame(3)
    assert np.array_equal(depth, depth0) and np.array_equal(rgb, rgb0)

    scaled = load_sequence(BUNDLED_CLIP, camera=FR1._replace(depth_scale=1.03))
    assert np.array_equal(scaled.load_frame(3)[1], depth0 * np.float32(1.03))

    depth_t, _ = read_file_list(BUNDLED_CLIP / "depth.txt")
    shifted = load_sequence(BUNDLED_CLIP, camera=FR1._replace(depth_time_offset_s=0.01))
    k = np.searchsorted(depth_t + 0.01, shifted.depth_timestamps)
    assert np.array_equal(shifted.depth_timestamps, (depth_t + 0.01)[k])  # true times
    assert np.all(np.abs(shifted.depth_timestamps - shifted.timestamps) <= 0.02)
    # the tracker's depth lags: the true times' differences, only for a stated offset
    np.testing.assert_array_equal(depth_lags(shifted),
                                  shifted.depth_timestamps - np.asarray(shifted.timestamps))
    assert depth_lags(same) is None
    # 30 ms earlier: rgb 102.175304 pairs with the depth image of 102.194330 (true time
    # 102.164330), not with 102.160407's (true time 102.130407)
    later = load_sequence(BUNDLED_CLIP, camera=FR1._replace(depth_time_offset_s=-0.03))
    first = later.rgb_files.index(BUNDLED_CLIP / "rgb" / "1305031102.175304.png")
    assert later.depth_files[first].name == "1305031102.194330.png"

    posed = load_sequence(BUNDLED_CLIP, camera=FR1._replace(T_color_depth=POSE))
    expected = register_depth(depth0, FR1.intrinsics, FR1.intrinsics, POSE)
    assert np.array_equal(posed.load_frame(3)[1], expected)
    assert not np.array_equal(expected, depth0)


def test_bags_refuse_depth_fields(tmp_path):
    bag = tmp_path / "x.bag"
    bag.write_bytes(b"")
    with pytest.raises(ValueError, match=r"a ROS bag cannot apply the camera's depth_scale, "
                                         r"T_color_depth; only TUM sequence folders"):
        load_bag(bag, camera=FR1._replace(depth_scale=1.1, T_color_depth=np.eye(4)))
    with pytest.raises(ValueError, match=r"a RealSense camera cannot apply the camera's "
                                         r"depth_time_offset_s"):
        open_realsense(camera=FR1._replace(depth_time_offset_s=0.01), rs=object())


class _Stop(Exception):
    pass


def test_cli_calibration_takes_a_camera_file(tmp_path, monkeypatch):
    """`edgevo run CLIP --calibration camera.toml` hands the tracker a sequence with the
    file's camera, depth fields included; a bad file stops the run naming the option."""
    seen = []

    def record(seq, *args, **kwargs):
        seen.append(seq)
        raise _Stop

    monkeypatch.setattr("edgevo_jax.runs.run.run_sequence", record)
    path = write_camera_toml(tmp_path / "camera.toml", FULL)
    with pytest.raises(_Stop):
        cli.main(["run", str(BUNDLED_CLIP), "--calibration", str(path), "--no-progress",
                  "--out", str(tmp_path / "t.txt")])
    (seq,) = seen
    assert (seq.intrinsics, seq.distortion, seq.readout_s) == FR1[:3]
    assert seq.depth_scale == 1.03 and seq.depth_time_offset_s == -0.012
    assert np.allclose(seq.T_color_depth, POSE, rtol=0, atol=1e-15)

    bad = _write(tmp_path, "fx = 1\nfy = 1\ncx = 1\ncy = 1\nfocal = 2\n")
    assert cli.main(["run", str(BUNDLED_CLIP), "--calibration", str(bad),
                     "--no-progress"]) == 2
