"""Perturbed copies of a TUM folder (edgevo_jax.datasets.perturb): read back with the true
camera they return, they give the source's frames and times again; read with their own
calibration.txt, the injected intrinsics error."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from edgevo_jax.camera import CAMERAS
from edgevo_jax.camera_file import read_camera_file
from edgevo_jax.cli import BUNDLED_CLIP
from edgevo_jax.datasets import load_sequence
from edgevo_jax.datasets.perturb import TRUE_CAMERA, perturbed_copy

FR1 = CAMERAS["fr1"].camera


def _pose(rotation_deg, translation_m) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(np.deg2rad(np.asarray(rotation_deg, np.float64)))[0]
    T[:3, 3] = translation_m
    return T


def test_scale_time_offset_and_focal_length(tmp_path):
    dst = tmp_path / "copy"
    truth = perturbed_copy(BUNDLED_CLIP, dst, depth_scale=1.03, depth_time_offset_s=0.012,
                           fx_factor=1.01)
    assert truth == FR1._replace(depth_scale=1.03, depth_time_offset_s=0.012)
    wrong = load_sequence(dst)  # its calibration.txt: fx off, readout 0
    assert wrong.intrinsics == FR1.intrinsics._replace(fx=517.3 * 1.01)
    assert wrong.distortion == FR1.distortion and wrong.readout_s == 0.0
    f = read_camera_file(dst / TRUE_CAMERA)
    assert f.camera == truth and f.source["fx_factor"] == 1.01

    src = load_sequence(BUNDLED_CLIP)
    seq = load_sequence(dst, camera=truth)
    np.testing.assert_allclose(seq.depth_timestamps, src.depth_timestamps, rtol=0, atol=1e-6)
    assert [p.name for p in seq.rgb_files] == [p.name for p in src.rgb_files]
    assert (dst / src.rgb_files[0].relative_to(BUNDLED_CLIP)).is_symlink()
    for i in (0, len(src) - 1):
        (rgb0, d0), (rgb, d) = src.load_frame(i), seq.load_frame(i)
        assert np.array_equal(rgb, rgb0)
        assert np.array_equal(d > 0, d0 > 0)
        assert np.max(np.abs(d - d0)) <= 0.6 * 1.03 / 5000 + 1e-6  # one raw unit's rounding


def test_depth_pose(tmp_path):
    """A depth camera 1 cm to the side and turned by half a degree: read back with the true
    camera, the depth re-rendered into the colour camera matches the source's (undistorted:
    the copy holds undistorted images) on most pixels."""
    pose = _pose([0.3, -0.5, 0.2], [0.01, -0.004, 0.002])
    dst = tmp_path / "posed"
    truth = perturbed_copy(BUNDLED_CLIP, dst, depth_pose=pose, link=False)
    assert truth.distortion is None and np.allclose(truth.T_color_depth, pose)
    src = load_sequence(BUNDLED_CLIP)
    raw = load_sequence(dst, camera=truth._replace(T_color_depth=None))
    seq = load_sequence(dst, camera=truth)
    rgb0, d0 = src.load_frame(2)
    rgb, d = seq.load_frame(2)
    assert np.array_equal(rgb, rgb0) and not (dst / "rgb").is_symlink()
    valid = d0 > 0
    close = valid & (np.abs(d - d0) < 2e-3)
    assert close.sum() > 0.85 * valid.sum()
    far = valid & (np.abs(raw.load_frame(2)[1] - d0) < 2e-3)
    assert far.sum() < close.sum()  # without the pose, the copy's depth does not match


def test_errors(tmp_path):
    (tmp_path / "there").mkdir()
    with pytest.raises(FileExistsError, match="exists already"):
        perturbed_copy(BUNDLED_CLIP, tmp_path / "there")
    with pytest.raises(ValueError, match="depth_scale"):
        perturbed_copy(BUNDLED_CLIP, tmp_path / "a", depth_scale=0.0)
    with pytest.raises(ValueError, match="depth_pose"):
        perturbed_copy(BUNDLED_CLIP, tmp_path / "b", depth_pose=np.eye(3))
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()
