"""Dataset readers (host side)."""

from __future__ import annotations

from pathlib import Path

from .calibration import camera_from_name, read_calibration
from .cover import covered_copy
from .groundtruth import groundtruth_pose_at
from .pingpong import pingpong, pingpong_indices, there_and_back
from .tum import TumSequence, load_sequence, read_file_list, subsequence

#: the clip shipped in the package: the first 10 frames of TUM fr1/xyz (CC BY 4.0), the
#: default sequence of ``edgevo run``; usable from any working directory
BUNDLED_CLIP = (Path(__file__).resolve().parent.parent / "data"
                / "rgbd_dataset_freiburg1_xyz_first10")

__all__ = [
    "BUNDLED_CLIP",
    "TumSequence",
    "camera_from_name",
    "covered_copy",
    "groundtruth_pose_at",
    "load_sequence",
    "pingpong",
    "pingpong_indices",
    "read_calibration",
    "read_file_list",
    "subsequence",
    "there_and_back",
]
