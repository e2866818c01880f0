"""``python -m edgevo_jax.cli``: the ``edgevo`` command (a sweep's local processes start
this way)."""

from . import main

if __name__ == "__main__":
    raise SystemExit(main())
