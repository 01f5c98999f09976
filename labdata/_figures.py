"""Saving report figures: one resolution and one format for every layer."""

from __future__ import annotations

import sys
from pathlib import Path

__all__ = ["FIGURE_DPI", "FIGURE_FORMAT", "save_figure"]

#: Resolution of every saved report figure, dots per inch.
FIGURE_DPI = 110
#: File format (and suffix) used when the path has none.
FIGURE_FORMAT = "png"


def save_figure(fig, path, *, dpi: float = FIGURE_DPI, tight: bool = True, close: bool = True) -> Path:
    """Write a matplotlib figure to ``path`` and (by default) release it.

    Needs no matplotlib import of its own: it calls the figure's methods.

    Parameters
    ----------
    fig : matplotlib.figure.Figure
    path : str or Path
        Target file; the format follows the suffix, :data:`FIGURE_FORMAT`
        (suffix added) when there is none. Missing parent folders are created.
    dpi : float
        Resolution, dots per inch (default :data:`FIGURE_DPI`).
    tight : bool
        Apply ``fig.tight_layout()`` first.
    close : bool
        Close the figure afterwards (through pyplot when pyplot manages it).

    Returns
    -------
    Path
        The file written.
    """
    path = Path(path)
    if not path.suffix:
        path = path.with_suffix("." + FIGURE_FORMAT)
    path.parent.mkdir(parents=True, exist_ok=True)
    if tight:
        fig.tight_layout()
    fig.savefig(path, dpi=dpi)
    if close:
        # A figure can only be registered with pyplot if pyplot was imported;
        # if it was not, there is nothing to release.
        plt = sys.modules.get("matplotlib.pyplot")
        if plt is not None:
            plt.close(fig)
    return path
