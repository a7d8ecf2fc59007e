"""Import a peer renderer's target (../shared/data/peer-cycles/*/scene.json)."""

from __future__ import annotations

import json
from pathlib import Path

from .errors import CaptureError
from .scene import Camera, ObjFile, RectLight, Scene


def _vec(value, where: str, n: int = 3) -> tuple[float, ...]:
    try:
        out = tuple(float(x) for x in value)
    except (TypeError, ValueError):
        raise CaptureError(f"{where}: expected {n} numbers, got {value!r}") from None
    if len(out) != n:
        raise CaptureError(f"{where}: expected {n} numbers, got {len(out)}")
    return out


def load_peer_scene(path: str | Path) -> Scene:
    """Read a peer `scene.json`: cameras, rectangle lights, constant environment, mesh.

    The returned scene's `meta` keeps the peer's `material` table and each view's image path.
    """
    path = Path(path)
    try:
        doc = json.loads(path.read_text())
    except FileNotFoundError:
        raise CaptureError(f"{path}: no such file") from None
    except json.JSONDecodeError as err:
        raise CaptureError(f"{path}: not valid JSON ({err})") from None

    def field(table: dict, key: str, where: str):
        if key not in table:
            raise CaptureError(f"{path}: {where} has no field {key!r}")
        return table[key]

    cameras, images = [], []
    for i, view in enumerate(field(doc, "views", "the file")):
        where = f"{path}: views[{i}]"
        cameras.append(
            Camera(
                origin=_vec(field(view, "origin", f"views[{i}]"), f"{where}.origin"),
                target=_vec(field(view, "target", f"views[{i}]"), f"{where}.target"),
                up=_vec(field(view, "up", f"views[{i}]"), f"{where}.up"),
                fov_x_deg=float(field(view, "fov_x_deg", f"views[{i}]")),
                width=int(field(view, "width", f"views[{i}]")),
                height=int(field(view, "height", f"views[{i}]")),
            )
        )
        images.append(path.parent / field(view, "image", f"views[{i}]"))
    lights = []
    for i, light in enumerate(doc.get("lights", [])):
        where = f"{path}: lights[{i}]"
        if light.get("type") != "rectangle":
            raise CaptureError(f"{where}.type = {light.get('type')!r}; only 'rectangle' is known")
        lights.append(
            RectLight(
                center=_vec(field(light, "center", f"lights[{i}]"), f"{where}.center"),
                u_axis=_vec(field(light, "u_axis", f"lights[{i}]"), f"{where}.u_axis"),
                v_axis=_vec(field(light, "v_axis", f"lights[{i}]"), f"{where}.v_axis"),
                size=_vec(field(light, "size", f"lights[{i}]"), f"{where}.size", 2),
                emit_direction=_vec(
                    field(light, "emit_direction", f"lights[{i}]"), f"{where}.emit_direction"
                ),
                radiance=_vec(
                    field(light, "radiance_rgb", f"lights[{i}]"), f"{where}.radiance_rgb"
                ),
            )
        )
    mesh = path.parent / field(doc, "mesh", "the file")
    if not mesh.exists():
        raise CaptureError(f"{path}: mesh {mesh.name!r} does not exist next to it")
    return Scene(
        geometry=ObjFile(mesh),
        cameras=tuple(cameras),
        lights=tuple(lights),
        environment=_vec(doc.get("environment_radiance_rgb", (0, 0, 0)), f"{path}: environment"),
        meta={"material": doc.get("material", {}), "images": images},
    )
