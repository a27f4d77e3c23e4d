"""Matplotlib helpers shared by the studies (headless: the Agg backend unless one is chosen)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

if matplotlib.get_backend().lower() not in ("agg", "module://matplotlib_inline.backend_inline"):
    matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402


def subplots(nrows=1, ncols=1, width=6.0, height=3.6, **kwargs):
    """``plt.subplots`` sized per panel, its axes always a 2-D array (``squeeze=False``:
    ``axes[0, 1]`` for one row of two, not ``axes[1]``)."""
    return plt.subplots(
        nrows, ncols, figsize=(width * ncols, height * nrows), squeeze=False, **kwargs
    )


def save(fig, path: Path, dpi: int = 120) -> Path:
    """Save ``fig`` as PNG at ``path`` (``dpi`` dots per inch) and close it."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.tight_layout()
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return path
