"""edgevo_jax: edge-based RGB-D visual odometry (EdgeVO) in JAX."""

from .determinism import cap_cpu_isa, full_precision_products

cap_cpu_isa()  # before any JAX computation: see determinism.py
full_precision_products()  # float32 products in float32 on GPUs too (determinism.py)

from .camera import Intrinsics  # noqa: E402
from .config import Config  # noqa: E402
from .tracker import FrameResult, Odometry  # noqa: E402

__all__ = ["Config", "FrameResult", "Intrinsics", "Odometry"]
__version__ = "0.1.0"
