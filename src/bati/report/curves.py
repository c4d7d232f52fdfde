"""Figures of the reports, each written atomically."""

from __future__ import annotations

from pathlib import Path


def save_figure(fig, path: Path, dpi: int) -> None:
    """Write a figure atomically (a temporary file, then a rename) and close it."""
    import matplotlib.pyplot as plt

    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp.png")
    fig.savefig(tmp, dpi=dpi)
    plt.close(fig)
    tmp.replace(path)
