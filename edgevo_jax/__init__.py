"""edgevo_jax: edge-based RGB-D visual odometry (EdgeVO) in JAX.

Importing the package changes no process-wide setting: see ``enable_batch_exact`` for
batch-size-exact CPU arithmetic (the ``edgevo`` CLI turns it on).
"""

from .camera import Intrinsics
from .config import Config
from .determinism import enable_batch_exact
from .tracker import FrameResult, Odometry

__all__ = ["Config", "FrameResult", "Intrinsics", "Odometry", "enable_batch_exact"]
__version__ = "0.1.0"
