"""Figures written by the CLI: matplotlib without a display, files whole or not at all."""

from __future__ import annotations

from pathlib import Path


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
    out.parent.mkdir(parents=True, exist_ok=True)
    partial = out.with_name(f".{out.name}.partial.png")
    try:
        fig.savefig(partial, dpi=dpi)
        partial.replace(out)
    finally:
        plt.close(fig)
        partial.unlink(missing_ok=True)
    return out
