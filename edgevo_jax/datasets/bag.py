"""ROS1 and ROS2 bags as a ``Source``, read with the ``rosbags`` package (no ROS install:
``pip install 'edgevo_jax[ros]'``).

Topics default to the TUM bags': ``/camera/rgb/image_color`` (sensor_msgs/Image, rgb8, bgr8,
rgba8, bgra8 or mono8; or sensor_msgs/CompressedImage), ``/camera/depth/image`` (Image,
32FC1 metres with NaN for no measurement, or 16UC1 millimetres) and
``/camera/rgb/camera_info`` (K and, when not all zero, D as OpenCV coefficients). Frames are
the rgb and depth messages associated by their header stamps (as TUM's ``associate.py``,
within ``max_diff`` seconds). Loading reads every message's header once (so a bad bag stops
before tracking); a frame's images are read again when it is decoded.
"""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ..camera import Camera, Distortion, Intrinsics, checked_readout
from ..io import read_trajectory
from ..metrics import associate_timestamps
from .base import DEPTH_TOPIC, INFO_TOPIC, RGB_TOPIC, SourceError, UnknownCameraError
from .calibration import camera_from_name, refuse_depth_fields, source_camera, undistort

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
#: rgb encodings -> the OpenCV conversion to RGB (None: already RGB)
_RGB_ENCODINGS = {"rgb8": None, "bgr8": cv2.COLOR_BGR2RGB, "rgba8": cv2.COLOR_RGBA2RGB,
                  "bgra8": cv2.COLOR_BGRA2RGB, "mono8": cv2.COLOR_GRAY2RGB}
#: depth encodings -> (numpy dtype, metres per unit)
_DEPTH_ENCODINGS = {"32FC1": (np.float32, 1.0), "16UC1": (np.uint16, 1e-3)}


def _rosbags() -> Any:
    try:
        from rosbags import highlevel, typesys
    except ImportError:
        raise ImportError("reading ROS bags needs the rosbags package: "
                          "pip install 'edgevo_jax[ros]'") from None
    return highlevel, typesys


@dataclass(frozen=True, eq=False)
class BagSequence:
    """An associated RGB-D sequence in a ROS bag (use :func:`load_bag`); a ``Source``.
    ``stamps``: per frame, the bag times (ns) of its rgb and depth messages; ``headers``
    their header stamps (s)."""

    root: Path
    name: str
    intrinsics: Intrinsics
    distortion: Distortion | None
    timestamps: np.ndarray
    groundtruth: tuple[np.ndarray, np.ndarray] | None
    width: int
    height: int
    rgb_topic: str
    depth_topic: str
    stamps: np.ndarray  # (N, 2) int64
    headers: np.ndarray  # (N, 2) float64
    readout_s: float = 0.0  # the colour camera's rolling-shutter readout time (s)
    _reader: list = field(default_factory=list, repr=False)  # the open AnyReader, lazily

    def __len__(self) -> int:
        return len(self.timestamps)

    @property
    def depth_timestamps(self) -> np.ndarray:
        """(N,) header stamps (s) of the frames' depth images."""
        return self.headers[:, 1].copy()

    def _open(self) -> Any:
        if not self._reader:
            highlevel, typesys = _rosbags()
            reader = highlevel.AnyReader(
                [self.root], default_typestore=typesys.get_typestore(typesys.Stores.ROS2_HUMBLE))
            reader.open()
            self._reader.append(reader)
        return self._reader[0]

    def close(self) -> None:
        """Close the bag (it opens again when a frame is decoded)."""
        while self._reader:
            self._reader.pop().close()

    def __enter__(self) -> BagSequence:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __del__(self) -> None:
        self.close()

    def _message(self, topic: str, bag_time: int, header: float) -> Any:
        reader = self._open()
        conns = [c for c in reader.connections if c.topic == topic]
        for conn, _, raw in reader.messages(conns, start=int(bag_time), stop=int(bag_time) + 1):
            msg = reader.deserialize(raw, conn.msgtype)
            if _stamp(msg) == header:
                return conn, msg
        raise ValueError(f"{self.root}: the message on {topic} at bag time {bag_time} ns is "
                         "gone (the bag changed since it was loaded?)")

    def decode_frame(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """Frame i: rgb uint8 (H, W, 3) in RGB order and depth as stored (float32 metres with
        NaN, or uint16 millimetres)."""
        n = len(self)
        if not -n <= i < n:
            raise IndexError(f"frame {i} out of range for {self.name} ({n} frames)")
        (t_rgb, t_depth), header = self.stamps[i], self.headers[i]
        conn, msg = self._message(self.rgb_topic, t_rgb, header[0])
        rgb = _rgb_image(msg, conn.msgtype, self.rgb_topic)
        _, dmsg = self._message(self.depth_topic, t_depth, header[1])
        depth = _depth_image(dmsg, self.depth_topic)
        if rgb.shape[:2] != depth.shape or depth.shape != (self.height, self.width):
            raise ValueError(f"{self.name} frame {i}: rgb on {self.rgb_topic} is "
                             f"{rgb.shape[1]}x{rgb.shape[0]}, depth on {self.depth_topic} "
                             f"{depth.shape[1]}x{depth.shape[0]}, the sequence "
                             f"{self.width}x{self.height} (width x height)")
        return rgb, depth

    def rectify_frame(self, rgb: np.ndarray, raw: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Undistort (when ``distortion`` is set) and give depth in float32 metres, 0 where
        nothing was measured (NaN, infinite, zero or negative)."""
        if raw.dtype == np.uint16:
            depth = raw.astype(np.float32) * np.float32(_DEPTH_ENCODINGS["16UC1"][1])
        else:
            depth = np.where(np.isfinite(raw) & (raw > 0), raw, np.float32(0)).astype(np.float32)
        return undistort(rgb, depth, self.intrinsics, self.distortion)


def _stamp(msg: Any) -> float:
    s = msg.header.stamp
    return float(getattr(s, "sec", 0)) + 1e-9 * float(getattr(s, "nanosec", 0))


def _rgb_image(msg: Any, msgtype: str, topic: str) -> np.ndarray:
    if msgtype == COMPRESSED:
        bgr = cv2.imdecode(np.frombuffer(bytes(msg.data), np.uint8), cv2.IMREAD_COLOR)
        if bgr is None:
            raise ValueError(f"cannot decode the compressed image on {topic} ({msg.format})")
        return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
    if msg.encoding not in _RGB_ENCODINGS:
        raise ValueError(f"rgb topic {topic}: encoding {msg.encoding!r} is not supported "
                         f"(expected one of {', '.join(_RGB_ENCODINGS)})")
    channels = {"mono8": 1, "rgb8": 3, "bgr8": 3}.get(msg.encoding, 4)
    img = _pixels(msg, np.uint8, channels, topic)
    code = _RGB_ENCODINGS[msg.encoding]
    return np.ascontiguousarray(img) if code is None else cv2.cvtColor(img, code)


def _depth_image(msg: Any, topic: str) -> np.ndarray:
    if getattr(msg, "encoding", None) not in _DEPTH_ENCODINGS:
        raise ValueError(f"depth topic {topic}: encoding {getattr(msg, 'encoding', None)!r} is "
                         "not supported (expected 32FC1 metres or 16UC1 millimetres)")
    return _pixels(msg, _DEPTH_ENCODINGS[msg.encoding][0], 1, topic).copy()


def _pixels(msg: Any, dtype: type, channels: int, topic: str) -> np.ndarray:
    """The image of an Image message (row stride ``step``, byte order ``is_bigendian``)."""
    dt = np.dtype(dtype).newbyteorder(">" if msg.is_bigendian else "<")
    row = msg.width * channels * dt.itemsize
    data = np.frombuffer(bytes(msg.data), np.uint8)
    if msg.step < row or data.size < msg.step * msg.height:
        raise ValueError(f"{topic}: a {msg.width}x{msg.height} {msg.encoding} image needs "
                         f"{row} bytes per row, the message has step {msg.step} and "
                         f"{data.size} bytes")
    rows = data[:msg.step * msg.height].reshape(msg.height, msg.step)[:, :row]
    img = np.ascontiguousarray(rows).view(dt).astype(dt.newbyteorder("="))
    return img.reshape(msg.height, msg.width) if channels == 1 else \
        img.reshape(msg.height, msg.width, channels)


def _camera(msg: Any) -> tuple[Intrinsics, Distortion | None]:
    K = np.asarray(msg.k if hasattr(msg, "k") else msg.K, np.float64)  # ROS2 / ROS1 names
    D = np.asarray(msg.d if hasattr(msg, "d") else msg.D, np.float64)
    intr = Intrinsics(float(K[0]), float(K[4]), float(K[2]), float(K[5]))
    dist = tuple(float(v) for v in D) if D.size and np.any(D != 0) else None
    return intr, dist


def load_bag(
    path: str | os.PathLike[str],
    *,
    rgb_topic: str = RGB_TOPIC,
    depth_topic: str = DEPTH_TOPIC,
    info_topic: str = INFO_TOPIC,
    camera: Camera | str | None = None,
    intrinsics: Intrinsics | None = None,
    groundtruth: str | os.PathLike[str] | None = None,
    max_diff: float = 0.02,
    frame_step: int = 1,
    readout_s: float | None = None,
) -> BagSequence:
    """Open a ROS1 bag (``.bag``) or ROS2 bag (folder, ``.db3``, ``.mcap``) as a ``Source``.

    The camera is ``camera`` when given (a ``Camera`` or a preset name of
    ``camera.CAMERAS``: its intrinsics, distortion and readout), else ``intrinsics`` (a
    pinhole: no undistortion), else the first message on ``info_topic`` (K, and D when not
    all zero). ``frame_step`` k keeps every k-th rgb and depth message before association.
    ``groundtruth``: a TUM trajectory file. ``readout_s``: the colour camera's rolling-shutter
    readout time (s); None: ``camera``'s when given, else the Freiburg cameras' when the bag's
    name names one (the benchmark's bags), else 0 (a global shutter). Errors (ValueError, naming
    the topic): a topic missing or of another message type, an unsupported encoding, rgb and
    depth of different sizes, no pair associating; UnknownCameraError (a ValueError) for no
    camera_info and no camera given; FileNotFoundError for a missing bag or ground-truth
    file."""
    root = Path(path)
    if not root.exists():
        raise FileNotFoundError(f"ROS bag not found: {root}")
    if not (isinstance(frame_step, int) and frame_step >= 1):
        raise ValueError(f"frame_step must be a positive integer, got {frame_step!r}")
    gt = None
    if groundtruth is not None:
        if not Path(groundtruth).is_file():
            raise FileNotFoundError(f"ground-truth file not found: {groundtruth}")
        gt = read_trajectory(groundtruth)
    given = source_camera(camera=camera, intrinsics=intrinsics)
    refuse_depth_fields(given, "a ROS bag")
    if readout_s is None:
        readout_s = given.readout_s if camera is not None else _readout_named(root.name)
    seq = BagSequence(root=root, name=root.stem if root.is_file() else root.name,
                      intrinsics=Intrinsics(1.0, 1.0, 1.0, 1.0), distortion=None,
                      timestamps=np.zeros(0), groundtruth=gt, width=0, height=0,
                      rgb_topic=rgb_topic, depth_topic=depth_topic,
                      stamps=np.zeros((0, 2), np.int64), headers=np.zeros((0, 2)),
                      readout_s=checked_readout(readout_s))
    try:
        reader = seq._open()
    except Exception as err:  # rosbags' own errors: not a bag, unreadable
        raise ValueError(f"cannot read the ROS bag {root}: {err}") from None
    try:
        return _scan(seq, reader, info_topic=info_topic, camera=given,
                     max_diff=max_diff, frame_step=frame_step)
    except BaseException:
        seq.close()
        raise


def _readout_named(name: str) -> float:
    """The readout of the Freiburg camera a bag's name names (the benchmark's bags), else 0."""
    try:
        return camera_from_name(name).readout_s
    except UnknownCameraError:
        return 0.0


def _scan(seq: BagSequence, reader: Any, *, info_topic: str, camera: Camera | None,
          max_diff: float, frame_step: int) -> BagSequence:
    """``seq`` with its camera, size and associated frames, from the open ``reader``."""
    root, rgb_topic, depth_topic = seq.root, seq.rgb_topic, seq.depth_topic
    conns = {c.topic: c for c in reader.connections}
    images = sorted(t for t, c in conns.items() if c.msgtype in (IMAGE, COMPRESSED))
    for topic, what, types in ((rgb_topic, "rgb", (IMAGE, COMPRESSED)),
                               (depth_topic, "depth", (IMAGE,))):
        if topic not in conns:
            raise SourceError(f"bag {root} has no topic {topic} ({what} images); its image "
                              f"topics: {', '.join(images) or 'none'}",
                              api=f"pass {what}_topic=", cli=f"pass --{what}-topic")
        if conns[topic].msgtype not in types:
            raise ValueError(f"{what} topic {topic} of {root} carries "
                             f"{conns[topic].msgtype}, not {' or '.join(types)}")
    if camera is not None:
        intr, dist = camera.intrinsics, camera.distortion
    elif info_topic in conns and conns[info_topic].msgtype == CAMERA_INFO:
        conn = conns[info_topic]
        _, _, raw = next(reader.messages([conn]))
        intr, dist = _camera(reader.deserialize(raw, conn.msgtype))
    else:
        raise UnknownCameraError(f"bag {root} has no camera_info topic {info_topic} (the "
                                 "camera's intrinsics)", also=("info_topic=", "--info-topic"))
    found: dict[str, list[tuple[int, float]]] = {rgb_topic: [], depth_topic: []}
    first: dict[str, np.ndarray] = {}
    for conn, bag_time, raw in reader.messages([conns[rgb_topic], conns[depth_topic]]):
        msg = reader.deserialize(raw, conn.msgtype)
        found[conn.topic].append((bag_time, _stamp(msg)))
        if conn.topic not in first:
            first[conn.topic] = (_rgb_image(msg, conn.msgtype, rgb_topic)
                                 if conn.topic == rgb_topic else _depth_image(msg, depth_topic))
    for topic, what in ((rgb_topic, "rgb"), (depth_topic, "depth")):
        if not found[topic]:
            raise ValueError(f"{what} topic {topic} of {root} has no messages")
    rgb0, depth0 = first[rgb_topic], first[depth_topic]
    if rgb0.shape[:2] != depth0.shape:
        raise ValueError(f"rgb on {rgb_topic} is {rgb0.shape[1]}x{rgb0.shape[0]} but depth on "
                         f"{depth_topic} is {depth0.shape[1]}x{depth0.shape[0]} "
                         "(width x height)")
    height, width = depth0.shape
    intr.validate(width=width, height=height)
    rgb_list = sorted(found[rgb_topic], key=lambda m: m[1])[::frame_step]
    depth_list = sorted(found[depth_topic], key=lambda m: m[1])[::frame_step]
    pairs = associate_timestamps(np.array([m[1] for m in rgb_list]),
                                 np.array([m[1] for m in depth_list]), max_diff)
    if pairs.shape[0] == 0:
        raise ValueError(f"no rgb/depth pair of {root} ({rgb_topic}, {depth_topic}) associates "
                         f"within {max_diff} s")
    stamps = np.array([(rgb_list[i][0], depth_list[j][0]) for i, j in pairs], np.int64)
    headers = np.array([(rgb_list[i][1], depth_list[j][1]) for i, j in pairs], np.float64)
    name = seq.name + (f"_every{frame_step}" if frame_step > 1 else "")
    return dataclasses.replace(seq, name=name, intrinsics=intr, distortion=dist,
                              timestamps=headers[:, 0].copy(), width=width, height=height,
                              stamps=stamps, headers=headers, _reader=seq._reader)
