"""What outlives the window: the one record of every keyframe's and frame's pose
(``poses``), the keyframe map with what aligning a frame to a keyframe again needs
(``store``), place recognition by randomised ferns (``recognition``), which frames a tie may
still move (``ledger``), the loops and the pose graph over the keyframes (``loops``,
``pose_graph``)."""

from .poses import Correction, Poses
from .recognition import Ferns, encode, make_ferns, similarity
from .store import (
    Appearance,
    Candidate,
    KeyframeMap,
    MapFullWarning,
    MapKeyframe,
    describe,
    edge_points,
    predicted_overlap,
)

__all__ = ["Appearance", "Candidate", "Correction", "Ferns", "KeyframeMap", "MapFullWarning",
           "MapKeyframe", "Poses", "describe", "edge_points", "encode", "make_ferns",
           "predicted_overlap", "similarity"]
