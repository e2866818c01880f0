"""Dataset readers (host side)."""

from __future__ import annotations

from .groundtruth import groundtruth_pose_at
from .pingpong import pingpong, pingpong_indices
from .tum import (
    TumSequence,
    camera_from_name,
    load_sequence,
    read_calibration,
    read_file_list,
    subsequence,
)

__all__ = [
    "TumSequence",
    "camera_from_name",
    "groundtruth_pose_at",
    "load_sequence",
    "pingpong",
    "pingpong_indices",
    "read_calibration",
    "read_file_list",
    "subsequence",
]
