"""Learning the tracker's weights by gradients: ``Params`` (the learnable numbers, apart
from the static ``Config``), the smooth training mode (``track_smooth``), the differentiable
alignment with its two adjoints, the depth residual's weight by implicit differentiation of
the plain solve (``depth_weight_gradient``), and pose losses against ground truth."""

from .balance import WeightGradient, depth_weight_gradient
from .differentiable import (
    ADJOINTS,
    CONSISTENCY,
    INTERPOLATIONS,
    edge_magnitudes,
    level_system,
    newton_decrement,
    selection_scores,
    track_differentiable,
    track_window,
)
from .losses import (
    ate_loss,
    pose_loss,
    relative_pose_error,
    rigid_alignment,
    rpe_loss,
    window_rpe_loss,
)
from .params import Params
from .smooth import Smoothing, smooth_system, soft_consistency_dots, track_smooth

__all__ = [
    "ADJOINTS",
    "CONSISTENCY",
    "INTERPOLATIONS",
    "Params",
    "Smoothing",
    "WeightGradient",
    "ate_loss",
    "depth_weight_gradient",
    "edge_magnitudes",
    "level_system",
    "newton_decrement",
    "pose_loss",
    "relative_pose_error",
    "rigid_alignment",
    "rpe_loss",
    "selection_scores",
    "smooth_system",
    "soft_consistency_dots",
    "track_differentiable",
    "track_smooth",
    "track_window",
    "window_rpe_loss",
]
