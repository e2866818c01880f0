"""``edgevo run``: track one RGB-D sequence (a TUM or ETH3D folder, a ROS bag, a live
RealSense) and write its trajectory, with run statistics and an optional rerun
recording."""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

from ..camera import CAMERAS
from ..datasets import BUNDLED_CLIP
from ..datasets.source import DEPTH_TOPIC, INFO_TOPIC, RGB_TOPIC
from ..io import check_output, json_safe
from ._common import _positive_float, _positive_int


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Add ``edgevo run`` and its options to the subcommands ``sub``."""
    run = sub.add_parser("run", help="track an RGB-D sequence and write its trajectory")
    run.add_argument("sequence", nargs="?", type=Path, default=None,
                     help="a TUM or ETH3D folder (its calibration.txt gives the camera), a "
                          "ROS1 or ROS2 bag (.bag, a folder with metadata.yaml, .db3, .mcap), "
                          "or realsense[:SERIAL] for a live camera (default: the bundled "
                          "fr1_xyz clip)")
    run.add_argument("--out", type=Path, default=None,
                     help="trajectory file (TUM format; default: <sequence>.traj.txt here)")
    run.add_argument("--stats", type=Path, default=None, help="write run statistics as JSON")
    run.add_argument("--online", type=Path, default=None, metavar="FILE",
                     help="also write the poses as each frame was reported, before the map "
                          "moved them (closed loops, chains found again): TUM format; --out "
                          "holds the corrected ones")
    run.add_argument("--map", dest="map_file", type=Path, default=None, metavar="FILE",
                     help="start in a keyframe map saved by --save-map (same camera and "
                          "settings): the trajectory is written in its frame once a frame is "
                          "found in it; --stats: map.found_in_loaded")
    run.add_argument("--save-map", type=Path, default=None, metavar="FILE",
                     help="write the keyframe map to FILE when the run ends (one versioned "
                          "file, written atomically: docs/map-file.md)")
    run.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                     help="override a Config field (repeatable), e.g. --set max_edges=1024")
    run.add_argument("--max-frames", type=_positive_int, default=None, metavar="N",
                     help="stop after N frames (N >= 1)")
    run.add_argument("--depth-factor", type=_positive_float, default=5000.0,
                     help="depth PNG units per metre (TUM: 5000)")
    run.add_argument("--frame-step", type=_positive_int, default=1, metavar="K",
                     help="keep every K-th line of rgb.txt and depth.txt (1/K of the frame "
                          "rate)")
    cam = run.add_argument_group(
        "camera", "Default: a folder's calibration.txt, else the camera its name names "
        "(freiburg1/2/3 or fr1/2/3); a bag's camera_info; a RealSense's own. One of these "
        "options replaces it.").add_mutually_exclusive_group()
    cam.add_argument("--camera", choices=list(CAMERAS), default=None,
                     help="a preset: "
                          + "; ".join(f"{k}: {v.about}" for k, v in CAMERAS.items()))
    cam.add_argument("--calibration", type=Path, default=None, metavar="FILE",
                     help="a text file of 4 numbers, fx fy cx cy (ETH3D's calibration.txt), "
                          "or 9, fx fy cx cy k1 k2 p1 p2 k3 (OpenCV distortion of the raw "
                          "images, removed before tracking); a global shutter unless "
                          "--set readout_s=SECONDS; or a camera file, FILE.toml, with its "
                          "readout and depth fields (docs/camera_file.md)")
    cam.add_argument("--intrinsics", type=float, nargs=4, default=None,
                     metavar=("FX", "FY", "CX", "CY"),
                     help="a pinhole camera of undistorted images with a global shutter (for "
                          "lens distortion use --calibration)")
    run.add_argument("--no-progress", action="store_true", help="no progress bar")
    run.add_argument("--rgb-topic", default=RGB_TOPIC, help=f"bags: rgb images ({RGB_TOPIC})")
    run.add_argument("--depth-topic", default=DEPTH_TOPIC,
                     help=f"bags: depth images, 32FC1 m or 16UC1 mm ({DEPTH_TOPIC})")
    run.add_argument("--info-topic", default=INFO_TOPIC,
                     help=f"bags: the camera's CameraInfo ({INFO_TOPIC})")
    run.add_argument("--groundtruth", type=Path, default=None,
                     help="bags and cameras: a TUM trajectory file to score against")
    run.add_argument("--rerun", type=Path, default=None, metavar="FILE.rrd",
                     help="record the run for the rerun viewer (pip install "
                          "'edgevo_jax[rerun]'); open it with `rerun FILE.rrd`")
    run.add_argument("--rerun-viewer", action="store_true",
                     help="show the run live in a rerun viewer (needs a display)")
    run.add_argument("--params", type=Path, default=None, metavar="JSON",
                     help="learnt parameters (Huber radii, eta, edge weighting, reobs_a): a "
                          "JSON of Params fields, or scripts/learn_weights.py's log")


def _camera(args: argparse.Namespace) -> dict:
    """``open_source``'s camera argument from ``--camera``, ``--calibration`` (``camera=``) or
    ``--intrinsics`` (``intrinsics=``); {} when none is given."""
    from ..camera import Intrinsics
    from ..datasets.tum import read_calibration

    if args.camera is not None:
        return {"camera": args.camera}
    if args.intrinsics is not None:
        try:
            return {"intrinsics": Intrinsics(*args.intrinsics).validate()}
        except ValueError as err:
            raise ValueError(f"--intrinsics {' '.join(f'{v:g}' for v in args.intrinsics)}: "
                             f"{err}") from None
    if args.calibration is None:
        return {}
    if not args.calibration.is_file():
        raise FileNotFoundError(f"--calibration file not found: {args.calibration}")
    try:
        return {"camera": read_calibration(args.calibration)}
    except ValueError as err:
        raise ValueError(f"--calibration {err}") from None


def command(args: argparse.Namespace) -> int:
    """``edgevo run``: track the sequence, write its trajectory (and --stats),
    print its summary; 130 when interrupted."""
    from ..config import Config
    from ..datasets.source import SourceError, open_source
    from ..runs.run import run_sequence, summarise

    # every output is checked before anything is read or tracked (docs/errors.md)
    for option in ("out", "stats", "rerun", "online"):
        if getattr(args, option) is not None:
            check_output(getattr(args, option), what=f"--{option}")
    if args.save_map is not None:  # its folder is made when the map is written
        check_output(args.save_map, what="--save-map", make_folders=True)
    config = Config().with_overrides(args.overrides)
    params = _read_params(args.params, config) if args.params is not None else None
    path = args.sequence if args.sequence is not None else BUNDLED_CLIP
    try:
        seq = open_source(
            path, **_camera(args), depth_factor=args.depth_factor,
            frame_step=args.frame_step, rgb_topic=args.rgb_topic, depth_topic=args.depth_topic,
            info_topic=args.info_topic, groundtruth=args.groundtruth, max_frames=args.max_frames)
    except SourceError as err:  # its remedy in the CLI's options
        raise ValueError(err.cli_message()) from None
    recording = None
    if args.rerun is not None or args.rerun_viewer:
        from ..viz.recording import RerunRecording

        recording = RerunRecording(seq, path=args.rerun, spawn=args.rerun_viewer)
    out = args.out if args.out is not None else check_output(Path(f"{seq.name}.traj.txt"),
                                                             what="the trajectory file")
    try:
        run = run_sequence(seq, config, out=out, progress=not args.no_progress,
                           max_frames=args.max_frames, params=params, started=args.started,
                           on_frame=recording, save_map=args.save_map,
                           map_file=args.map_file)
    except KeyboardInterrupt as err:
        notes = getattr(err, "__notes__", [])
        print("edgevo: interrupted" + (f"; {notes[0]}" if notes else ""), file=sys.stderr)
        return 130
    finally:
        if recording is not None:
            recording.close()
        if hasattr(seq, "close"):  # a bag's reader, a live camera
            seq.close()
    if args.online is not None:
        from ..io import matrices_to_poses7, write_trajectory

        online = run.online_poses if run.online_poses is not None else run.poses
        write_trajectory(args.online, run.timestamps, matrices_to_poses7(online))
    stats = summarise(run, seq)
    if args.stats is not None:
        args.stats.write_text(json.dumps(json_safe(stats), indent=2) + "\n")
    print(_summary_text(stats, out, _rpe_per_frame(run, seq)))
    if args.map_file is not None:
        found = run.found_in_loaded
        print(f"loaded map    {args.map_file}: " + (
            f"found in it at frame {found}; the trajectory is in its frame" if found is not None
            else "never found in it: the trajectory is in its own frame, its frames WEAK"))
    if args.save_map is not None:
        print(f"map           {args.save_map} ({run.map_keyframes} keyframes, "
              f"{args.save_map.stat().st_size / 1e6:.1f} MB)")
    if args.rerun is not None:
        print(f"rerun recording: {args.rerun} (open with `rerun {args.rerun}`)")
    return 0


def _read_params(path: Path, config):
    """Params from a JSON file: Params fields at the top level, or under "fitted_params"
    (``scripts/learn_weights.py``'s log)."""
    from ..learn.params import params_from_dict

    try:
        values = json.loads(path.read_text())
    except FileNotFoundError:
        raise FileNotFoundError(f"--params file not found: {path}") from None
    except json.JSONDecodeError as err:
        raise ValueError(f"--params {path} is not JSON: {err}") from None
    if not isinstance(values, dict):
        raise ValueError(f"--params {path} must hold a JSON object")
    values = values.get("fitted_params", values)
    try:
        return params_from_dict(values, config)
    except (ValueError, TypeError) as err:
        raise ValueError(f"--params {path}: {err}") from None


def _rpe_per_frame(run, seq) -> float | None:
    """The run's RPE between consecutive frames (m), as ``edgevo eval`` reports it by
    default; None without ground truth or pairs."""
    from ..io import matrices_to_poses7
    from ..metrics import rpe

    if seq.groundtruth is None or len(run.results) < 2:
        return None
    try:
        r = rpe(seq.groundtruth, (run.timestamps, matrices_to_poses7(run.poses)))
    except ValueError:  # no timestamps in common with the ground truth
        return None
    return r["rmse"] if r["n"] else None


def _summary_text(stats: dict, out: Path, rpe_frame: float | None = None) -> str:
    ms = stats["ms_per_frame"]
    timing = (f"mean {ms['mean']:.1f}  median {ms['median']:.1f}  p90 {ms['p90']:.1f}"
              "  (every later frame, decoding excluded)" if math.isfinite(ms["mean"])
              else "n/a (no frame after the first: its time is the start-up)")
    lines = [
        f"sequence      {stats['sequence']}",
        f"frames        {stats['frames']}  (keyframes {stats['keyframes']}, weak {stats['weak']}, "
        f"lost {stats['lost']})",
        f"start-up      {stats['startup_s']:.2f} s (command to first pose; compiling or "
        f"loading every program: {stats['warm_up_s']:.2f} s)",
        f"ms/frame      {timing}",
    ]
    if "ate_rmse_m" in stats:
        lines.append(f"ATE RMSE      {stats['ate_rmse_m']:.4f} m")
        rpe = stats.get("rpe_rmse_m_per_s")
        per_s = ("over 1 s n/a (the run is shorter)" if rpe is None or math.isnan(rpe)
                 else f"{rpe:.4f} m/s over 1 s")
        per_frame = "" if rpe_frame is None else f"; {rpe_frame:.4f} m per frame (edgevo eval's)"
        lines.append(f"RPE RMSE      {per_s}{per_frame}")
    else:
        lines.append("ATE           n/a (" + stats.get("ground_truth_note", "no ground truth")
                     + ")")
    lines.append(f"trajectory    {out}")
    return "\n".join(lines)
