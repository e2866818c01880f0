"""edgevo_jax: edge-based RGB-D visual odometry (EdgeVO) in JAX.

The public API: ``Config`` and ``Intrinsics`` (what a run needs; ``Camera``: intrinsics
with lens distortion and rolling-shutter readout, for ``load_sequence(camera=...)``, which
also takes a preset name of ``camera.CAMERAS``), ``Odometry`` (the streaming tracker, with
per-frame motion priors and ``reset``; ``FrameResult`` per frame), ``align`` (one frame pair
from an initial guess: success, transform, information; ``AlignResult``), ``run`` (a whole
sequence, with its trajectory file) and ``evaluate`` (many sequences under many
configurations, batched), ``load_sequence`` (TUM-style folders), ``summarise`` (a run's
statistics and ATE / RPE), ``ate`` and ``rpe`` (a trajectory's absolute and relative pose
errors, as evo computes them), ``Pose`` (the SE(3) pose type of device code) and
``enable_batch_exact``. Importing the package changes no process-wide setting. The first
tracker (``Odometry``, ``run``, ``evaluate``, ``align``) switches on, as the ``edgevo`` CLI
does, the on-disk program cache (``EDGEVO_CACHE_DIR``; "" turns it off) and batch-size-exact
CPU arithmetic (``EDGEVO_EXACT=0`` turns it off): ``programs.enable_cache``, which leaves
settings the user made alone. ``enable_batch_exact`` does the latter alone, before any JAX
computation.

Layout (docs/architecture.md): ``tracking`` (the per-frame tracker: the driver ``Odometry``,
the decision, recovery, the keyframe map's queries, the back end), ``map`` (the record of
every pose, the keyframe store, recognition, loops and the pose graph), ``window`` (the
sliding window, Schur complement, marginalisation, its worker), ``frontend`` (residual,
alignment, selection, keyframes), ``image`` (preprocessing, interpolation), ``learn``
(Params, differentiable tracking, losses), ``runs`` (run, batch, sweep, calibrate, measure),
with ``geometry``, ``camera``, ``config`` / ``derive``, ``solvers``, ``workers``,
``metrics``, ``io``, ``datasets``, ``viz`` and ``cli`` beside them; ``peers`` (other odometry
methods, for comparison), ``runs.measure`` and ``reports`` serve the benchmarks.
"""

from .camera import Camera, Intrinsics
from .config import Config
from .datasets.tum import load_sequence
from .determinism import enable_batch_exact
from .geometry import Pose
from .metrics import ate, rpe
from .runs.batch import evaluate
from .runs.pair import AlignResult, align
from .runs.run import run_sequence as run
from .runs.run import summarise
from .tracking.odometry import FrameResult, Odometry

__all__ = ["AlignResult", "Camera", "Config", "FrameResult", "Intrinsics", "Odometry", "Pose",
           "align", "ate", "enable_batch_exact", "evaluate", "load_sequence", "rpe", "run",
           "summarise"]
__version__ = "0.1.0"
