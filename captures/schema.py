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
aperture_radius = 0.002        # thin lens (depth of field); focus_distance defaults to the target

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

import math
import tomllib
from pathlib import Path

import numpy as np

from .color import blackbody_rgb
from .errors import CaptureError
from .geometry import CupShape, check_obj_has_uvs
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
)

INTEGRATORS = ("prb", "path")


def load_toml(path: Path, what: str = "file") -> dict:
    """A TOML document, or a `CaptureError` naming the file and what is wrong with it."""
    try:
        return tomllib.loads(Path(path).read_text())
    except FileNotFoundError:
        raise CaptureError(f"{path}: no such {what}") from None
    except tomllib.TOMLDecodeError as err:
        raise CaptureError(f"{path}: not valid TOML ({err})") from None


class Table:
    """A TOML table that knows where it came from and which keys it may hold."""

    def __init__(self, data, file: Path, where: str, known: tuple[str, ...]):
        if not isinstance(data, dict):
            raise CaptureError(f"{file}: [{where}] must be a table")
        unknown = sorted(set(data) - set(known))
        if unknown:  # before missing keys: a misspelt key is the likelier mistake
            raise CaptureError(
                f"{file}: unknown key(s) {', '.join(unknown)} in "
                f"{f'[{where}]' if where else 'the top level'}; "
                f"known: {', '.join(known)}"
            )
        self.data, self.file, self.where = data, file, where

    def has(self, key) -> bool:
        return key in self.data

    def error(self, key, problem) -> CaptureError:
        name = f"{self.where}.{key}" if self.where else key
        return CaptureError(f"{self.file}: {name} {problem}")

    def _get(self, key, default, required):
        if key not in self.data:
            if required:
                place = f"[{self.where}]" if self.where else "the top level"
                raise CaptureError(f"{self.file}: {place} needs {key!r}")
            return default
        return self.data[key]

    def vec(self, key, n=3, default=None, required=None):
        value = self._get(key, default, default is None if required is None else required)
        if value is None:
            return None
        try:
            out = tuple(float(x) for x in value)
        except (TypeError, ValueError):
            out = ()
        if len(out) != n or not all(math.isfinite(x) for x in out):
            raise self.error(key, f"must be {n} finite numbers, got {value!r}")
        return out

    def number(self, key, kind=float, default=None, minimum=None, required=None):
        value = self._get(key, default, default is None if required is None else required)
        if value is None:
            return None
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise self.error(key, f"must be a number, got {value!r}")
        if kind is int and int(value) != value:
            raise self.error(key, f"must be an integer, got {value!r}")
        if not math.isfinite(value) or (minimum is not None and value < minimum):
            raise self.error(key, f"= {value} must be >= {minimum}")
        return kind(value)

    def positive(self, key, default=None, required=None):
        value = self.number(key, float, default, 0.0, required)
        if value is not None and value <= 0:
            raise self.error(key, f"= {value} must be > 0")
        return value

    def string(self, key, default=None, choices=None):
        value = self._get(key, default, default is None)
        if not isinstance(value, str):
            raise self.error(key, f"must be a string, got {value!r}")
        if choices is not None and value not in choices:
            raise self.error(key, f"= {value!r}; choose one of {', '.join(choices)}")
        return value

    def boolean(self, key, default):
        value = self._get(key, default, False)
        if not isinstance(value, bool):
            raise self.error(key, f"must be true or false, got {value!r}")
        return value

    def path(self, key, default=None):
        value = self.string(key, default)
        path = (self.file.parent / value).resolve()
        if not path.exists():
            raise self.error(key, f"= {value!r} does not exist (relative to {self.file.parent})")
        return path

    def tables(self, key):
        value = self._get(key, [], False)
        if not isinstance(value, list):
            raise self.error(key, "must be an array of tables ([[...]])")
        return value


# Geometry -----------------------------------------------------------------------------------------

_CUP_KEYS = ("height", "radius_top", "radius_bottom", "wall", "base", "fillet", "segments")


def _geometry(value, file: Path):
    if isinstance(value, str):
        value = {"type": value} if value in ("sphere", "cup") else {"type": "obj", "file": value}
    t = Table(
        value, file, "scene.geometry", ("type", "file", "center", "radius", "handle", *_CUP_KEYS)
    )
    kind = t.string("type", choices=("sphere", "cup", "obj"))
    if kind == "sphere":
        return Sphere(t.vec("center", default=(0.0, 0.0, 0.0)), t.positive("radius", 1.0))
    if kind == "cup":
        defaults = CupShape()
        values = {k: t.positive(k, getattr(defaults, k)) for k in _CUP_KEYS if k != "segments"}
        values["segments"] = t.number("segments", int, defaults.segments, 8)
        try:
            return Cup(CupShape(**values, handle=t.boolean("handle", True)))
        except ValueError as err:
            raise CaptureError(f"{file}: scene.geometry: {err}") from None
    path = t.path("file")
    if path.suffix.lower() != ".obj":
        raise t.error("file", f"= {path.name!r}: only OBJ meshes are read")
    check_obj_has_uvs(path)
    return ObjFile(path)


# Cameras ------------------------------------------------------------------------------------------


def _camera(item, file: Path, i: int) -> Camera:
    c = Table(
        item,
        file,
        f"scene.cameras[{i}]",
        (
            "type",
            "origin",
            "target",
            "up",
            "fov_x_deg",
            "width",
            "height",
            "aperture_radius",
            "focus_distance",
            "ortho_width",
        ),
    )
    kind = c.string("type", "perspective", ("perspective", "orthographic"))
    origin, target = c.vec("origin"), c.vec("target")
    if np.linalg.norm(np.subtract(target, origin)) == 0:
        raise c.error("target", "equals origin: the camera has no viewing direction")
    camera = Camera(
        origin=origin,
        target=target,
        up=c.vec("up", default=(0.0, 0.0, 1.0)),
        fov_x_deg=c.number("fov_x_deg", required=kind == "perspective", default=40.0),
        width=c.number("width", int, minimum=1),
        height=c.number("height", int, minimum=1),
        kind=kind,
        aperture_radius=c.number("aperture_radius", default=0.0, minimum=0.0),
        focus_distance=c.positive("focus_distance", required=False),
        ortho_width=c.positive("ortho_width", required=kind == "orthographic", default=1.0),
    )
    if kind == "perspective" and not 0 < camera.fov_x_deg < 180:
        raise c.error("fov_x_deg", f"= {camera.fov_x_deg} must be in (0, 180)")
    if kind == "orthographic" and (c.has("fov_x_deg") or c.has("aperture_radius")):
        raise c.error("type", "= 'orthographic' takes ortho_width, not fov_x_deg/aperture_radius")
    return camera


# Lights -------------------------------------------------------------------------------------------


def _colour(t: Table) -> np.ndarray:
    """`color` (RGB) or `temperature` (kelvin, luminance 1), default white."""
    if t.has("color") and t.has("temperature"):
        raise t.error("color", "and temperature both given; give one")
    if t.has("temperature"):
        try:
            return np.array(blackbody_rgb(t.positive("temperature")))
        except ValueError as err:
            raise t.error("temperature", f"{err}") from None
    colour = np.array(t.vec("color", default=(1.0, 1.0, 1.0)))
    if np.any(colour < 0):
        raise t.error("color", "must not be negative")
    return colour


def _amount(t: Table, direct: str, per_watt: float | None) -> tuple[float, float, float]:
    """A light's RGB amount: `direct` given as RGB (or a number times the colour), or `power`
    (watts) times the colour times `per_watt`."""
    given = [k for k in (direct, "power") if t.has(k) and (k == direct or per_watt is not None)]
    if len(given) != 1:
        options = f"{direct} or power" if per_watt is not None else direct
        raise CaptureError(f"{t.file}: [{t.where}] needs exactly one of {options}")
    if given[0] == "power":
        value = t.positive("power") * per_watt * _colour(t)
    elif isinstance(t.data[direct], int | float):
        value = t.number(direct, minimum=0.0) * _colour(t)
    else:
        if t.has("color") or t.has("temperature"):
            raise t.error(direct, "is RGB already; drop color/temperature or give a number")
        value = np.array(t.vec(direct))
    if np.any(value < 0) or not np.any(value > 0):
        raise t.error(given[0], "must be positive")
    return tuple(float(x) for x in value)


def _frame(t: Table):
    """(u, v, n) of a rectangle light: given, or facing `target` (with `up`)."""
    if t.has("target"):
        n = np.subtract(t.vec("target"), t.vec("center"))
        if np.linalg.norm(n) == 0:
            raise t.error("target", "equals center")
        n /= np.linalg.norm(n)
        up = np.array(t.vec("up", default=(0.0, 0.0, 1.0)))
        u = np.cross(up, n)
        if np.linalg.norm(u) < 1e-6:
            u = np.cross([1.0, 0.0, 0.0], n)
        u /= np.linalg.norm(u)
        v = np.cross(u, n)  # so that n = -(u x v), the peers' convention
        return tuple(u), tuple(v), tuple(n)
    u, v, n = (np.array(t.vec(k)) for k in ("u_axis", "v_axis", "emit_direction"))
    for key, vec in (("u_axis", u), ("v_axis", v), ("emit_direction", n)):
        if abs(np.linalg.norm(vec) - 1) > 1e-3:
            raise t.error(key, "must be a unit vector")
    if abs(u @ v) > 1e-3 or abs(u @ n) > 1e-3 or abs(v @ n) > 1e-3:
        raise CaptureError(
            f"{t.file}: [{t.where}] u_axis, v_axis, emit_direction must be orthogonal"
        )
    return tuple(u), tuple(v), tuple(n)


def _light(item, file: Path, i: int):
    where = f"scene.lights[{i}]"
    kind = item.get("type", "rectangle") if isinstance(item, dict) else None
    colour_keys = ("color", "temperature")
    if kind == "rectangle":
        t = Table(
            item,
            file,
            where,
            (
                "type",
                "center",
                "target",
                "up",
                "u_axis",
                "v_axis",
                "emit_direction",
                "size",
                "radiance",
                "power",
                *colour_keys,
            ),
        )
        size = t.vec("size", 2)
        if min(size) <= 0:
            raise t.error("size", "must be positive")
        u, v, n = _frame(t)
        area = size[0] * size[1]
        radiance = _amount(t, "radiance", 1.0 / (math.pi * area))
        return RectLight(t.vec("center"), u, v, size, n, radiance)
    if kind == "point":
        t = Table(item, file, where, ("type", "position", "intensity", "power", *colour_keys))
        return PointLight(t.vec("position"), _amount(t, "intensity", 1.0 / (4 * math.pi)))
    if kind == "directional":
        t = Table(item, file, where, ("type", "direction", "irradiance", *colour_keys))
        direction = np.array(t.vec("direction"))
        if np.linalg.norm(direction) == 0:
            raise t.error("direction", "must not be zero")
        return DirectionalLight(
            tuple(direction / np.linalg.norm(direction)), _amount(t, "irradiance", None)
        )
    raise CaptureError(f"{file}: {where}.type = {kind!r}; choose rectangle, point or directional")


def _environment(value, file: Path):
    if not isinstance(value, dict):
        t = Table({"radiance": value}, file, "scene", ("radiance",))
        return t.vec("radiance")
    t = Table(value, file, "scene.environment", ("type", "radiance", "file", "scale"))
    if t.string("type", choices=("constant", "envmap")) == "constant":
        return t.vec("radiance")
    return EnvMap(t.path("file"), t.positive("scale", 1.0))


def parse_scene(data: dict, file: Path) -> Scene:
    """A `Scene` from the `[scene]` table of `file` (relative paths resolve against its folder)."""
    t = Table(
        data,
        file,
        "scene",
        ("geometry", "cameras", "lights", "environment", "integrator", "max_depth"),
    )
    geometry = _geometry(t._get("geometry", None, True), file)
    cameras = tuple(_camera(item, file, i) for i, item in enumerate(t.tables("cameras")))
    if not cameras:
        raise CaptureError(f"{file}: [scene] needs at least one [[scene.cameras]]")
    lights = tuple(_light(item, file, i) for i, item in enumerate(t.tables("lights")))
    environment = _environment(t._get("environment", (0.0, 0.0, 0.0), False), file)
    if not lights and not isinstance(environment, EnvMap) and not any(environment):
        raise CaptureError(f"{file}: the scene has no light: add [[scene.lights]] or environment")
    return Scene(
        geometry=geometry,
        cameras=cameras,
        lights=lights,
        environment=environment,
        integrator=t.string("integrator", "prb", INTEGRATORS),
        max_depth=t.number("max_depth", int, default=8, minimum=1),
    )


def scene_to_table(scene: Scene, folder: Path | None = None) -> dict:
    """The `[scene]` table of `scene` without cameras (a capture's come from its views). File
    paths are written relative to `folder`."""

    def rel(path: Path) -> str:
        return str(Path(path).relative_to(folder)) if folder else str(path)

    g = scene.geometry
    if isinstance(g, Sphere):
        geometry = {"type": "sphere", "center": list(g.center), "radius": g.radius}
    elif isinstance(g, Cup):
        geometry = {
            "type": "cup",
            "handle": g.shape.handle,
            **{k: getattr(g.shape, k) for k in _CUP_KEYS},
        }
    else:
        geometry = {"type": "obj", "file": rel(g.path)}
    lights = []
    for light in scene.lights:
        if isinstance(light, RectLight):
            lights.append(
                {
                    "type": "rectangle",
                    "center": list(light.center),
                    "u_axis": list(light.u_axis),
                    "v_axis": list(light.v_axis),
                    "emit_direction": list(light.emit_direction),
                    "size": list(light.size),
                    "radiance": list(light.radiance),
                }
            )
        elif isinstance(light, PointLight):
            lights.append(
                {
                    "type": "point",
                    "position": list(light.position),
                    "intensity": list(light.intensity),
                }
            )
        else:
            lights.append(
                {
                    "type": "directional",
                    "direction": list(light.direction),
                    "irradiance": list(light.irradiance),
                }
            )
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
        if camera.aperture_radius > 0:
            out["aperture_radius"] = camera.aperture_radius
            if camera.focus_distance:
                out["focus_distance"] = camera.focus_distance
    return out
