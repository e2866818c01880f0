"""Dataset readers (host side)."""

from __future__ import annotations

from .groundtruth import groundtruth_pose_at
from .pingpong import pingpong, pingpong_indices
from .tum import (
    FREIBURG_CAMERAS,
    FROM_NAME,
    TumSequence,
    camera_from_name,
    load_sequence,
    read_file_list,
    subsequence,
)

__all__ = [
    "FREIBURG_CAMERAS",
    "FROM_NAME",
    "TumSequence",
    "camera_from_name",
    "groundtruth_pose_at",
    "load_sequence",
    "pingpong",
    "pingpong_indices",
    "read_file_list",
    "subsequence",
]
