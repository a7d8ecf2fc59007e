"""What a fit hands back: figures and sheets (written whole or not at all, through the one atomic
writer `captures.files`)."""

from captures.files import atomic_path, write_text

from .figures import pyplot, save_figure
from .sheets import comparison_sheet, loss_plot

__all__ = ["atomic_path", "comparison_sheet", "loss_plot", "pyplot", "save_figure", "write_text"]
