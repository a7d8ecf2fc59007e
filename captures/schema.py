"""Read the `[scene]` table of a TOML config or capture manifest into a `Scene`, strictly:
unknown or misspelt keys, wrong types and missing fields are errors naming the file and the key.

```toml
[scene]
geometry = "sphere"            # or "cup", or "mesh.obj", or a table: {type = "cup", height = 0.1}
environment = [0.05, 0.05, 0.06]   # or {type = "envmap", file = "sky.exr", scale = 1.0}
integrator = "prb"             # prb | path
max_depth = 8

[[scene.cameras]]
type = "perspective"           # or "orthographic" (with ortho_width, metres)
origin = [0, -0.5, 0.2]
target = [0, 0, 0.05]
fov_x_deg = 30
width = 256
height = 256
principal_point = [129.5, 126.0]   # calibrated, pixels from the top-left (default: the centre)
# aperture_radius = 0.002      # a thin lens instead (depth of field; no principal_point);
                               # focus_distance defaults to the target

[[scene.lights]]
type = "rectangle"             # rectangle | point | directional
center = [0.3, -0.3, 0.4]
target = [0, 0, 0.05]          # or u_axis, v_axis, emit_direction
size = [0.2, 0.2]
power = 20.0                   # watts; or radiance = [r, g, b]
temperature = 3200             # kelvin; or color = [r, g, b]
```
"""

from __future__ import annotations

import logging
import math
import tomllib
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path
from typing import Annotated, ClassVar, Literal

import numpy as np
from pydantic import BeforeValidator, Field, StrictBool, field_validator, model_validator

from .color import blackbody_rgb
from .errors import CaptureError
from .geometry import CupShape, check_obj
from .model import (
    ExistingPath,
    FieldError,
    FiniteFloat,
    NonNegativeFloat,
    NonNegativeVec3,
    PositiveFloat,
    PositiveInt,
    StrictModel,
    Vec3,
    by_shape,
    parse_model,
    tagged,
)
from .scene import (
    Camera,
    Cup,
    DirectionalLight,
    EnvMap,
    ObjFile,
    PointLight,
    RectLight,
    Scene,
    Sphere,
    bounding_sphere,
    inside,
)

log = logging.getLogger(__name__)


def load_toml(path: Path, what: str = "file") -> dict:
    """A TOML document, or a `CaptureError` naming the file and what is wrong with it."""
    try:
        return tomllib.loads(Path(path).read_text(encoding="utf-8-sig"))
    except FileNotFoundError:
        raise CaptureError(f"{path}: no such {what}") from None
    except IsADirectoryError:
        raise CaptureError(f"{path}: is a folder; give the {what} (a TOML file)") from None
    except UnicodeDecodeError as err:
        raise CaptureError(
            f"{path}: not UTF-8 text ({err.reason} at byte {err.start}); the {what} is a TOML "
            "file saved as UTF-8"
        ) from None
    except tomllib.TOMLDecodeError as err:
        raise CaptureError(f"{path}: not valid TOML ({err}); fix the syntax") from None
    except OSError as err:
        raise CaptureError(f"{path}: cannot read ({err.strerror})") from None


# Geometry -----------------------------------------------------------------------------------------


class SphereSpec(StrictModel):
    type: Literal["sphere"]
    """Mitsuba's analytic sphere (with UVs)."""
    center: Vec3 = (0.0, 0.0, 0.0)
    """Centre in metres."""
    radius: PositiveFloat = 1.0
    """Radius in metres."""

    def build(self) -> Sphere:
        return Sphere(self.center, self.radius)


#: A cup's segments around its axis at most: 2048 is under a 0.2 mm chord on a 10 cm cup (the
#: default 128 renders smooth); 1e8 asked for 97 GiB and failed as an internal error.
MAX_CUP_SEGMENTS = 2048


class CupSpec(StrictModel):
    type: Literal["cup"]
    """The procedural cup (`captures.geometry.cup_mesh`)."""
    height: PositiveFloat = CupShape.height
    """Height in metres."""
    radius_top: PositiveFloat = CupShape.radius_top
    """Outer radius at the rim, metres."""
    radius_bottom: PositiveFloat = CupShape.radius_bottom
    """Outer radius at the foot, metres."""
    wall: PositiveFloat = CupShape.wall
    """Wall thickness, metres."""
    base: PositiveFloat = CupShape.base
    """Base thickness, metres."""
    fillet: PositiveFloat = CupShape.fillet
    """Radius of the fillets joining base and walls, metres."""
    handle: StrictBool = CupShape.handle
    """Whether the cup has a handle."""
    segments: Annotated[int, Field(ge=8, le=MAX_CUP_SEGMENTS, strict=True)] = CupShape.segments
    """Segments around the axis."""

    @model_validator(mode="after")
    def _shape_is_sound(self):
        self.build()  # CupShape's ValueError names the dimension
        return self

    def build(self) -> Cup:
        return Cup(CupShape(**self.model_dump(exclude={"type"})))


class ObjSpec(StrictModel):
    type: Literal["obj"]
    """A triangle mesh from an OBJ file (UVs where the material has masks, textures or noise)."""
    file: ExistingPath
    """The OBJ file, relative to the TOML file's folder."""
    face_normals: StrictBool = False
    """Shade each face flat by its own normal. The default shades by the file's `vn` normals or,
    without them, by normals interpolated over the faces (which rounds sharp edges: a warning
    says so)."""

    @field_validator("file")
    @classmethod
    def _is_obj(cls, path: Path) -> Path:
        if path.suffix.lower() != ".obj":
            raise ValueError(
                f"'{path.name}' is not an OBJ file; only OBJ meshes are read: convert it (e.g. "
                "Blender or meshio: meshio convert mesh.ply mesh.obj) and keep its UVs"
            )
        return path

    def build(self) -> ObjFile:
        check = check_obj(self.file, self.face_normals)
        for message in check.warnings:
            log.warning(message)
        return ObjFile(
            self.file, check.without_uvs == 0, self.face_normals, check.warnings, check.bounds
        )


def _geometry_shorthand(value):
    """ "sphere", "cup" or an OBJ file name for its table."""
    if isinstance(value, str):
        if value in ("sphere", "cup"):
            return {"type": value}
        if not value.lower().endswith(".obj"):
            raise ValueError(
                f"got {value!r}; give sphere, cup or the name of an .obj file (convert other "
                "meshes, e.g. meshio convert mesh.ply mesh.obj, keeping their UVs)"
            )
        return {"type": "obj", "file": value}
    return value


Geometry = Annotated[tagged(SphereSpec, CupSpec, ObjSpec), BeforeValidator(_geometry_shorthand)]


# Cameras ------------------------------------------------------------------------------------------


#: How far a principal point may lie from the image's centre, as a share of the image's size: a
#: calibrated one is within a few percent; further off, it was likely given in another
#: convention (normalised, or pixels of another resolution).
MAX_PRINCIPAL_OFFSET = 0.25


class CameraSpec(StrictModel):
    type: Literal["perspective", "orthographic"] = "perspective"
    """The projection (a thin lens is a perspective camera with an `aperture_radius`)."""

    @field_validator("type", mode="before")
    @classmethod
    def _thin_lens(cls, value):
        if isinstance(value, str) and value.replace("_", "").replace("-", "").lower() in (
            "thinlens",
            "lens",
        ):
            raise ValueError(
                f'got {value!r}; a thin lens is type = "perspective" with aperture_radius '
                "(and focus_distance, default the target's)"
            )
        return value

    origin: Vec3
    """The camera's position, metres."""
    target: Vec3
    """The point it looks at, metres."""
    up: Vec3 = (0.0, 0.0, 1.0)
    """The world direction that is up in the image."""
    fov_x_deg: Annotated[FiniteFloat, Field(gt=0, lt=180)] = 40.0
    """Horizontal field of view in degrees (perspective only; required there)."""
    width: PositiveInt
    """Image width in pixels."""
    height: PositiveInt
    """Image height in pixels."""
    aperture_radius: NonNegativeFloat = 0.0
    """Thin-lens aperture radius in metres (perspective only; 0: a pinhole)."""
    focus_distance: PositiveFloat | None = None
    """Thin-lens focus distance in metres (default: the target's)."""
    ortho_width: PositiveFloat = 1.0
    """Horizontal extent of the view in metres (orthographic only; required there)."""
    principal_point: tuple[FiniteFloat, FiniteFloat] | None = None
    """A calibrated pinhole camera's principal point `[cx, cy]`, in pixels of this image from its
    top-left corner, pixel centres at +0.5 (COLMAP's convention: the image's centre is
    `[width / 2, height / 2]`, the default; OpenCV's `cx, cy` plus 0.5)."""

    @model_validator(mode="after")
    def _consistent(self):
        given = self.model_fields_set
        if self.origin == self.target:
            raise FieldError("target", "equals origin; the camera needs a viewing direction")
        view, up = np.subtract(self.target, self.origin), np.asarray(self.up, float)
        if np.linalg.norm(np.cross(view, up)) <= 1e-6 * np.linalg.norm(view) * np.linalg.norm(up):
            # z (the world's up), else y, else x: the first well across the view
            axes = ([0, 0, 1], [0, 1, 0], [1, 0, 0])
            across = next(a for a in axes if abs(np.dot(a, view)) < 0.7 * np.linalg.norm(view))
            raise FieldError(
                "up",
                ("" if "up" in given else "the default ")
                + f"{list(self.up)} is zero or along the viewing direction (origin to target); "
                f"give up = {across} (or another direction across it: the image's top)",
            )
        if self.type == "perspective" and "fov_x_deg" not in given:
            raise FieldError("fov_x_deg", "missing; add it (a perspective camera needs it)")
        if self.type == "orthographic":
            if "ortho_width" not in given:
                raise FieldError("ortho_width", "missing; add it (an orthographic camera needs it)")
            lens = {"fov_x_deg", "aperture_radius", "focus_distance", "principal_point"}
            for key in sorted(lens & given):
                raise FieldError(key, "does not apply to type = 'orthographic'; drop it")
        if self.focus_distance is not None and self.aperture_radius == 0:
            raise FieldError(  # it was dropped without a word: a pinhole focuses everywhere
                "focus_distance",
                "applies to a thin lens only, and this camera is a pinhole (aperture_radius 0); "
                "give aperture_radius (metres) for a thin lens, or drop focus_distance",
            )
        if self.principal_point is not None:
            self._check_principal_point()
        return self

    def _check_principal_point(self) -> None:
        if self.aperture_radius > 0:
            raise FieldError(
                "principal_point",
                "applies to a pinhole camera only (Mitsuba's thin lens has none); drop it or "
                "aperture_radius",
            )
        centre = (self.width / 2, self.height / 2)
        off = [abs(p - c) / (2 * c) for p, c in zip(self.principal_point, centre, strict=True)]
        if max(off) > MAX_PRINCIPAL_OFFSET:
            cx, cy = self.principal_point
            raise FieldError(
                "principal_point",
                f"[{cx:g}, {cy:g}] is {max(off):.0%} of the image from its centre "
                f"[{centre[0]:g}, {centre[1]:g}] (at most {MAX_PRINCIPAL_OFFSET:.0%}): give it in "
                f"pixels of this {self.width}x{self.height} image from its top-left corner (a "
                "calibration at another resolution scales with it)",
            )

    def build(self) -> Camera:
        return Camera(kind=self.type, **self.model_dump(exclude={"type"}))


# Lights -------------------------------------------------------------------------------------------

Amount = by_shape(number=NonNegativeFloat, array=NonNegativeVec3)


class _Emitter(StrictModel):
    """A light's colour and amount: `<amount>` as RGB or a number times the colour, or `power`
    (watts, where the light has it) times the colour."""

    color: NonNegativeVec3 | None = None
    """Linear RGB tint of a number or power (default white); or give temperature."""
    temperature: float | None = None
    """Colour temperature in kelvin, 1667 to 25000 (luminance 1); or give color."""

    amount: ClassVar[str]  # the field holding the amount

    @field_validator("temperature")
    @classmethod
    def _black_body(cls, kelvin: float | None):
        try:
            blackbody_rgb(6500.0 if kelvin is None else kelvin)  # None only from Python callers
        except ValueError as err:
            raise ValueError(str(err).removeprefix("= ")) from None
        return kelvin

    @model_validator(mode="after")
    def _one_amount(self):
        if self.color is not None and self.temperature is not None:
            raise ValueError("color and temperature both given; give one")
        self.rgb()
        return self

    def per_watt(self) -> float:
        """The amount per watt of power per unit of colour."""
        raise NotImplementedError

    def rgb(self) -> tuple[float, float, float]:
        """The light's linear RGB amount."""
        direct, power = getattr(self, self.amount), getattr(self, "power", None)
        if (direct is None) == (power is None):
            raise ValueError(f"needs exactly one of {self.amount} or power; give one")
        white = self.color or (1.0, 1.0, 1.0)
        colour = np.array(white if self.temperature is None else blackbody_rgb(self.temperature))
        if isinstance(direct, tuple):
            if self.color is not None or self.temperature is not None:
                raise FieldError(self.amount, "is RGB already; drop color/temperature")
            value = np.array(direct)
        else:
            value = (direct if power is None else power * self.per_watt()) * colour
        if not np.any(value > 0):
            if self.color is not None and not any(c > 0 for c in self.color):
                raise FieldError("color", "is black; give a colour with light in it")
            raise FieldError(self.amount if power is None else "power", "is zero; make it > 0")
        return tuple(float(x) for x in value)


class RectLightSpec(_Emitter):
    type: Literal["rectangle"] = "rectangle"
    """A one-sided emitting rectangle."""
    center: Vec3
    """Centre in metres."""
    target: Vec3 | None = None
    """A point it faces (or give u_axis, v_axis, emit_direction)."""
    up: Vec3 | None = None
    """With target: the world direction its v edge leans towards (default +z)."""
    u_axis: Vec3 | None = None
    """Unit direction of the first edge."""
    v_axis: Vec3 | None = None
    """Unit direction of the second edge."""
    emit_direction: Vec3 | None = None
    """Unit direction it emits towards, -(u_axis x v_axis)."""
    size: tuple[PositiveFloat, PositiveFloat]
    """Edge lengths along u_axis and v_axis, metres."""
    radiance: Amount | None = None
    """Emitted radiance, W/(m^2 sr): linear RGB, or a number times the colour."""
    power: PositiveFloat | None = None
    """Emitted power in watts (or give radiance)."""

    amount = "radiance"

    @model_validator(mode="after")
    def _frame_given(self):
        axes = ("u_axis", "v_axis", "emit_direction")
        if self.target is not None:
            if any(getattr(self, k) is not None for k in axes):
                raise ValueError("give target (and up) or u_axis, v_axis, emit_direction, not both")
            if self.target == self.center:
                raise FieldError("target", "equals center; the light needs a direction")
            return self
        for key in axes:
            if getattr(self, key) is None:
                raise FieldError(key, "missing; add it, or give target instead")
        uvn = np.array([getattr(self, k) for k in axes])
        with np.errstate(all="ignore"):  # 1e200 in an axis: its products overflow
            gram = uvn @ uvn.T
        if not np.allclose(gram, np.eye(3), atol=1e-3):  # inf and nan are not close
            raise ValueError(
                "u_axis, v_axis, emit_direction must be orthogonal unit vectors (emit_direction "
                "= -(u_axis x v_axis)); fix them, or give target (and up) instead"
            )
        return self

    def per_watt(self) -> float:
        return 1.0 / (math.pi * (self.size[0] * self.size[1]))  # the area first, as before

    def frame(self):
        """(u, v, n): given, or facing `target` with `up` (n = -(u x v), the peers' convention)."""
        if self.target is None:
            return self.u_axis, self.v_axis, self.emit_direction
        n = np.subtract(self.target, self.center)
        n /= np.linalg.norm(n)
        u = np.cross(self.up or (0.0, 0.0, 1.0), n)
        if np.linalg.norm(u) < 1e-6:
            u = np.cross([1.0, 0.0, 0.0], n)
        u /= np.linalg.norm(u)
        return tuple(tuple(float(x) for x in a) for a in (u, np.cross(u, n), n))

    def build(self) -> RectLight:
        u, v, n = self.frame()
        return RectLight(self.center, u, v, self.size, n, self.rgb())


class PointLightSpec(_Emitter):
    type: Literal["point"]
    """An isotropic point light."""
    position: Vec3
    """Position in metres."""
    intensity: Amount | None = None
    """Radiant intensity, W/sr: linear RGB, or a number times the colour."""
    power: PositiveFloat | None = None
    """Emitted power in watts (or give intensity)."""

    amount = "intensity"

    def per_watt(self) -> float:
        return 1.0 / (4 * math.pi)

    def build(self) -> PointLight:
        return PointLight(self.position, self.rgb())


class DirectionalLightSpec(_Emitter):
    type: Literal["directional"]
    """A distant light."""
    direction: Vec3
    """The direction the light travels (normalised here)."""
    irradiance: Amount
    """Irradiance, W/m^2: linear RGB, or a number times the colour."""

    amount = "irradiance"

    @field_validator("direction")
    @classmethod
    def _nonzero(cls, direction):
        if not any(direction):
            raise ValueError("is zero; give the direction the light travels")
        return direction

    def build(self) -> DirectionalLight:
        d = np.array(self.direction) / np.linalg.norm(self.direction)
        return DirectionalLight(tuple(float(x) for x in d), self.rgb())


Light = tagged(RectLightSpec, PointLightSpec, DirectionalLightSpec, default="rectangle")


# Environment and scene ----------------------------------------------------------------------------


class ConstantEnvSpec(StrictModel):
    type: Literal["constant"]
    """Constant radiance from every direction."""
    radiance: NonNegativeVec3
    """Linear RGB radiance, W/(m^2 sr)."""

    def build(self) -> tuple[float, float, float]:
        return self.radiance


class EnvMapSpec(StrictModel):
    type: Literal["envmap"]
    """A lat-long (equirectangular) environment map: its top row is up (+z), its centre
    column faces -y."""
    file: ExistingPath
    """The linear image, relative to the TOML file's folder."""
    scale: PositiveFloat = 1.0
    """Factor on the map's values."""

    @field_validator("file")
    @classmethod
    def _is_image(cls, path: Path) -> Path:
        from .images import image_problem, read_image

        problem = image_problem(path)
        if problem is not None:
            raise ValueError(problem)
        pixels = read_image(path)
        low = float(pixels[..., :3].min())
        if low < 0:  # a constant environment below 0 is refused too
            raise ValueError(
                f"'{path.name}' holds negative radiance (down to {low:.4g}); light is not "
                "negative: clip the map at 0"
            )
        if not float(pixels[..., :3].max()) > 0:  # it lights nothing (without lights: nothing)
            raise ValueError(
                f"'{path.name}' is black everywhere: it lights nothing; give a map with light, "
                "or drop the environment"
            )
        return path

    def build(self) -> EnvMap:
        return EnvMap(self.file, self.scale)


def _environment_shorthand(value):
    """[r, g, b] for a constant environment's table."""
    return {"type": "constant", "radiance": value} if isinstance(value, list | tuple) else value


Environment = Annotated[
    tagged(ConstantEnvSpec, EnvMapSpec), BeforeValidator(_environment_shorthand)
]


class SceneSpec(StrictModel):
    geometry: Geometry
    """The object: "sphere", "cup", an OBJ file, or a table with its type."""
    cameras: Annotated[tuple[CameraSpec, ...], Field(min_length=1)]
    """The views' cameras ([[scene.cameras]])."""
    lights: tuple[Light, ...] = ()
    """The lights ([[scene.lights]])."""
    environment: Environment = ConstantEnvSpec(type="constant", radiance=(0.0, 0.0, 0.0))
    """Light from afar: [r, g, b] radiance or a table (constant or envmap)."""
    integrator: Literal["prb", "path"] = "prb"
    """Mitsuba's integrator."""
    max_depth: PositiveInt = 8
    """The integrator's maximum path depth."""

    @model_validator(mode="after")
    def _lit(self):
        if (
            not self.lights
            and self.environment.type == "constant"
            and not any(self.environment.radiance)
        ):
            raise ValueError("the scene has no light; add [[scene.lights]] or an environment")
        return self

    def build(self) -> Scene:
        return Scene(
            geometry=self.geometry.build(),
            cameras=tuple(c.build() for c in self.cameras),
            lights=tuple(light.build() for light in self.lights),
            environment=self.environment.build(),
            integrator=self.integrator,
            max_depth=self.max_depth,
        )


#: How far from the origin an object may reach, in its own radii. The renderer keeps positions in
#: float32, which resolves |x| * 1.2e-7 at |x|: beyond 1e4 radii that is over 1e-3 of the
#: object's size. Measured (a sphere of radius 1, its cameras and lights moved with it): 1e3
#: away it rendered and fitted as at the origin; at (1e5, 1e5, 0) its surface rendered torn and
#: a fit to photographs of the sphere missed its pigment by 0.09 (16 sd), at (5e5, 4e6, 100)
#: alpha by 30 % and ior by 0.14.
FAR_FROM_ORIGIN = 1e4


#: A perspective camera whose field of view in degrees is at most pi, and whose object spans
#: more than this many times it, has probably been given its field of view in radians.
RADIANS_SPAN = 3.0


def radians_note(camera, center, radius: float) -> str | None:
    """Why a camera's field of view looks like radians given as degrees (None where it does
    not): at most pi, with the object (its bounding sphere) spanning `RADIANS_SPAN` times it or
    more, so the view sees a small piece of it. Blender's Python gives `camera.data.angle` in
    radians; 0.846 was taken as 0.846 degrees and only the silhouette's overlap warned."""
    if camera.kind != "perspective" or camera.fov_x_deg > np.pi:
        return None
    distance = float(np.linalg.norm(np.subtract(camera.origin, center)))
    if distance <= radius:
        return None
    span = 2.0 * np.degrees(np.arcsin(radius / distance))
    if span < RADIANS_SPAN * camera.fov_x_deg:
        return None
    return (
        f"a field of view of {camera.fov_x_deg:g} degrees sees a small piece of the object "
        f"(it spans {span:.3g} degrees from this camera); if the value is in radians, give "
        f"{np.degrees(camera.fov_x_deg):.4g} (degrees)"
    )


def parse_scene(data: dict, file: Path, names: Callable[[str], str] = str) -> Scene:
    """A `Scene` from the `[scene]` table of `file` (relative paths resolve against its folder),
    its warnings' field names passed through `names` (a peer file's own)."""
    scene = parse_model(SceneSpec, data, file, "scene").build()
    center, radius = bounding_sphere(scene.geometry)
    reach = float(np.max(np.abs(center)) + radius)
    if radius > 0 and reach > FAR_FROM_ORIGIN * radius:
        raise CaptureError(
            f"{file}: scene.geometry: the object (centre {np.round(center, 3).tolist()}, radius "
            f"{radius:.3g}) reaches {reach:.3g} from the origin, {reach / radius:.2g} times its "
            f"radius, where the renderer's float32 positions are {reach * 2.0**-23:.2g} apart: "
            "its surface would render torn; move the scene to the origin (subtract the centre "
            "from the mesh's vertices, the cameras' origins and targets and the lights' "
            "positions)"
        )
    for i, camera in enumerate(scene.cameras):
        note = radians_note(camera, center, radius)
        if note is not None:
            message = f"{file}: scene.cameras[{i}].fov_x_deg = {camera.fov_x_deg:g}: {note}"
            log.warning(names(message))
    # the cameras' origins and the lights' positions, each with its field (one mesh read)
    where = [(f"cameras[{i}].origin", c.origin) for i, c in enumerate(scene.cameras)]
    for i, light in enumerate(scene.lights):
        if isinstance(light, RectLight | PointLight):
            field = "center" if isinstance(light, RectLight) else "position"
            where.append((f"lights[{i}].{field}", getattr(light, field)))
    points = np.array([point for _, point in where], float).reshape(-1, 3)
    within = np.flatnonzero(inside(scene.geometry, points))
    if len(within):
        name, point = where[within[0]]
        others = f" (and {len(within) - 1} more)" if len(within) > 1 else ""
        what = (
            "the camera would see the object's inside; move it out"
            if name.startswith("cameras")
            else "the light would light the object's inside only; move it out"
        )
        raise CaptureError(
            f"{file}: scene.{name} {list(point)} is inside the object{others} (centre "
            f"{np.round(center, 3).tolist()}, bounding radius {radius:.3g}): {what} (check the "
            "units and the axes: a mesh in millimetres with cameras and lights in metres, or a "
            "swapped axis, puts it there)"
        )
    for i, light in enumerate(scene.lights):
        if isinstance(light, RectLight):
            ahead = float(np.dot(light.emit_direction, np.subtract(center, light.center)))
            if ahead < -radius:  # the whole object behind the emitting side
                raise CaptureError(
                    f"{file}: scene.lights[{i}]: emits towards {list(light.emit_direction)}, "
                    f"away from the object (centre {np.round(center, 3).tolist()}, "
                    f"{-ahead:.3g} behind the light): it lights nothing; negate emit_direction "
                    "(it is -(u_axis x v_axis)), or give target instead"
                )
    return scene


# Writing ------------------------------------------------------------------------------------------


def geometry_to_table(g, rel=str) -> dict:
    """The `[scene.geometry]` table of a sphere, a cup or an OBJ file (its path written by
    `rel`)."""
    if isinstance(g, Sphere):
        return {"type": "sphere", "center": list(g.center), "radius": g.radius}
    if isinstance(g, Cup):
        return {"type": "cup", **asdict(g.shape)}
    if isinstance(g, ObjFile):
        table = {"type": "obj", "file": rel(g.path)}
        if g.face_normals:
            table["face_normals"] = True
        return table
    raise CaptureError(f"{g.source}: a mesh held in memory has no manifest entry; save an OBJ")


def scene_to_table(scene: Scene, folder: Path | None = None) -> dict:
    """The `[scene]` table of `scene` without cameras (a capture's come from its views). File
    paths are written relative to `folder`."""

    def rel(path: Path) -> str:
        return str(Path(path).relative_to(folder)) if folder else str(path)

    geometry = geometry_to_table(scene.geometry, rel)
    lights = []
    for light in scene.lights:
        if isinstance(light, RectLight):
            keys = ("center", "u_axis", "v_axis", "emit_direction", "size", "radiance")
            lights.append({"type": "rectangle", **{k: list(getattr(light, k)) for k in keys}})
        elif isinstance(light, PointLight):
            keys = ("position", "intensity")
            lights.append({"type": "point", **{k: list(getattr(light, k)) for k in keys}})
        else:
            keys = ("direction", "irradiance")
            lights.append({"type": "directional", **{k: list(getattr(light, k)) for k in keys}})
    env = scene.environment
    environment = (
        {"type": "envmap", "file": rel(env.path), "scale": env.scale}
        if isinstance(env, EnvMap)
        else {"type": "constant", "radiance": list(env)}
    )
    return {
        "geometry": geometry,
        "environment": environment,
        "integrator": scene.integrator,
        "max_depth": scene.max_depth,
        "lights": lights,
    }


def camera_to_table(camera: Camera) -> dict:
    out = {
        "type": camera.kind,
        "origin": list(camera.origin),
        "target": list(camera.target),
        "up": list(camera.up),
        "width": camera.width,
        "height": camera.height,
    }
    if camera.kind == "orthographic":
        out["ortho_width"] = camera.ortho_width
    else:
        out["fov_x_deg"] = camera.fov_x_deg
        if camera.principal_point is not None:
            out["principal_point"] = list(camera.principal_point)
        if camera.aperture_radius > 0:
            out["aperture_radius"] = camera.aperture_radius
            if camera.focus_distance:
                out["focus_distance"] = camera.focus_distance
    return out
