"""What a fit hands back: figures and the HTML report (written whole or not at all,
through the one atomic writer `captures.files`)."""

from captures.files import atomic_path, write_text

from .figures import pyplot, save_figure
from .report import ViewPanel, write_report

__all__ = [
    "ViewPanel",
    "atomic_path",
    "pyplot",
    "save_figure",
    "write_report",
    "write_text",
]
