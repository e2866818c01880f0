"""Plots of trajectories, frames, edge selection and configuration comparisons (matplotlib).

matplotlib is an optional dependency (``pip install edgevo_jax[viz]``) and is imported only
inside the functions. Figures are drawn on matplotlib's Agg canvas directly (no pyplot, no
global backend switch, no display needed); each function writes one PNG and returns its path.
The ``edgevo plot`` command (``edgevo_jax.cli``) makes each figure with one command line.

- :func:`plot_trajectory`: estimated trajectory vs ground truth after the ATE's rigid
  alignment (:func:`edgevo_jax.metrics.align_trajectory`), top view and x / y / z over
  time, coloured by the per-pose error.
- :func:`plot_frame`: one pre-processed frame: gray image, Canny edges coloured by gradient
  magnitude, nearest-edge gradient direction and the distance-field pyramid (EdgeVO Fig. 3).
- :func:`plot_selection_overlay`: selected edges over the gray image, one panel per selection
  (EdgeVO Fig. 5: partition greedy spreads the edges, plain greedy clusters them).
- :func:`plot_ablation`: edges used vs ATE (EdgeVO Fig. 6) and time per frame vs ATE
  (Fig. 1d), from the records the selection ablation aggregates (docs/ablation).
- :func:`plot_benchmark`: time per frame vs ATE per method, from ``scripts/bench.py`` rows.
- :func:`plot_frame_rates`: ATE and silently diverged frames against the frame step, from
  ``scripts/robustness_bench.py``'s aggregates.
- :func:`learning.plot_loss_curve`, :func:`learning.plot_weight_curves`: a fit of ``Params``
  (``runs.fit``): the loss per step, the learnt weight against each input.
- :func:`sweep.plot_sweep`: ATE and ms per frame of every run of a sweep (``edgevo batch
  SWEEP.toml``'s ``summary.png``).
- :func:`map.plot_map`: a saved keyframe map's edges from two sides, coloured by keyframe
  time (``edgevo plot map``).
- :func:`read_results`: the records of a benchmark, ablation or ``edgevo run --stats`` JSON.
"""

from ..metrics import TrajectoryAlignment, align_trajectory
from ._canvas import require_matplotlib
from .comparisons import (
    ABLATION_KEYS,
    BENCH_KEYS,
    plot_ablation,
    plot_benchmark,
    plot_frame_rates,
    plot_selection_overlay,
    read_results,
)
from .run import plot_frame, plot_trajectory

__all__ = [
    "ABLATION_KEYS",
    "BENCH_KEYS",
    "TrajectoryAlignment",
    "align_trajectory",
    "plot_ablation",
    "plot_benchmark",
    "plot_frame",
    "plot_frame_rates",
    "plot_selection_overlay",
    "plot_trajectory",
    "read_results",
    "require_matplotlib",
]
