"""The figures of a fit of ``Params`` (``runs.fit``, ``scripts/learn_weights.py``): the
training loss per step, and the learnt weight against each input of the weighting model."""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ._canvas import figure, save

__all__ = ["FEATURE_LABELS", "plot_loss_curve", "plot_weight_curves"]

#: axis labels of the weighting model's inputs (``frontend.robust.FEATURES``)
FEATURE_LABELS = {"gradient magnitude": "log(m / canny_high)", "depth": "log depth (m)",
                  "depth discontinuity": "log(1 + 10 (max - min) / z)",
                  "residual": "residual / gate", "level": "level / (L - 1)",
                  "re-observation": "1 / (1 + exp(a - m))"}


def plot_loss_curve(losses: Sequence[float], full: Sequence[float],
                    path: str | os.PathLike[str], title: str, what: str) -> Path:
    """Each step's minibatch loss (before its step) and the loss over all training ``what``
    (``full``: before the first step, then after each) against the adam step; the PNG's
    path."""
    fig = figure((5, 3), dpi=80)
    ax = fig.add_subplot(1, 1, 1)
    ax.plot(np.arange(len(losses)), losses, marker="o", markersize=2, lw=0.8, alpha=0.6,
            label="minibatch (before its step)")
    ax.plot(np.arange(len(full)), full, lw=1.8, label=f"all training {what}")
    ax.set_xlabel("adam step")
    ax.set_ylabel("mean RPE loss")
    ax.legend(fontsize=8)
    ax.set_title(title, fontsize=9)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    return save(fig, path, dpi=80)


def plot_weight_curves(curves: Mapping[str, Mapping[str, Any]],
                       path: str | os.PathLike[str], title: str) -> Path:
    """One panel per input of ``curves`` (``runs.fit.weight_curves``: name -> ``feature``
    and ``weight`` lists): the weight scale against the input, 1 dashed; the PNG's path."""
    fig = figure((9, 5), dpi=80)
    for i, (name, c) in enumerate(curves.items()):
        ax = fig.add_subplot(2, 3, i + 1)
        ax.plot(c["feature"], c["weight"], lw=1.8)
        ax.axhline(1.0, color="gray", lw=0.8, ls="--")
        ax.set_xlabel(FEATURE_LABELS.get(name, name), fontsize=8)
        ax.set_ylabel("weight scale", fontsize=8)
        ax.set_title(name, fontsize=9)
        ax.grid(alpha=0.3)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    return save(fig, path, dpi=80)
