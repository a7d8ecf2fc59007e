"""Figures written by the CLI: matplotlib without a display, files whole or not at all."""

from __future__ import annotations

from pathlib import Path

from captures.files import atomic_path


def pyplot():
    """`matplotlib.pyplot` on the Agg backend (no display needed)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig, out: Path, dpi: int = 110) -> Path:
    """Save `fig` to `out` through a temporary file (a reader never sees half a PNG), then close
    it."""
    plt = pyplot()
    try:
        with atomic_path(out) as partial:
            fig.savefig(partial, dpi=dpi, format=out.suffix.lstrip(".") or "png")
    finally:
        plt.close(fig)
    return out
