"""The Agg canvas every figure is drawn on, the selection modes' styles, and the
ImportError naming the ``viz`` extra when matplotlib is missing."""

from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # only for annotations: viz sits beside preprocess, not above it
    pass


# one colour and marker per selection mode, stable across figures
STYLE = {
    "spg": ("tab:blue", "o", "spg (partition greedy)"),
    "greedy": ("tab:orange", "s", "greedy (no partitions)"),
    "random": ("tab:green", "^", "random"),
    "all": ("tab:red", "*", "all culled edges"),
}
MODE_ORDER = ("spg", "greedy", "random", "all")
DPI = 120
MISSING_MATPLOTLIB = (
    "edgevo_jax.viz needs matplotlib: pip install 'edgevo_jax[viz]' "
    "(or pip install 'matplotlib>=3.7')"
)


def require_matplotlib() -> None:
    """Raise ImportError naming ``pip install 'edgevo_jax[viz]'`` when matplotlib is missing
    (call it before expensive work whose only purpose is a plot)."""
    try:
        import matplotlib  # noqa: F401
    except ImportError as err:
        raise ImportError(MISSING_MATPLOTLIB) from err


def figure(figsize: tuple[float, float], **kwargs: Any) -> Any:
    """A matplotlib Figure on an Agg canvas; a clear ImportError when matplotlib is missing."""
    try:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
    except ImportError as err:  # pragma: no cover - exercised only without matplotlib
        raise ImportError(MISSING_MATPLOTLIB) from err
    fig = Figure(figsize=figsize, **kwargs)
    FigureCanvasAgg(fig)
    return fig


def save(fig: Any, path: str | os.PathLike[str], dpi: float | None = None) -> Path:
    """Write ``fig`` as a PNG at ``path`` (parent folders made), ``dpi`` or the default."""
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, format="png", dpi=DPI if dpi is None else dpi)
    return out


