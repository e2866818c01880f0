"""The ``edgevo`` command: ``edgevo run`` tracks a TUM sequence, ``edgevo calibrate``
estimates its camera from the recording, ``edgevo batch`` tracks many sequences under many
configurations at once, ``edgevo eval`` scores a trajectory, ``edgevo plot`` draws figures
(trajectory, frame, selection, configs; see ``edgevo_jax.viz``)."""

from __future__ import annotations

import argparse
import sys
import time

STARTED = time.perf_counter()  # the command's start (the start-up it reports counts from it)

from ..datasets import BUNDLED_CLIP  # noqa: E402  (re-exported: tests, notebooks)
from . import batch, calibrate, plot, run  # noqa: E402
from . import eval as eval_  # noqa: E402
from . import map as map_  # noqa: E402
from .eval import ALIGN_CHOICES, DELTA_UNIT_CHOICES  # noqa: E402

# One module per subcommand (run, calibrate, batch, eval, plot, map), each with
# add_parser(sub) and command(args); this module assembles the parser and turns errors into
# exit codes.
# Heavy imports (JAX, OpenCV, the pipeline) wait inside the commands, so that
# `edgevo --help` and argument errors are quick.

__all__ = ["ALIGN_CHOICES", "BUNDLED_CLIP", "DELTA_UNIT_CHOICES", "STARTED", "main"]


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="edgevo", description="Edge-based RGB-D visual odometry (EdgeVO) in JAX."
    )
    sub = p.add_subparsers(dest="command", required=True)
    for module in (run, calibrate, batch, eval_, plot, map_):  # the order `edgevo --help` lists
        module.add_parser(sub)
    return p


def main(argv: list[str] | None = None, *, started: float | None = None) -> int:
    """Entry point of the ``edgevo`` console script; ``started``: the ``time.perf_counter()``
    the reported start-up counts from (None: when this module was imported)."""
    args = _parser().parse_args(argv)
    args.started = STARTED if started is None else started
    if args.command in ("run", "batch", "calibrate"):
        from ..determinism import enable_batch_exact

        enable_batch_exact()  # a run's trajectory equals its trajectory in any batch
    try:
        if args.command == "run":
            return run.command(args)
        if args.command == "calibrate":
            return calibrate.command(args)
        if args.command == "plot":
            return plot.command(args)
        if args.command == "batch":
            return batch.command(args)
        if args.command == "map":
            return map_.command(args)
        return eval_.command(args)
    except (FileNotFoundError, ValueError, ImportError) as err:
        print(f"edgevo: error: {err}", file=sys.stderr)
        for note in getattr(err, "__notes__", []):  # where a run stopped, what it kept
            print(f"edgevo: {note}", file=sys.stderr)
        return 2
