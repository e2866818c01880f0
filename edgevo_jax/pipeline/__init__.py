"""Deprecated: the modules of ``edgevo_jax.pipeline`` moved to ``edgevo_jax.tracking`` (the
per-frame tracker), ``edgevo_jax.runs`` (run, batch, sweep, calibrate, measure, pair),
``edgevo_jax.map`` (ledger, loops) and ``edgevo_jax.window`` (the window's worker). Importing
``edgevo_jax.pipeline.X`` still works, with a DeprecationWarning, until 0.3."""

import importlib
import sys
import warnings

_MOVED = {"odometry": "tracking.odometry", "decision": "tracking.decision",
          "records": "tracking.records", "results": "tracking.results",
          "recovery": "tracking.recovery", "effects": "tracking.effects",
          "relocalise": "tracking.places", "inputs": "tracking.inputs",
          "loops": "map.loops", "mapping": "window.worker", "run": "runs.run",
          "batch": "runs.batch", "sweep": "runs.sweep", "sweep_file": "runs.sweep_file",
          "calibrate": "runs.calibrate", "measure": "runs.measure", "pair": "runs.pair",
          "processes": "runs.processes"}

warnings.warn("edgevo_jax.pipeline is deprecated: its modules moved to edgevo_jax.tracking, "
              "edgevo_jax.runs, edgevo_jax.map and edgevo_jax.window (docs/architecture.md)",
              DeprecationWarning, stacklevel=2)
for _name, _target in _MOVED.items():
    sys.modules[f"{__name__}.{_name}"] = importlib.import_module(f"edgevo_jax.{_target}")
