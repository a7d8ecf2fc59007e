"""What the camera saw: scene descriptions, photo sets and their loaders (no Dr.Jit, no JAX)."""

from .errors import CaptureError, InputError
from .open import open_capture
from .peer import load_peer_scene
from .scene import Camera, RectLight, Scene
from .schema import parse_scene

__all__ = [
    "Camera",
    "CaptureError",
    "InputError",
    "RectLight",
    "Scene",
    "load_peer_scene",
    "open_capture",
    "parse_scene",
]
