"""Deprecated: the modules of ``edgevo_jax.backend`` moved to ``edgevo_jax.window`` (the
sliding window: ``local_map`` (now ``sliding``), ``problem`` (was ``window``), ``schur``,
``prior``, ``refine``, ``activation``) and ``edgevo_jax.map`` (``pose_graph``). Importing
``edgevo_jax.backend.X`` still works, with a DeprecationWarning, until 0.3."""

import importlib
import sys
import warnings

_MOVED = {"local_map": "window.sliding", "window": "window.problem",
          "schur": "window.schur", "prior": "window.prior", "refine": "window.refine",
          "activation": "window.activation", "pose_graph": "map.pose_graph"}

warnings.warn("edgevo_jax.backend is deprecated: its modules moved to edgevo_jax.window and "
              "edgevo_jax.map (docs/architecture.md)", DeprecationWarning, stacklevel=2)
for _name, _target in _MOVED.items():
    sys.modules[f"{__name__}.{_name}"] = importlib.import_module(f"edgevo_jax.{_target}")
