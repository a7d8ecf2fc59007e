"""Open any capture the tools read: a manifest, a peer `scene.json` or a DiLiGenT folder."""

from __future__ import annotations

from pathlib import Path

from .capture import Capture, load_capture
from .errors import CaptureError
from .importers import diligent_capture, peer_capture


def open_capture(path: str | Path, downscale: int = 1, name: str | None = None) -> Capture:
    """A capture manifest (file or folder), a peer `scene.json`, or a DiLiGenT folder, area-
    averaged by `downscale` (every kind: the cameras follow); a factor that leaves a view too
    small is refused naming `name` (the field that gave it; default `<path>: downscale`)."""
    path = Path(path)
    if downscale < 1:
        raise CaptureError(f"{path}: downscale = {downscale}; give an integer >= 1")
    kind, path = _kind(path)
    if kind == "diligent":
        return diligent_capture(path, downscale)
    if kind == "peer":
        try:
            capture = peer_capture(path)
        except CaptureError:
            raise
        except OSError as err:
            raise CaptureError(
                f"{path}: cannot read ({err.strerror or err}); check the path"
            ) from None
        except (ValueError, TypeError, KeyError, AttributeError, IndexError) as err:
            raise CaptureError(
                f"{path}: not a peer scene.json this version reads ({type(err).__name__}: {err}); "
                "check it against the peer format"
            ) from None
    else:
        capture = load_capture(path)
    capture.check_factor(downscale, name or f"{path}: downscale")
    return capture.downscaled(downscale)


def check_capture(path: str | Path) -> None:
    """What `open_capture` refuses of a capture's own file before reading any image: a file
    that is no capture, a manifest that is another kind of file (a fit config given as a
    capture) or not valid TOML, a `scene.json` its loader refuses (its images left unread). A
    batch checks its captures so before any fit starts (a folder without its file is left to
    the fit)."""
    from .capture import GIVE_A_CAPTURE
    from .model import expect_kind
    from .peer import load_peer_scene
    from .schema import load_toml

    path = Path(path)
    if path.is_dir() and not any((path / n).exists() for n in ("capture.toml", "scene.json")):
        return
    kind, path = _kind(path)
    if kind == "peer":  # the loader's own checks (a byte-order mark read, UTF-16 named)
        load_peer_scene(path)
    elif kind == "manifest":
        path = path / "capture.toml" if path.is_dir() else path
        expect_kind(
            load_toml(path, "capture manifest"),
            path,
            "a capture manifest",
            GIVE_A_CAPTURE,
            CaptureError,
        )


def _kind(path: Path) -> tuple[str, Path]:
    """("diligent" | "peer" | "manifest", its path) of a capture path, or a `CaptureError`."""
    if not path.exists():
        raise CaptureError(
            f"{path}: no such capture; give a capture.toml, its folder, a peer "
            "scene.json or a DiLiGenT folder"
        )
    if path.is_file() and path.name != "scene.json" and path.suffix.lower() != ".toml":
        raise CaptureError(
            f"{path}: is not a capture; give its capture.toml (or the folder holding it), a peer "
            "scene.json or a DiLiGenT folder"
        )
    if path.is_dir() and (path / "filenames.txt").exists():
        return "diligent", path
    if path.is_dir() and not (path / "capture.toml").exists() and (path / "scene.json").is_file():
        path = path / "scene.json"  # a peer target's folder
    if path.name == "scene.json":
        return "peer", path
    if path.is_dir() and not (path / "capture.toml").exists():
        raise CaptureError(
            f"{path}: no capture.toml, scene.json or DiLiGenT files in the folder; give a "
            "capture folder"
        )
    return "manifest", path
