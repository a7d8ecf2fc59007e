"""Figures written by the CLI: matplotlib without a display, files whole or not at all."""

from __future__ import annotations

import warnings
from pathlib import Path

from captures.files import atomic_path


def pyplot():
    """`matplotlib.pyplot` on the Agg backend (no display needed)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    # a view or key named in a script the font lacks (CJK) draws boxes; its warning (with a
    # source line, per glyph) on stderr said nothing a user can act on
    warnings.filterwarnings(
        "ignore", message=r"Glyph \d+ .* missing from font", category=UserWarning
    )
    return plt


#: The PNG `Software` tag of every figure layerfit writes: a file carrying it may be redrawn
#: (a resumed bench), any other is a user's own.
SOFTWARE = "layerfit"


def save_figure(fig, out: Path, dpi: int = 110) -> Path:
    """Save `fig` to `out` through a temporary file (a reader never sees half a PNG), then close
    it. PNGs are tagged `Software = layerfit`."""
    plt = pyplot()
    fmt = out.suffix.lstrip(".").lower() or "png"
    try:
        with atomic_path(out) as partial:
            metadata = {"Software": SOFTWARE} if fmt == "png" else None
            fig.savefig(partial, dpi=dpi, format=fmt, metadata=metadata)
    finally:
        plt.close(fig)
    return out


def drawn_by_layerfit(path: Path) -> bool:
    """Whether `path` is a PNG that layerfit drew (its `Software` tag)."""
    try:
        with open(path, "rb") as f:
            head = f.read(4096)
    except OSError:
        return False
    return head.startswith(b"\x89PNG") and b"Software\x00" + SOFTWARE.encode() in head
