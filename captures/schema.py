"""Read the `[scene]` table of a TOML config or capture manifest into a `Scene`, strictly:
unknown or misspelt keys, wrong types and missing fields are errors naming the file and the key."""

from __future__ import annotations

from pathlib import Path

from .peer import CaptureError
from .scene import Camera, RectLight, Scene


class _Table:
    """A TOML table that knows where it came from and which keys it may hold."""

    def __init__(self, data: dict, file: Path, where: str, known: tuple[str, ...]):
        if not isinstance(data, dict):
            raise CaptureError(f"{file}: [{where}] must be a table")
        unknown = sorted(set(data) - set(known))
        if unknown:  # before missing keys: a misspelt key is the likelier mistake
            raise CaptureError(
                f"{file}: unknown key(s) {', '.join(unknown)} in [{where}]; "
                f"known: {', '.join(known)}"
            )
        self.data, self.file, self.where = data, file, where

    def _get(self, key, default, required):
        if key not in self.data:
            if required:
                raise CaptureError(f"{self.file}: [{self.where}] needs {key!r}")
            return default
        return self.data[key]

    def vec(self, key, n=3, default=None):
        value = self._get(key, default, default is None)
        try:
            out = tuple(float(x) for x in value)
        except (TypeError, ValueError):
            out = ()
        if len(out) != n:
            raise CaptureError(
                f"{self.file}: {self.where}.{key} must be {n} numbers, got {value!r}"
            )
        return out

    def number(self, key, kind=float, default=None, minimum=None):
        value = self._get(key, default, default is None)
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise CaptureError(f"{self.file}: {self.where}.{key} must be a number, got {value!r}")
        if minimum is not None and value < minimum:
            raise CaptureError(f"{self.file}: {self.where}.{key} = {value} must be >= {minimum}")
        return kind(value)

    def string(self, key, default=None):
        value = self._get(key, default, default is None)
        if not isinstance(value, str):
            raise CaptureError(f"{self.file}: {self.where}.{key} must be a string, got {value!r}")
        return value

    def list(self, key):
        value = self._get(key, [], False)
        if not isinstance(value, list):
            raise CaptureError(f"{self.file}: {self.where}.{key} must be an array of tables")
        return value


def parse_scene(data: dict, file: Path) -> Scene:
    """A `Scene` from the `[scene]` table of `file` (relative paths resolve against its folder)."""
    t = _Table(data, file, "scene", ("geometry", "cameras", "lights", "environment", "max_depth"))
    geometry = t.string("geometry")
    if geometry != "sphere":
        path = (file.parent / geometry).resolve()
        if not path.exists():
            raise CaptureError(f"{file}: scene.geometry {geometry!r} does not exist")
        geometry = path
    cameras = []
    for i, item in enumerate(t.list("cameras")):
        c = _Table(
            item,
            file,
            f"scene.cameras[{i}]",
            ("origin", "target", "up", "fov_x_deg", "width", "height"),
        )
        cameras.append(
            Camera(
                origin=c.vec("origin"),
                target=c.vec("target"),
                up=c.vec("up", default=(0.0, 0.0, 1.0)),
                fov_x_deg=c.number("fov_x_deg"),
                width=c.number("width", int, minimum=1),
                height=c.number("height", int, minimum=1),
            )
        )
    if not cameras:
        raise CaptureError(f"{file}: [scene] needs at least one [[scene.cameras]]")
    lights = []
    for i, item in enumerate(t.list("lights")):
        lt = _Table(
            item,
            file,
            f"scene.lights[{i}]",
            ("type", "center", "u_axis", "v_axis", "size", "emit_direction", "radiance"),
        )
        kind = lt.string("type", "rectangle")
        if kind != "rectangle":
            raise CaptureError(f"{file}: scene.lights[{i}].type = {kind!r}; known: rectangle")
        lights.append(
            RectLight(
                center=lt.vec("center"),
                u_axis=lt.vec("u_axis"),
                v_axis=lt.vec("v_axis"),
                size=lt.vec("size", 2),
                emit_direction=lt.vec("emit_direction"),
                radiance=lt.vec("radiance"),
            )
        )
    scene = Scene(
        geometry=geometry,
        cameras=tuple(cameras),
        lights=tuple(lights),
        environment=t.vec("environment", default=(0.0, 0.0, 0.0)),
        max_depth=t.number("max_depth", int, default=8, minimum=1),
    )
    return scene
