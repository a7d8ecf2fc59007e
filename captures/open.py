"""Open any capture the tools read: a manifest, a peer `scene.json` or a DiLiGenT folder."""

from __future__ import annotations

from pathlib import Path

from .capture import Capture, load_capture
from .errors import CaptureError
from .importers import diligent_capture, peer_capture


def open_capture(path: str | Path, downscale: int = 1) -> Capture:
    """A capture manifest (file or folder), a peer `scene.json`, or a DiLiGenT folder, area-
    averaged by `downscale` (every kind: the cameras follow)."""
    path = Path(path)
    if path.is_dir() and (path / "filenames.txt").exists():
        return diligent_capture(path, downscale)
    if path.name == "scene.json":
        capture = peer_capture(path)
    elif path.is_dir() and not (path / "capture.toml").exists():
        raise CaptureError(f"{path}: no capture.toml, scene.json or DiLiGenT files in the folder")
    else:
        capture = load_capture(path)
    return capture.downscaled(downscale)
