"""Cameras (edgevo_jax.camera): the presets table, calibration files, and how a camera is
given to ``load_sequence`` / ``open_source`` and to ``edgevo run`` (--camera, --calibration,
--intrinsics), with errors that name the API's arguments in the API and the CLI's options on
the CLI."""

from __future__ import annotations

import shutil

import pytest

from edgevo_jax import cli
from edgevo_jax.camera import CAMERAS, Camera, Intrinsics
from edgevo_jax.cli import BUNDLED_CLIP
from edgevo_jax.datasets import load_sequence, read_calibration
from edgevo_jax.datasets.source import UnknownCameraError, open_source

FR1 = CAMERAS["fr1"].camera


@pytest.fixture(scope="module")
def renamed(tmp_path_factory):
    """A copy of the bundled fr1 clip under a name that names no camera."""
    root = tmp_path_factory.mktemp("copy") / "corrupt"
    shutil.copytree(BUNDLED_CLIP, root)
    return root


def _camera_of(seq) -> Camera:
    return Camera(seq.intrinsics, seq.distortion, seq.readout_s)


@pytest.mark.slow
def test_renamed_copy_with_its_preset_tracks_bit_for_bit(renamed, tmp_path, capsys):
    """`edgevo run COPY --camera fr1` writes the very bytes `edgevo run` writes for the folder
    named freiburg1: the same intrinsics, undistortion and rolling-shutter readout."""
    assert cli.main(["run", str(renamed), "--no-progress", "--out", str(tmp_path / "c.txt")]) == 2
    assert "--camera (fr1, fr2, fr3, kinect)" in capsys.readouterr().err
    for argv, out in (([str(BUNDLED_CLIP)], "folder.txt"),
                      ([str(renamed), "--camera", "fr1"], "copy.txt")):
        assert cli.main(["run", *argv, "--no-progress", "--out", str(tmp_path / out)]) == 0
    folder = (tmp_path / "folder.txt").read_bytes()
    assert len(folder.splitlines()) == 9 and (tmp_path / "copy.txt").read_bytes() == folder


def test_a_preset_is_the_named_folder_camera(renamed):
    """Without running the tracker: the copy with camera='fr1' (and a 9-number calibration
    file of fr1 with its readout) is the folder's camera, in every field."""
    folder = load_sequence(BUNDLED_CLIP)
    assert _camera_of(folder) == FR1 and FR1.readout_s == 0.020
    assert _camera_of(load_sequence(renamed, camera="fr1")) == FR1
    assert _camera_of(load_sequence(renamed, camera=FR1)) == FR1
    cal = renamed.parent / "fr1.txt"
    cal.write_text("# TUM fr1\n517.3 516.5 318.6 255.3\n0.2624 -0.9531 -0.0054 0.0026 1.1633\n")
    assert read_calibration(cal) == FR1._replace(readout_s=0.0)  # a file: global shutter
    assert _camera_of(load_sequence(renamed, camera=read_calibration(cal), readout_s=0.02)) == FR1
    with pytest.raises(UnknownCameraError, match=r"'corrupt'.*pass camera= \(a preset: fr1, "
                       r"fr2, fr3, kinect; .*\) or intrinsics="):
        load_sequence(renamed)


@pytest.mark.parametrize("name", list(CAMERAS))
def test_every_preset_is_accepted_by_the_cli(name, renamed, monkeypatch):
    """`edgevo run COPY --camera NAME` hands the tracker a source with that preset's camera."""
    seen = []

    def record(seq, *args, **kwargs):
        seen.append(_camera_of(seq))
        raise _Stop

    monkeypatch.setattr("edgevo_jax.runs.run.run_sequence", record)
    with pytest.raises(_Stop):
        cli.main(["run", str(renamed), "--camera", name, "--no-progress",
                  "--out", str(renamed.parent / "t.txt")])
    assert seen == [CAMERAS[name].camera]
    assert CAMERAS[name].about and CAMERAS[name].camera.validate() == CAMERAS[name].camera


class _Stop(Exception):
    pass


def test_kinect_preset_is_tums_default():
    """TUM's "ROS default" Kinect calibration: fx = fy = 525, cx = 319.5, cy = 239.5, no
    distortion; a Kinect-type rolling shutter (the Freiburg cameras' 20 ms)."""
    assert CAMERAS["kinect"].camera == Camera(Intrinsics(525.0, 525.0, 319.5, 239.5), None,
                                              0.020)


def test_calibration_files(tmp_path):
    """4 numbers (ETH3D's calibration.txt) or 9 (with OpenCV distortion), spaces or commas,
    one line or several; anything else names the file and what is wrong."""
    p = tmp_path / "cam.txt"
    p.write_text("525 525 319.5 239.5\n")
    assert read_calibration(p) == Camera(Intrinsics(525.0, 525.0, 319.5, 239.5))
    p.write_text("# mine\n\n500, 501, 320, 240, 0.1, -0.2, 0.001, 0.002, 0.05\n")
    assert read_calibration(p) == Camera(Intrinsics(500.0, 501.0, 320.0, 240.0),
                                         (0.1, -0.2, 0.001, 0.002, 0.05))
    for text, problem in (("500 501 320\n", r"expected 4 numbers \(fx fy cx cy\) or 9 .*got 3"),
                          ("500 501 320 240 0.1 0.2 0 0\n", "got 8"),
                          ("500 501 320 x\n", "must be numbers, got '500 501 320 x'"),
                          ("500 -501 320 240\n", "focal lengths must be positive"),
                          ("500 501 320 240 0.1 nan 0 0 0\n", "finite OpenCV coefficients"),
                          ("", "got 0")):
        p.write_text(text)
        with pytest.raises(ValueError, match=rf"^{p}: .*{problem}"):
            read_calibration(p)
    with pytest.raises(FileNotFoundError, match="calibration file not found"):
        read_calibration(tmp_path / "none.txt")


def _run_error(capsys, *argv: str) -> str:
    assert cli.main(["run", *argv, "--no-progress"]) == 2
    return capsys.readouterr().err


def test_cli_camera_errors_name_the_options(renamed, tmp_path, capsys):
    bad = tmp_path / "bad.txt"
    bad.write_text("517.3 516.5 318.6 255.3 0.26 0.1 0\n")
    err = _run_error(capsys, str(renamed), "--calibration", str(bad))
    assert err.startswith(f"edgevo: error: --calibration {bad}: expected 4 numbers"), err
    err = _run_error(capsys, str(renamed), "--calibration", str(tmp_path / "none.txt"))
    assert f"--calibration file not found: {tmp_path / 'none.txt'}" in err
    err = _run_error(capsys, str(renamed), "--intrinsics", "517.3", "0", "318.6", "255.3")
    assert "--intrinsics 517.3 0 318.6 255.3: intrinsics: focal lengths must be positive" in err
    err = _run_error(capsys, str(renamed))
    assert "name 'corrupt'" in err and "--camera (fr1, fr2, fr3, kinect), --calibration FILE" \
        in err and "--intrinsics FX FY CX CY" in err and "camera=" not in err
    for argv in (["--camera", "fr1", "--intrinsics", "1", "1", "1", "1"],
                 ["--camera", "fr1", "--calibration", str(bad)], ["--camera", "fr9"]):
        with pytest.raises(SystemExit) as info:
            cli.main(["run", str(renamed), *argv])
        assert info.value.code == 2
    err = capsys.readouterr().err
    assert "argument --intrinsics: not allowed with argument --camera" in err
    assert "argument --calibration: not allowed with argument --camera" in err
    assert "argument --camera: invalid choice: 'fr9' (choose from" in err


def test_api_camera_errors_name_the_arguments(renamed):
    with pytest.raises(ValueError, match="pass camera= or intrinsics=, not both"):
        open_source(renamed, camera="fr1", intrinsics=FR1.intrinsics)
    with pytest.raises(ValueError, match=r"camera='fr9' is not a preset; the presets are fr1"):
        open_source(renamed, camera="fr9")
    with pytest.raises(ValueError, match="readout_s must be finite and >= 0"):
        load_sequence(renamed, camera=FR1._replace(readout_s=-0.02))
    with pytest.raises(ValueError, match="camera= must be a Camera or a preset name"):
        load_sequence(renamed, camera=FR1.intrinsics)
    with pytest.raises(ValueError, match="groundtruth.txt: pass groundtruth= for bags and "
                       "cameras only"):
        open_source(renamed, camera="fr1", groundtruth=renamed / "groundtruth.txt")
