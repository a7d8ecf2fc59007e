"""The scene a capture was taken in: geometry, cameras, lights, environment (no Dr.Jit, no JAX).

Frozen dataclasses holding plain tuples, so that a render config and a capture manifest share one
description and `fit` turns it into a Mitsuba scene. Light colours are resolved to linear RGB here
(from RGB, power or colour temperature), so nothing downstream needs to know how they were given.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from .geometry import CupShape, MeshData

Vec3 = tuple[float, float, float]


# Geometry -----------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Sphere:
    """Mitsuba's analytic sphere (with UVs)."""

    center: Vec3 = (0.0, 0.0, 0.0)
    radius: float = 1.0


@dataclass(frozen=True)
class Cup:
    """The procedural cup (`captures.geometry.cup_mesh`)."""

    shape: CupShape = field(default_factory=CupShape)


@dataclass(frozen=True)
class ObjFile:
    """A triangle mesh from an OBJ file; `uvs`: texture coordinates on every face (what layer
    masks, textures and the glaze's noise need; a plain material renders without)."""

    path: Path
    uvs: bool = True
    face_normals: bool = False
    """Shade each face by its own normal (flat) rather than normals interpolated over faces."""
    warnings: tuple[str, ...] = field(default=(), compare=False)
    """How the renderer's shading will differ from the object (`captures.geometry.check_obj`)."""
    bounds: tuple | None = field(default=None, compare=False)
    """Its vertices' box (lowest, highest corner) where `check_obj` read it; else read again."""


@dataclass(frozen=True, eq=False)
class MeshArrays:
    """A triangle mesh held in memory (`MeshData`), e.g. the height field of a normal map;
    `source` names where it came from (shown to the user)."""

    data: MeshData
    source: str


Geometry = Sphere | Cup | ObjFile | MeshArrays


# Cameras ------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Camera:
    """A camera looking from `origin` at `target`.

    `kind` "perspective": horizontal field of view `fov_x_deg`; a thin lens when
    `aperture_radius` > 0 (metres), focused at `focus_distance` (metres; default: the target).
    `kind` "orthographic": the view spans `ortho_width` metres horizontally.
    `principal_point` (a pinhole's, calibrated): `(cx, cy)` in pixels from the image's top-left
    corner, pixel centres at +0.5; None is the image's centre.
    """

    origin: Vec3
    target: Vec3
    up: Vec3
    fov_x_deg: float
    width: int
    height: int
    kind: str = "perspective"
    aperture_radius: float = 0.0
    focus_distance: float | None = None
    ortho_width: float = 1.0
    principal_point: tuple[float, float] | None = None

    def principal_offset(self) -> tuple[float, float]:
        """The image's centre minus the principal point, as shares of the width and height
        (Mitsuba's `principal_point_offset_x`, `_y`); (0, 0) without one."""
        if self.principal_point is None:
            return 0.0, 0.0
        cx, cy = self.principal_point
        return 0.5 - cx / self.width, 0.5 - cy / self.height

    def resized(self, width: int, height: int) -> Camera:
        """The camera with `width` x `height` square pixels over the same field of view, centred
        as `weights.downscale` centres them (`width / self.width` of this one's pixels a side);
        the principal point follows."""
        point = self.principal_point
        if point is not None:
            scale = width / self.width
            point = (
                width / 2 + (point[0] - self.width / 2) * scale,
                height / 2 + (point[1] - self.height / 2) * scale,
            )
        return replace(self, width=width, height=height, principal_point=point)


# Lights -------------------------------------------------------------------------------------------


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
class PointLight:
    """An isotropic point light of radiant `intensity` (linear RGB, W/sr)."""

    position: Vec3
    intensity: Vec3


@dataclass(frozen=True)
class DirectionalLight:
    """A distant light travelling along `direction`, of `irradiance` (linear RGB, W/m^2)."""

    direction: Vec3
    irradiance: Vec3


Light = RectLight | PointLight | DirectionalLight


@dataclass(frozen=True)
class EnvMap:
    """An environment map (lat-long image, linear) scaled by `scale`: its top row is up (+z),
    its centre column faces -y."""

    path: Path
    scale: float = 1.0


# Scene --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Scene:
    """Geometry, the views' cameras, lights, an environment (constant RGB radiance or a map), and
    the integrator (`prb` by default) with its maximum path depth."""

    geometry: Geometry
    cameras: tuple[Camera, ...]
    lights: tuple[Light, ...] = ()
    environment: Vec3 | EnvMap = (0.0, 0.0, 0.0)
    integrator: str = "prb"
    max_depth: int = 8
    meta: dict = field(default_factory=dict, compare=False)


def bounding_sphere(geometry: Geometry) -> tuple[np.ndarray, float]:
    """(centre, radius) enclosing the object."""
    if isinstance(geometry, Sphere):
        return np.asarray(geometry.center, float), float(geometry.radius)
    if isinstance(geometry, Cup):
        s = geometry.shape
        reach = s.radius_top + (0.045 if s.handle else 0.0)
        return np.array([0.0, 0.0, s.height / 2]), float(np.hypot(reach, s.height / 2 + s.wall))
    if isinstance(geometry, MeshArrays):
        points = geometry.data.positions
        lo, hi = np.min(points, axis=0), np.max(points, axis=0)
        return (lo + hi) / 2, float(np.linalg.norm(hi - lo) / 2)
    if geometry.bounds is not None:
        lo, hi = (np.asarray(corner, float) for corner in geometry.bounds)
    else:
        text = Path(geometry.path).read_text(errors="replace")
        words = (line.split() for line in text.splitlines())
        points = [[float(x) for x in w[1:4]] for w in words if w and w[0] == "v"]
        lo, hi = np.min(points, axis=0), np.max(points, axis=0)
    return (lo + hi) / 2, float(np.linalg.norm(hi - lo) / 2)


def inside(geometry: Geometry, points: np.ndarray) -> np.ndarray:
    """Whether each point lies inside the object. A mesh: inside its box, and most of three rays
    crossing its faces an odd number of times; where the mesh is open (an edge not shared by
    exactly two faces) also its winding number above 3/4 in magnitude (about 1 inside, an open
    flat sheet below 1/2). The count alone decides a closed mesh: faces wound against their
    neighbours spoil the winding number, not the count."""
    from .geometry import closed, crossings, cup_mesh, obj_triangles, winding_numbers

    points = np.atleast_2d(np.asarray(points, float))
    if isinstance(geometry, Sphere):
        distance = np.linalg.norm(points - np.asarray(geometry.center, float), axis=1)
        return distance < geometry.radius
    if isinstance(geometry, ObjFile) and geometry.bounds is not None:
        lo, hi = (np.asarray(corner, float) for corner in geometry.bounds)
    elif isinstance(geometry, MeshArrays):
        lo, hi = geometry.data.positions.min(axis=0), geometry.data.positions.max(axis=0)
    else:
        center, radius = bounding_sphere(geometry)
        lo, hi = center - radius, center + radius
    near = np.all((points > lo) & (points < hi), axis=1)  # the rest: outside, no mesh read
    out = np.zeros(len(points), bool)
    if not near.any():
        return out
    if isinstance(geometry, Cup):
        mesh = cup_mesh(geometry.shape)
        positions, faces = mesh.positions, mesh.faces
    elif isinstance(geometry, MeshArrays):
        positions, faces = geometry.data.positions, geometry.data.faces
    else:
        positions, faces = obj_triangles(geometry.path)
    unique, index = np.unique(points[near], axis=0, return_inverse=True)
    odd = np.sum(crossings(positions, faces, unique) % 2, axis=1) >= 2  # most of three rays
    if not closed(positions, faces):  # a ray may leave through a hole: the winding number too
        odd &= np.abs(winding_numbers(positions, faces, unique)) > 0.75
    out[near] = odd[np.ravel(index)]
    return out


def sees(camera: Camera, center: np.ndarray, radius: float) -> bool:
    """Whether any of the sphere (center, radius) falls inside the camera's view."""
    origin, forward = np.asarray(camera.origin, float), np.subtract(camera.target, camera.origin)
    forward = forward / np.linalg.norm(forward)
    offset = center - origin
    if np.linalg.norm(offset) <= radius:
        return True  # inside the bounding sphere (a long shelf, a stray vertex): not decided here
    depth = offset @ forward
    lateral = np.linalg.norm(offset - depth * forward)
    aspect = camera.height / camera.width
    if camera.kind == "orthographic":
        half = camera.ortho_width / 2 * np.hypot(1.0, aspect)
        return depth + radius > 0 and lateral < half + radius
    if depth + radius <= 0:
        return False
    half_x = np.tan(np.radians(camera.fov_x_deg) / 2)
    ox, oy = (abs(x) for x in camera.principal_offset())  # an off-centre axis: its far corner
    half_diag = np.arctan(half_x * np.hypot(1 + 2 * ox, aspect * (1 + 2 * oy)))
    angle = np.arctan2(lateral, depth)
    return angle < half_diag + np.arcsin(min(1.0, radius / max(np.linalg.norm(offset), 1e-12)))
