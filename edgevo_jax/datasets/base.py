"""What every reader shares, below them all: the ``Source`` interface (timestamped rgb and
metric depth frames with the camera's intrinsics and, optionally, ground truth), the errors
of a source that cannot be opened as asked, and the names sources are opened by (the TUM
bags' topics, ``realsense``). ``source.open_source`` picks the reader for a path."""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np

from ..camera import CAMERAS, Intrinsics

#: The TUM bags' topics (``load_bag``'s defaults).
RGB_TOPIC = "/camera/rgb/image_color"
DEPTH_TOPIC = "/camera/depth/image"
INFO_TOPIC = "/camera/rgb/camera_info"
#: ``open_source`` opens the first RealSense camera for this path (``realsense:SERIAL``: that one).
REALSENSE = "realsense"


class SourceError(ValueError):
    """A source that cannot be opened as asked, with the remedy worded twice: ``str(err)``
    names the API's arguments, ``cli_message()`` the ``edgevo run`` options."""

    def __init__(self, what: str, *, api: str, cli: str) -> None:
        self.what, self.cli = what, cli
        super().__init__(f"{what}: {api}")

    def cli_message(self) -> str:
        """The message with the ``edgevo run`` options instead of the API's arguments."""
        return f"{self.what}: {self.cli}"


class UnknownCameraError(SourceError):
    """A source whose camera is neither given nor found (in a folder name, a calibration.txt,
    a bag's camera_info, a RealSense's own calibration); ``also``: one more remedy, as
    (API argument, CLI option)."""

    def __init__(self, what: str, *, also: tuple[str, str] | None = None) -> None:
        api_more, cli_more = (f", or {also[0]}", f", or {also[1]}") if also else ("", "")
        presets = ", ".join(CAMERAS)
        super().__init__(
            what, api=f"pass camera= (a preset: {presets}; or a Camera with intrinsics and "
            f"distortion) or intrinsics={api_more}",
            cli=f"pass --camera ({presets}), --calibration FILE (fx fy cx cy [k1 k2 p1 p2 k3]) "
            f"or --intrinsics FX FY CX CY{cli_more}")


@runtime_checkable
class Source(Protocol):
    """A sequence of RGB-D frames, read in order by ``runs.run.run_sequence``.

    ``decode_frame(i)`` returns frame i as stored (rgb uint8 (H, W, 3) in RGB order, depth
    in the source's own units); ``rectify_frame`` turns that into what the tracker takes:
    rgb undistorted onto the pinhole ``intrinsics`` and depth float32 metres (H, W), 0 where
    nothing was measured. ``timestamps[i]`` (seconds, increasing) is known once frame i is
    decoded; ``groundtruth`` is (timestamps (M,), poses7 (M, 7) T_world_cam) or None.
    A live source is read in order only (i = 0, 1, 2, ...). Optional: ``readout_s``, the
    colour camera's rolling-shutter readout time (s; ``camera_readout``),
    ``depth_time_offset_s`` and ``depth_timestamps`` (N,), the depth images' times
    (``depth_lags``)."""

    name: str
    intrinsics: Intrinsics
    groundtruth: tuple[np.ndarray, np.ndarray] | None
    width: int
    height: int

    @property
    def timestamps(self) -> np.ndarray | list[float]:
        """(N,) seconds of the frames (of those read so far, for a live source)."""
        ...

    def __len__(self) -> int: ...

    def decode_frame(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """Frame i as stored: rgb uint8 (H, W, 3) in RGB order, depth in the source's units."""
        ...

    def rectify_frame(self, rgb: np.ndarray, raw: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """A decoded frame as the tracker takes it: undistorted rgb, float32 metres depth."""
        ...


def depth_lags(seq: Source) -> np.ndarray | None:
    """How long after its colour image each depth image of a source was taken (s, (N,)):
    ``depth_timestamps`` minus ``timestamps``, where the source's camera states a depth time
    offset (``depth_time_offset_s``: a calibrated camera, whose depth stamps are then true
    times); None otherwise, and the tracker reads depth as taken with the colour image: the
    files' stamps alone are not taken for capture times (docs/decisions.md, "The tracker
    models the depth time")."""
    depth_t = getattr(seq, "depth_timestamps", None)
    if not getattr(seq, "depth_time_offset_s", 0.0) or depth_t is None:
        return None
    return np.asarray(depth_t, np.float64) - np.asarray(seq.timestamps, np.float64)


def camera_readout(seq: Source) -> float:
    """The rolling-shutter readout time (s) of a source's colour camera, 0 (a global shutter)
    where it does not say."""
    return float(getattr(seq, "readout_s", 0.0) or 0.0)
