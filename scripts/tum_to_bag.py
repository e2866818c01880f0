"""Write the associated frames of a TUM folder as a ROS bag laid out like the TUM bags
(ROS1 ``.bag`` or ROS2 folder), with rosbags: ``/camera/rgb/image_color`` (rgb8 or bgr8),
``/camera/depth/image`` (32FC1 metres with NaN for no measurement, or 16UC1 millimetres) and
``/camera/rgb/camera_info`` (K from the folder's camera, D its distortion or zeros), header
stamps the folder's timestamps. Needs ``pip install 'edgevo_jax[ros]'``.

    python scripts/tum_to_bag.py ../shared/data/tum/rgbd_dataset_freiburg3_teddy_first200 \\
        teddy60.bag --frames 60
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from edgevo_jax.camera import CAMERAS
from edgevo_jax.datasets import load_sequence
from edgevo_jax.datasets.source import DEPTH_TOPIC, INFO_TOPIC, RGB_TOPIC, UnknownCameraError


def write_bag(seq, out: str | Path, *, frames: int | None = None, ros2: bool = False,
              rgb_encoding: str = "rgb8", depth_encoding: str = "32FC1",
              camera_info: bool = True, rgb_topic: str = RGB_TOPIC,
              depth_topic: str = DEPTH_TOPIC, depth_size: tuple[int, int] | None = None) -> Path:
    """``seq``'s first ``frames`` associated frames (None: all) as a bag at ``out``.
    ``depth_size`` (W, H): resize depth (nearest) to make a broken bag for tests."""
    import cv2
    from rosbags import rosbag1, rosbag2
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE if ros2 else Stores.ROS1_NOETIC)
    T = ts.types
    Time, Image, Info = (T["builtin_interfaces/msg/Time"], T["sensor_msgs/msg/Image"],
                         T["sensor_msgs/msg/CameraInfo"])
    RegionOfInterest = T["sensor_msgs/msg/RegionOfInterest"]

    def header(t: float, frame: str):
        sec = int(np.floor(t))
        stamp = Time(sec=sec, nanosec=int(round((t - sec) * 1e9)))
        if ros2:
            return T["std_msgs/msg/Header"](stamp=stamp, frame_id=frame)
        return T["std_msgs/msg/Header"](seq=0, stamp=stamp, frame_id=frame)

    def image(t, img, encoding):
        h, w = img.shape[:2]
        data = np.ascontiguousarray(img).view(np.uint8).reshape(-1)
        return Image(header=header(t, "camera"), height=h, width=w, encoding=encoding,
                     is_bigendian=0, step=data.size // h, data=data)

    serialize = ts.serialize_cdr if ros2 else ts.serialize_ros1
    out = Path(out)
    writer = rosbag2.Writer(out, version=9) if ros2 else rosbag1.Writer(out)
    n = len(seq) if frames is None else min(frames, len(seq))
    with writer:
        c_rgb = writer.add_connection(rgb_topic, Image.__msgtype__, typestore=ts)
        c_depth = writer.add_connection(depth_topic, Image.__msgtype__, typestore=ts)
        c_info = writer.add_connection(INFO_TOPIC, Info.__msgtype__, typestore=ts) \
            if camera_info else None
        intr = seq.intrinsics
        K = np.array([intr.fx, 0, intr.cx, 0, intr.fy, intr.cy, 0, 0, 1], np.float64)
        D = np.array(seq.distortion or (0.0,) * 5, np.float64)
        for i in range(n):
            t = float(seq.timestamps[i])
            rgb, raw = seq.decode_frame(i)
            ns = int(round(t * 1e9))
            if c_info is not None:
                fields = dict(header=header(t, "camera"), height=seq.height, width=seq.width,
                              distortion_model="plumb_bob",
                              R=np.eye(3).reshape(-1), P=np.zeros(12), binning_x=0, binning_y=0,
                              roi=RegionOfInterest(x_offset=0, y_offset=0, height=0, width=0,
                                                   do_rectify=False))
                fields.update({"d": D, "k": K, "r": fields.pop("R"), "p": fields.pop("P")}
                              if ros2 else {"D": D, "K": K})
                writer.write(c_info, ns, serialize(Info(**fields), Info.__msgtype__))
            colour = rgb if rgb_encoding == "rgb8" else cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)
            writer.write(c_rgb, ns, serialize(image(t, colour, rgb_encoding), Image.__msgtype__))
            if depth_encoding == "32FC1":
                depth = raw.astype(np.float32) / np.float32(seq.depth_factor)
                depth[raw == 0] = np.nan
            else:  # millimetres
                depth = np.round(raw.astype(np.float64) / seq.depth_factor * 1e3).astype(
                    np.uint16)
            if depth_size is not None:
                depth = cv2.resize(depth, depth_size, interpolation=cv2.INTER_NEAREST)
            writer.write(c_depth, ns + 1000,
                         serialize(image(t, depth, depth_encoding), Image.__msgtype__))
    return out


def main() -> int:
    """The command: 0 when the bag is written, 2 (and a one-line message) when rosbags is
    missing or the folder is bad."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("sequence", type=Path, help="TUM sequence folder")
    ap.add_argument("out", type=Path, help="the bag (ROS1: a .bag file; ROS2: a folder)")
    ap.add_argument("--frames", type=int, default=None, help="first N associated frames")
    ap.add_argument("--ros2", action="store_true", help="write a ROS2 bag (sqlite3)")
    ap.add_argument("--depth-encoding", choices=("32FC1", "16UC1"), default="32FC1")
    ap.add_argument("--rgb-encoding", choices=("rgb8", "bgr8"), default="rgb8")
    ap.add_argument("--camera", choices=list(CAMERAS), default=None,
                    help="the folder's camera when its name names none (a preset)")
    args = ap.parse_args()
    try:
        import rosbags  # noqa: F401  (before any work: the writer needs it)
    except ImportError:
        print('tum_to_bag.py: error: writing ROS bags needs the rosbags package: '
              'pip install "edgevo_jax[ros]"', file=sys.stderr)
        return 2
    try:
        seq = load_sequence(args.sequence, camera=args.camera)
    except UnknownCameraError as err:
        print(f"tum_to_bag.py: error: {err.what}: pass --camera ({', '.join(CAMERAS)})",
              file=sys.stderr)
        return 2
    except (FileNotFoundError, ValueError) as err:
        print(f"tum_to_bag.py: error: {err}", file=sys.stderr)
        return 2
    path = write_bag(seq, args.out, frames=args.frames, ros2=args.ros2,
                     rgb_encoding=args.rgb_encoding, depth_encoding=args.depth_encoding)
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
