"""Bad inputs: each one gives a clear error naming the file and the problem before any JAX code
runs (or, for an all-zero depth frame, a warning naming it while the run goes on); bad options
of ``edgevo run`` and of scripts/tum_to_bag.py, likewise.

The cases are real frames of the bundled fr1/xyz clip copied into tmp_path and damaged.
``python tests/test_inputs.py`` prints the catalogue of what a user of ``edgevo`` sees for each
(docs/errors.md is its output; its ROS bag section needs rosbags).
"""

from __future__ import annotations

import contextlib
import io
import re
import shutil
import sys
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from unittest import mock

import cv2
import numpy as np
import pytest
from conftest import load_script

from edgevo_jax import cli
from edgevo_jax.camera import Intrinsics
from edgevo_jax.cli import BUNDLED_CLIP
from edgevo_jax.config import Config
from edgevo_jax.datasets import read_file_list
from edgevo_jax.datasets.images import _jpeg_header
from edgevo_jax.datasets.tum import EmptyDepthWarning, TumSequence, load_sequence
from edgevo_jax.io import TrajectoryWriter

NAME = "rgbd_dataset_freiburg1_xyz_bad"  # the camera (freiburg1) comes from the name
FRAMES = 5  # rgb and depth images copied from the bundled clip (4 associated pairs)


def copy_clip(root: Path, *, groundtruth: bool = True) -> Path:
    """The first FRAMES rgb and depth images of the bundled clip with their lists, writable
    (the packaged files may be read-only, so no copytree)."""
    for kind in ("rgb", "depth"):
        (root / kind).mkdir(parents=True)
        stamps, names = read_file_list(BUNDLED_CLIP / f"{kind}.txt")
        lines = [f"# {kind} (first {FRAMES} of the bundled clip)\n"]
        for t, rel in list(zip(stamps, names, strict=True))[:FRAMES]:
            shutil.copyfile(BUNDLED_CLIP / rel, root / rel)
            lines.append(f"{t:.6f} {rel}\n")
        (root / f"{kind}.txt").write_text("".join(lines))
    if groundtruth:
        shutil.copyfile(BUNDLED_CLIP / "groundtruth.txt", root / "groundtruth.txt")
    return root


def _frame(root: Path, kind: str, k: int) -> Path:
    """The image file of list line k (0-based, comments skipped) of rgb.txt / depth.txt.

    Of the copied lines, rgb 2 and depth 1 associate with nothing (see test_tum); the pairs
    are (rgb, depth) = (0, 0), (1, 2), (3, 3), (4, 4)."""
    return root / read_file_list(root / f"{kind}.txt")[1][k]


def _lines(path: Path) -> list[str]:
    return path.read_text().splitlines(keepends=True)


# ----------------------------------------------------------------------------- the cases


@dataclass(frozen=True)
class Case:
    """A bad input: ``make(root)`` damages a fresh copy and returns (folder to load, keyword
    arguments of load_sequence, the path the message must name); the error's type and a regex
    for the problem."""

    name: str
    make: Callable[[Path], tuple[Path, dict, Path]]
    error: type[Exception]
    problem: str


def _missing_folder(root):
    return root.parent / "rgbd_dataset_freiburg1_nowhere", {}, root.parent / (
        "rgbd_dataset_freiburg1_nowhere")


def _missing_list(kind):
    def make(root):
        (root / f"{kind}.txt").unlink()
        return root, {}, root / f"{kind}.txt"
    return make


def _missing_image(root):
    path = _frame(root, "depth", 3)
    path.unlink()
    return root, {}, path


def _random_bytes(root):
    path = _frame(root, "rgb", 3)
    path.write_bytes(np.random.default_rng(0).bytes(5000))
    return root, {}, path


def _truncated(root):
    path = _frame(root, "depth", 3)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    return root, {}, path


def _as_jpeg(root: Path) -> Path:
    """The copy's rgb images as JPEG files (rgb.txt rewritten): a folder of user data."""
    path = root / "rgb.txt"
    lines = []
    for line in _lines(path):
        if not line.startswith("#"):
            t, rel = line.split()
            img = cv2.imread(str(root / rel), cv2.IMREAD_COLOR)
            (root / rel).unlink()
            rel = rel.replace(".png", ".jpg")
            cv2.imwrite(str(root / rel), img)
            line = f"{t} {rel}\n"
        lines.append(line)
    path.write_text("".join(lines))
    return root


def _jpeg_truncated(root):
    path = _frame(_as_jpeg(root), "rgb", 3)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    return root, {}, path


def _jpeg_random_bytes(root):
    path = _frame(_as_jpeg(root), "rgb", 4)
    path.write_bytes(np.random.default_rng(0).bytes(5000))
    return root, {}, path


def _depth_as(convert):
    def make(root):
        path = _frame(root, "depth", 2)
        raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        cv2.imwrite(str(path), convert(raw))
        return root, {}, path
    return make


def _depth_other_size(root):
    path = _frame(root, "depth", 3)
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    cv2.imwrite(str(path), cv2.resize(raw, (320, 240), interpolation=cv2.INTER_NEAREST))
    return root, {}, path


def _frame_other_size(root):
    for kind in ("rgb", "depth"):
        path = _frame(root, kind, 3)
        img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        cv2.imwrite(str(path), cv2.resize(img, (320, 240), interpolation=cv2.INTER_NEAREST))
    return root, {}, _frame(root, "rgb", 3)


def _intrinsics(fx, fy, cx, cy):
    def make(root):
        return root, {"intrinsics": Intrinsics(fx, fy, cx, cy)}, Path("intrinsics")
    return make


def _list_line(kind, k, text):
    """Replace data line k (0-based) of rgb.txt / depth.txt (line 1 is the comment)."""
    def make(root):
        path = root / f"{kind}.txt"
        lines = _lines(path)
        lines[1 + k] = text(lines[1 + k]) + "\n"
        path.write_text("".join(lines))
        return root, {}, Path(f"{path}:{2 + k}")
    return make


def _swap_first_two(root):
    path = root / "rgb.txt"
    lines = _lines(path)
    lines[1], lines[2] = lines[2], lines[1]
    path.write_text("".join(lines))
    return root, {}, Path(f"{path}:3")


def _duplicate(root):
    path = root / "depth.txt"
    lines = _lines(path)
    t = lines[1].split()[0]
    lines[2] = f"{t} {lines[2].split()[1]}\n"
    path.write_text("".join(lines))
    return root, {}, Path(f"{path}:3")


def _groundtruth_line(text):
    def make(root):
        path = root / "groundtruth.txt"
        lines = _lines(path)
        lines[5] = text + "\n"  # line 6: the first three are comments
        path.write_text("".join(lines))
        return root, {}, Path(f"{path}:6")
    return make


def _no_pairs(root):
    path = root / "depth.txt"
    lines = [ln if ln.startswith("#") else f"{float(ln.split()[0]) + 5:.6f} {ln.split()[1]}\n"
             for ln in _lines(path)]
    path.write_text("".join(lines))
    return root, {}, root


def _no_camera(root):
    other = root.parent / "my_recording"
    root.rename(other)
    return other, {}, Path("my_recording")


CASES = [
    Case("missing folder", _missing_folder, FileNotFoundError, "folder not found"),
    Case("missing rgb.txt", _missing_list("rgb"), FileNotFoundError, "not found"),
    Case("missing depth.txt", _missing_list("depth"), FileNotFoundError, "not found"),
    Case("missing image", _missing_image, FileNotFoundError, "depth image not found"),
    Case("corrupt PNG (random bytes)", _random_bytes, ValueError,
         r"cannot decode rgb image .*not a PNG file"),
    Case("truncated PNG", _truncated, ValueError, r"cannot decode depth image .*truncated"),
    Case("truncated JPEG", _jpeg_truncated, ValueError,
         r"cannot decode rgb image .*truncated JPEG \(no end-of-image marker"),
    Case("corrupt JPEG (random bytes)", _jpeg_random_bytes, ValueError,
         r"cannot decode rgb image .*not a JPEG file"),
    Case("8-bit depth", _depth_as(lambda d: (d // 256).astype(np.uint8)), ValueError,
         r"must be single-channel 16-bit, got 8-bit, 1 channel"),
    Case("3-channel depth", _depth_as(lambda d: np.dstack([d, d, d])), ValueError,
         r"must be single-channel 16-bit, got 16-bit, 3 channels"),
    Case("rgb and depth of different sizes", _depth_other_size, ValueError,
         r"is 640x480 but depth .* is 320x240"),
    Case("a frame of another size", _frame_other_size, ValueError,
         r"is 320x240, the sequence .* is 640x480"),
    Case("NaN intrinsics", _intrinsics(float("nan"), 516.5, 318.6, 255.3), ValueError,
         "intrinsics must be finite"),
    Case("non-positive focal length", _intrinsics(517.3, 0.0, 318.6, 255.3), ValueError,
         "focal lengths must be positive"),
    Case("non-positive principal point", _intrinsics(517.3, 516.5, -318.6, 255.3), ValueError,
         "principal point must be positive"),
    Case("principal point outside the image", _intrinsics(318.6, 255.3, 517.3, 516.5),
         ValueError, "outside the 640x480 image"),
    Case("unsorted timestamps", _swap_first_two, ValueError, "strictly increasing"),
    Case("duplicate timestamps", _duplicate, ValueError, "strictly increasing"),
    Case("list line without a filename", _list_line("depth", 2, lambda ln: ln.split()[0]),
         ValueError, "expected 'timestamp filename'"),
    Case("list line with a bad timestamp", _list_line("rgb", 1, lambda ln: "x" + ln.strip()),
         ValueError, "bad timestamp"),
    Case("list line with a non-finite timestamp",
         _list_line("rgb", 3, lambda ln: "nan " + ln.split()[1]), ValueError,
         "non-finite timestamp"),
    Case("no rgb/depth pair associates", _no_pairs, ValueError, "no rgb/depth pair"),
    Case("ground-truth line of 7 numbers", _groundtruth_line("1305031101.7 1 2 3 0 0 0"),
         ValueError, r"ground truth .*expected 8 numbers.*remove groundtruth\.txt"),
    Case("ground-truth line with a word", _groundtruth_line("1305031101.7 1 2 3 0 0 0 one"),
         ValueError, "not a number"),
    Case("ground-truth line with NaN", _groundtruth_line("1305031101.7 1 nan 3 0 0 0 1"),
         ValueError, "non-finite value"),
    Case("ground-truth zero quaternion", _groundtruth_line("1305031101.7 1 2 3 0 0 0 0"),
         ValueError, "zero quaternion"),
    Case("no camera in the folder name", _no_camera, ValueError,
         "cannot tell the camera from the name"),
]


@dataclass(frozen=True)
class OptionCase:
    """A bad option of ``edgevo run`` on the good copy: ``argv(root)`` are the arguments after
    the folder; what the error must say (argparse's own errors exit with SystemExit(2))."""

    name: str
    argv: Callable[[Path], list[str]]
    problem: str


def _calibration(text: str):
    def argv(root):
        path = root.parent / "mycamera.txt"
        path.write_text(text)
        return ["--calibration", str(path)]
    return argv


OPTION_CASES = [
    OptionCase("--max-frames 0", lambda root: ["--max-frames", "0"],
               "argument --max-frames: must be at least 1, got 0"),
    OptionCase("--frame-step 0", lambda root: ["--frame-step", "0"],
               "argument --frame-step: must be at least 1, got 0"),
    OptionCase("--depth-factor 0", lambda root: ["--depth-factor", "0"],
               "argument --depth-factor: must be a finite number > 0, got 0"),
    OptionCase("unknown --camera", lambda root: ["--camera", "freiburg1"],
               r"argument --camera: invalid choice: 'freiburg1' \(choose from"),
    OptionCase("--camera with --intrinsics",
               lambda root: ["--camera", "fr1", "--intrinsics", "517.3", "516.5", "318.6", "255.3"],
               "argument --intrinsics: not allowed with argument --camera"),
    OptionCase("--groundtruth with a folder (it reads its own)",
               lambda root: ["--groundtruth", str(root / "groundtruth.txt")],
               r"a folder reads its own groundtruth.txt: pass --groundtruth for bags and "
               "cameras only"),
    OptionCase("--calibration file missing", lambda root: ["--calibration", "nowhere.txt"],
               "--calibration file not found: nowhere.txt"),
    OptionCase("--calibration with 7 numbers", _calibration("517.3 516.5 318.6 255.3 0.26 0.1 0\n"),
               r"--calibration .*mycamera.txt: expected 4 numbers \(fx fy cx cy\) or 9 .*got 7"),
    OptionCase("--calibration with a word", _calibration("fx=517.3 516.5 318.6 255.3\n"),
               r"--calibration .*mycamera.txt: .*must be numbers, got 'fx=517.3"),
]


def _out_cases(root: Path) -> list[tuple[str, list[str], str]]:
    """Output paths ``edgevo run`` must refuse before reading a frame: (name, the options,
    the message expected). ``root``: the clip's copy (its parent holds the outputs)."""
    here = root.parent
    (here / "results").mkdir(exist_ok=True)
    return [
        ("--out an existing folder", ["--out", str(here / "results")],
         r"--out .*results: is a folder; give a file path in it"),
        ("--out in a folder that does not exist", ["--out", str(here / "nowhere" / "t.txt")],
         r"--out .*t.txt: the folder .*nowhere does not exist"),
        ("--stats an existing folder", ["--out", str(here / "t.txt"), "--stats",
                                        str(here / "results")],
         r"--stats .*results: is a folder"),
        ("--stats in a place nothing can be written", ["--out", str(here / "t.txt"), "--stats",
                                                       "/proc/edgevo_stats.json"],
         r"--stats /proc/edgevo_stats.json: cannot write in /proc"),
    ]


@pytest.fixture
def clip(tmp_path) -> Path:
    return copy_clip(tmp_path / NAME)


def test_the_copied_clip_loads(clip):
    """The undamaged copy is a good sequence: each failure below is the damage's doing."""
    seq = load_sequence(clip)
    assert len(seq) == 4 and (seq.width, seq.height) == (640, 480)
    assert seq.groundtruth is not None
    for i in range(len(seq)):
        seq.decode_frame(i)


@pytest.mark.parametrize("case", CASES, ids=[c.name for c in CASES])
def test_bad_input_names_file_and_problem(clip, case):
    path, kwargs, names = case.make(clip)
    with pytest.raises(case.error) as info:
        load_sequence(path, **kwargs)
    message = str(info.value)
    assert re.search(case.problem, message), message
    assert str(names) in message, message


@pytest.mark.parametrize("case", CASES, ids=[c.name for c in CASES])
def test_cli_reports_bad_input_before_tracking(clip, case, monkeypatch, capsys):
    """``edgevo run``: exit status 2 and the message on stderr; the tracker never starts."""
    path, kwargs, names = case.make(clip)
    argv = ["run", str(path), "--out", str(clip.parent / "t.txt"), "--no-progress"]
    if "intrinsics" in kwargs:
        argv += ["--intrinsics", *(str(v) for v in kwargs["intrinsics"])]

    def no_run(*args, **kw):
        raise AssertionError("run_sequence called on a bad input")

    monkeypatch.setattr("edgevo_jax.runs.run.run_sequence", no_run)
    monkeypatch.setenv("EDGEVO_CACHE_DIR", "")
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("edgevo: error: ") and str(names) in err, err
    assert re.search(case.problem, err), err


@pytest.mark.parametrize("case", OPTION_CASES, ids=[c.name for c in OPTION_CASES])
def test_bad_options_stop_with_the_option_named(clip, case, monkeypatch, capsys):
    def no_run(*args, **kw):
        raise AssertionError("run_sequence called with a bad option")

    monkeypatch.setattr("edgevo_jax.runs.run.run_sequence", no_run)
    rc, text = _user_sees(["run", str(clip), *case.argv(clip), "--out",
                           str(clip.parent / "t.txt"), "--no-progress"])
    assert rc == 2 and re.search(case.problem, text), text
    assert "Traceback" not in text and "nan" not in text


@pytest.mark.parametrize("n", range(4))
def test_bad_output_paths_stop_before_tracking_and_write_nothing(clip, n, monkeypatch):
    """A folder, a missing folder or an unwritable place as an output: exit 2, one line
    naming the option and the problem, nothing written (no ``.part`` file, no stats)."""
    name, options, problem = _out_cases(clip)[n]

    def no_run(*args, **kw):
        raise AssertionError("run_sequence called with a bad output path")

    monkeypatch.setattr("edgevo_jax.runs.run.run_sequence", no_run)
    before = sorted(clip.parent.rglob("*"))
    rc, text = _user_sees(["run", str(clip), *options, "--no-progress"])
    assert rc == 2 and re.search(problem, text), (name, text)
    assert len(text.strip().splitlines()) == 1 and "Traceback" not in text, text
    assert sorted(clip.parent.rglob("*")) == before


def test_a_jpeg_folder_is_checked_from_its_headers(clip):
    """JPEG rgb images: size and channels read from the frame header (no decoding), the same
    as decoding gives; a truncated one stops loading, or (checks off) its own decode."""
    _as_jpeg(clip)
    seq = load_sequence(clip)
    assert seq.rgb_files[0].suffix == ".jpg"
    assert _jpeg_header(seq.rgb_files[0], "rgb") == (640, 480, "8-bit, 3 channels")
    assert seq.load_frame(2)[0].shape == (480, 640, 3)
    path = seq.rgb_files[2]
    path.write_bytes(path.read_bytes()[:-2])  # all but its EOI marker
    with pytest.raises(ValueError, match=rf"{re.escape(str(path))}: truncated JPEG"):
        load_sequence(clip)
    unchecked = load_sequence(clip, check_images=False)
    unchecked.decode_frame(1)
    with pytest.raises(ValueError, match=rf"{re.escape(str(path))}: truncated JPEG"):
        unchecked.decode_frame(2)


def _tum_to_bag_without_rosbags(out: Path) -> tuple[int, str]:
    """scripts/tum_to_bag.py run where rosbags cannot be imported: status, stderr + stdout."""
    to_bag = load_script("tum_to_bag")
    err, stdout = io.StringIO(), io.StringIO()
    with (mock.patch.dict(sys.modules, {"rosbags": None}),
          mock.patch.object(sys, "argv", ["tum_to_bag.py", str(BUNDLED_CLIP), str(out)]),
          contextlib.redirect_stderr(err), contextlib.redirect_stdout(stdout)):
        rc = to_bag.main()
    return rc, err.getvalue() + stdout.getvalue()


def test_tum_to_bag_without_rosbags_says_what_to_install(tmp_path):
    rc, text = _tum_to_bag_without_rosbags(tmp_path / "x.bag")
    assert rc == 2 and text == ('tum_to_bag.py: error: writing ROS bags needs the rosbags '
                                'package: pip install "edgevo_jax[ros]"\n'), text
    assert not (tmp_path / "x.bag").exists()


def test_damaged_middle_of_a_png_stops_at_its_frame(clip):
    """Header and end intact, data scrambled: only decoding finds it, at its own frame."""
    path = _frame(clip, "depth", 2)
    data = bytearray(path.read_bytes())
    mid = len(data) // 2
    data[mid : mid + 2000] = bytes(b ^ 0x5A for b in data[mid : mid + 2000])
    path.write_bytes(bytes(data))
    seq = load_sequence(clip)
    k = seq.depth_files.index(path)
    for i in range(k):
        seq.decode_frame(i)
    with pytest.raises(ValueError, match=rf"cannot decode depth image {re.escape(str(path))}"):
        seq.decode_frame(k)


def test_images_unchecked_on_load_are_still_checked_on_decode(clip):
    """check_images=False defers the checks to decode_frame, which still names the file."""
    path = _frame(clip, "depth", 3)
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    cv2.imwrite(str(path), (raw // 256).astype(np.uint8))
    with pytest.raises(ValueError, match="8-bit"):
        load_sequence(clip)
    seq = load_sequence(clip, check_images=False)
    k = seq.depth_files.index(path)
    with pytest.raises(ValueError, match=rf"{re.escape(str(path))}.*8-bit, 1 channel"):
        seq.decode_frame(k)


def _zero_depth(clip: Path, k: int) -> Path:
    path = _frame(clip, "depth", k)
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    cv2.imwrite(str(path), np.zeros_like(raw))
    return path


def test_all_zero_depth_warns_with_its_file_and_does_not_stop(clip):
    path = _zero_depth(clip, 2)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        seq = load_sequence(clip)  # loading is quiet: the frame warns when it is decoded
    k = seq.depth_files.index(path)
    with pytest.warns(EmptyDepthWarning, match=rf"frame {k}: depth image "
                      rf"{re.escape(str(path))} has no depth measurement \(all zero\)"):
        rgb, depth = seq.load_frame(k)
    assert rgb.shape == (480, 640, 3) and not depth.any()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        seq.load_frame(k - 1)  # the others do not warn


@pytest.mark.slow
def test_all_zero_depth_frames_are_flagged_and_the_run_goes_on(clip, tmp_path):
    """An all-zero first depth cannot start the map and a later one cannot be a keyframe, but
    the run tracks every frame and writes every pose."""
    from edgevo_jax.runs.run import run_sequence

    paths = [_zero_depth(clip, 0), _zero_depth(clip, 4)]  # frames 0 and 3
    seq = load_sequence(clip)
    assert [seq.depth_files.index(p) for p in paths] == [0, 3]
    out = tmp_path / "traj.txt"
    with pytest.warns(EmptyDepthWarning) as record:
        run = run_sequence(seq, Config(), out=out, progress=False)
    named = [str(w.message).split(": depth image ")[1].split(" has no")[0]
             for w in record if issubclass(w.category, EmptyDepthWarning)]
    assert named == [str(p) for p in paths]
    assert len(run.results) == len(seq) and run.stopped_at is None
    assert len(out.read_text().splitlines()) == len(seq)
    # the first frame is flagged (no map can start from it) and is no keyframe
    assert run.results[0].reason is not None and run.results[0].keyframe is None
    assert run.results[1].keyframe is not None  # the map starts at the next frame
    assert run.results[3].keyframe is None
    assert np.all(np.isfinite(run.poses))


@pytest.mark.slow
def test_missing_ground_truth_runs_without_ate_and_says_so(tmp_path, capsys):
    clip = copy_clip(tmp_path / NAME, groundtruth=False)
    out = tmp_path / "t.txt"
    assert cli.main(["run", str(clip), "--out", str(out), "--max-frames", "3",
                     "--no-progress"]) == 0
    text = capsys.readouterr().out
    assert "ATE           n/a (no ground truth)" in text, text
    assert "ATE RMSE" not in text
    assert len(out.read_text().splitlines()) == 3


def test_non_finite_user_pose(tmp_path, capsys):
    """A pose handed in by the user: the initial pose of Odometry, a line of an estimate given
    to ``edgevo eval``, a pose written to a trajectory file."""
    from edgevo_jax.tracking.odometry import Odometry

    pose = np.eye(4)
    pose[1, 3] = np.nan
    intr = Intrinsics(517.3, 516.5, 318.6, 255.3)
    with pytest.raises(ValueError, match="initial_pose.*finite"):
        Odometry(Config(), intr, initial_pose=pose)
    est = tmp_path / "est.txt"
    est.write_text("1305031102.175304 0 0 0 0 0 0 1\n1305031102.211214 0 inf 0 0 0 0 1\n")
    gt = BUNDLED_CLIP / "groundtruth.txt"
    assert cli.main(["eval", str(gt), str(est)]) == 2
    err = capsys.readouterr().err
    assert f"{est}:2: non-finite value" in err, err
    with TrajectoryWriter(tmp_path / "w.txt") as w, pytest.raises(ValueError, match="non-finite"):
        w.write(1.0, [0, 0, np.nan, 0, 0, 0, 1])


# ----------------------------------------------------------------------------- catalogue


def _user_sees(argv: list[str]) -> tuple[int, str]:
    """Exit status and what ``edgevo`` prints (stderr, then stdout)."""
    err, out = io.StringIO(), io.StringIO()
    with (contextlib.redirect_stderr(err), contextlib.redirect_stdout(out),
          warnings.catch_warnings()):
        warnings.resetwarnings()  # Python's defaults, as a user's shell has them
        warnings.simplefilter("default")
        try:
            rc = cli.main(argv)
        except SystemExit as stop:  # argparse's errors
            rc = stop.code
    return rc, (err.getvalue() + out.getvalue()).replace(str(_REPO) + "/", "")


_REPO = Path(__file__).resolve().parents[1]
_HEADER = """\
# What `edgevo` says about bad inputs

Each bad input below was made from real frames of the bundled fr1/xyz clip, copied and
damaged, and run through `edgevo run` (or `edgevo eval`, `scripts/tum_to_bag.py`); the text is
what the command printed (paths shortened: `DIR` is the folder holding the damaged copy, `OUT`
the output folder; `--out OUT/t.txt --no-progress` left out of the commands). Everything here
is generated by `python tests/test_inputs.py > docs/errors.md`, and tests/test_inputs.py,
tests/test_cameras.py and tests/test_sources.py check each message names the file (and line),
the option or the topic, and the problem.

Everything that can be checked without tracking is checked by `load_sequence` before the
tracker starts (exit status 2, nothing written): folder, lists, ground truth, camera, and
every associated image's PNG or JPEG header and end (present, whole, same size, 16-bit
single-channel depth), plus a full decode of the first frame. An image damaged *inside*
(header and end whole) is only found when its frame is decoded: the run stops there and the
poses done so far stay in `<out>.part` (as after Ctrl-C). An all-zero depth frame is no error:
it warns, naming the file, and the run goes on. A missing `groundtruth.txt` is no error either:
the run goes on and the summary says `ATE n/a (no ground truth)`. Options are checked before
anything is read (argparse's errors print the usage first). A ROS bag is read through once
(every message's header) before tracking, so a bad bag stops there too.
"""


def _shown(argv: list[str], folder: Path, base: Path, *, out: bool = False) -> str:
    """The command as the catalogue shows it: no --no-progress, no --out (unless ``out``),
    paths shortened."""
    keep: list[str] = []
    for a in argv:
        if keep and keep[-1] == "--out" and not out:
            keep.pop()
        elif a != "--no-progress":
            keep.append(a)
    return _short("$ edgevo " + " ".join(keep), folder, base)


def _short(text: str, folder: Path, base: Path) -> str:
    return (text.replace(str(folder), "DIR").replace(str(base), "OUT")
            .replace(str(_REPO) + "/", ""))


def _bag_rows(base: Path) -> list[tuple[str, str, int, str]]:
    """Bad bags (written from the bundled clip with scripts/tum_to_bag.py; needs rosbags)."""
    to_bag = load_script("tum_to_bag")
    folder = base / "bags"
    folder.mkdir()
    seq = load_sequence(BUNDLED_CLIP)
    ok = to_bag.write_bag(seq, folder / "ok.bag", frames=2)
    (folder / "junk.bag").write_bytes(b"not a bag")
    cases = [
        ("bag without the rgb topic", [str(ok), "--rgb-topic", "/camera/rgb/image_raw"]),
        ("depth topic of another message type",
         [str(ok), "--depth-topic", "/camera/rgb/camera_info"]),
        ("rgb and depth of different sizes",
         [str(to_bag.write_bag(seq, folder / "small.bag", frames=2, depth_size=(320, 240)))]),
        ("bag without camera_info (and no camera given)",
         [str(to_bag.write_bag(seq, folder / "blind.bag", frames=2, camera_info=False))]),
        ("unsupported rgb encoding",
         [str(to_bag.write_bag(seq, folder / "yuv.bag", frames=2, rgb_encoding="yuv422"))]),
        ("--groundtruth file missing", [str(ok), "--groundtruth", str(folder / "gt.txt")]),
        ("missing bag", [str(folder / "missing.bag")]),
        ("not a bag", [str(folder / "junk.bag")]),
    ]
    rows = []
    for name, args in cases:
        argv = ["run", *args, "--out", str(base / "t.txt"), "--no-progress"]
        rc, text = _user_sees(argv)
        rows.append((name, _shown(argv, folder, base), rc, _short(text, folder, base)))
    return rows


def catalogue() -> str:
    """Markdown: each bad input and the message ``edgevo run`` prints for it."""
    import tempfile

    groups: dict[str, list[tuple[str, str, int, str]]] = {
        "Folders and images": [], "Options of `edgevo run`": [], "Output paths": [],
        "ROS bags": [],
        "Live cameras and scripts": []}

    def add(group: str, name: str, argv: list[str], folder: Path, base: Path) -> None:
        rc, text = _user_sees(argv)
        groups[group].append((name, _shown(argv, folder, base, out=group == "Output paths"), rc,
                              _short(text, folder, base)))

    with tempfile.TemporaryDirectory() as tmp:
        base = Path(tmp)
        for n, case in enumerate(CASES):
            root = copy_clip(base / str(n) / NAME)
            path, kwargs, _ = case.make(root)
            argv = ["run", str(path), "--out", str(base / "t.txt"), "--no-progress"]
            if "intrinsics" in kwargs:
                argv += ["--intrinsics", *(str(v) for v in kwargs["intrinsics"])]
            add("Folders and images", case.name, argv, base / str(n), base)
        root = copy_clip(base / "zero" / NAME)
        _zero_depth(root, 2)
        add("Folders and images", "all-zero depth frame (a warning; the run goes on)",
            ["run", str(root), "--out", str(base / "t.txt"), "--no-progress"],
            base / "zero", base)
        root = copy_clip(base / "nogt" / NAME, groundtruth=False)
        add("Folders and images", "no groundtruth.txt (the run goes on without ATE)",
            ["run", str(root), "--out", str(base / "t.txt"), "--no-progress"],
            base / "nogt", base)
        root = copy_clip(base / "mid" / NAME)
        path = _frame(root, "depth", 3)
        data = bytearray(path.read_bytes())
        data[len(data) // 2 : len(data) // 2 + 2000] = bytes(2000)
        path.write_bytes(bytes(data))
        add("Folders and images", "PNG damaged inside (header and end whole): found when its "
            "frame is decoded, the run stops there",
            ["run", str(root), "--out", str(base / "t.txt"), "--no-progress"],
            base / "mid", base)
        root = copy_clip(base / "int" / NAME)
        decode = TumSequence.decode_frame

        def interrupt_at_3(self, i):
            if i == 3:
                raise KeyboardInterrupt
            return decode(self, i)

        with mock.patch.object(TumSequence, "decode_frame", interrupt_at_3):
            add("Folders and images", "Ctrl-C while frame 3 is decoded",
                ["run", str(root), "--out", str(base / "t.txt"), "--no-progress"],
                base / "int", base)
        est = base / "est.txt"
        est.write_text("1305031102.175304 0 0 0 0 0 0 1\n1305031102.211214 0 inf 0 0 0 0 1\n")
        add("Folders and images", "`edgevo eval` of an estimate with a non-finite value",
            ["eval", str(BUNDLED_CLIP / "groundtruth.txt"), str(est)], base / "-", base)
        for n, case in enumerate(OPTION_CASES):
            root = copy_clip(base / f"o{n}" / NAME)
            add("Options of `edgevo run`", case.name,
                ["run", str(root), *case.argv(root), "--out", str(base / "t.txt"),
                 "--no-progress"], base / f"o{n}", base)
        root = copy_clip(base / "out" / NAME)
        for name, options, _ in _out_cases(root):
            add("Output paths", name, ["run", str(root), *options, "--no-progress"],
                base / "out", base)
        try:
            import rosbags  # noqa: F401
        except ImportError:
            groups["ROS bags"] = [("(not generated: rosbags is not installed here)", "", 0,
                                   "")]
        else:
            groups["ROS bags"] = _bag_rows(base)
        with mock.patch.dict(sys.modules, {"pyrealsense2": None}):
            add("Live cameras and scripts", "a live RealSense without pyrealsense2",
                ["run", "realsense", "--max-frames", "30"], base / "-", base)
        rc, text = _tum_to_bag_without_rosbags(base / "x.bag")
        groups["Live cameras and scripts"].append((
            "scripts/tum_to_bag.py without rosbags",
            _short(f"$ python scripts/tum_to_bag.py {BUNDLED_CLIP} {base / 'x.bag'}",
                   base / "-", base),
            rc, text))
    parts = [_HEADER]
    for group, rows in groups.items():
        parts.append(f"## {group}\n")
        for name, shown, rc, text in rows:
            body = "\n".join(x for x in (shown, text.rstrip()) if x)
            parts.append(f"### {name}\n\nexit status {rc}\n\n```\n{body}\n```\n")
    return "\n".join(parts).rstrip() + "\n"


if __name__ == "__main__":
    sys.stdout.write(catalogue())


@pytest.mark.parametrize("max_frames", [0, -3])
def test_run_refuses_a_max_frames_under_one(max_frames: int) -> None:
    from edgevo_jax import Config, load_sequence, run
    from edgevo_jax.datasets import BUNDLED_CLIP

    with pytest.raises(ValueError, match="max_frames must be at least 1"):
        run(load_sequence(BUNDLED_CLIP), Config(), max_frames=max_frames, progress=False)
