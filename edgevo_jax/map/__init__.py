"""The keyframe map (DESIGN.md, "Beyond the paper"): every keyframe kept with what aligning a
frame to it again needs (``store``), place recognition by randomised ferns
(``recognition``) and what a keyframe joins the map with (``describe``)."""

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

__all__ = ["Appearance", "Candidate", "Ferns", "KeyframeMap", "MapFullWarning", "MapKeyframe",
           "describe", "edge_points", "encode", "make_ferns", "predicted_overlap", "similarity"]
