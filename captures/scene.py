"""The scene a capture was taken in: geometry, cameras, lights, environment (no Dr.Jit, no JAX).

Plain frozen dataclasses with numpy-free tuples at the edges, so that a render config and a capture
manifest share one description and `fit` turns it into a Mitsuba scene.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

Vec3 = tuple[float, float, float]


@dataclass(frozen=True)
class Camera:
    """A perspective pinhole camera looking from `origin` at `target`; `fov_x_deg` is horizontal."""

    origin: Vec3
    target: Vec3
    up: Vec3
    fov_x_deg: float
    width: int
    height: int


@dataclass(frozen=True)
class RectLight:
    """A one-sided rectangle emitting `radiance` (linear RGB, W/(m^2 sr)) towards `emit_direction`.

    `u_axis`, `v_axis` are unit edge directions and `size` the edge lengths in metres.
    """

    center: Vec3
    u_axis: Vec3
    v_axis: Vec3
    size: tuple[float, float]
    emit_direction: Vec3
    radiance: Vec3


@dataclass(frozen=True)
class Scene:
    """Geometry (an OBJ path or the built-in unit `"sphere"`), cameras, lights, environment."""

    geometry: Path | str
    cameras: tuple[Camera, ...]
    lights: tuple[RectLight, ...] = ()
    environment: Vec3 = (0.0, 0.0, 0.0)
    max_depth: int = 8
    meta: dict = field(default_factory=dict, compare=False)
