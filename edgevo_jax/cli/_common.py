"""What the ``edgevo`` subcommands share: argparse types of positive numbers, and a
trajectory file read with an error that says which one is missing."""

from __future__ import annotations

import argparse
import math
from pathlib import Path


def _positive_int(text: str) -> int:
    """argparse type: an integer >= 1."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number >= 1, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {value}")
    return value


def _positive_float(text: str) -> float:
    """argparse type: a finite number > 0."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number > 0, got {text!r}") from None
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"must be a finite number > 0, got {text}")
    return value


def _read(path: Path, what: str):
    from ..io import read_trajectory

    if not path.is_file():
        raise FileNotFoundError(f"{what} trajectory file not found: {path}")
    return read_trajectory(path)

