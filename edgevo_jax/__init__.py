"""edgevo_jax: edge-based RGB-D visual odometry (EdgeVO) in JAX."""

from .camera import Intrinsics
from .config import Config
from .tracker import FrameResult, Odometry

__all__ = ["Config", "FrameResult", "Intrinsics", "Odometry"]
__version__ = "0.1.0"
