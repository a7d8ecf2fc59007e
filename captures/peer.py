"""Import a peer renderer's target (../shared/data/peer-cycles/*/scene.json)."""

from __future__ import annotations

import json
import re
from dataclasses import replace
from pathlib import Path

import numpy as np

from .errors import CaptureError
from .scene import Scene
from .schema import parse_scene

#: The fields a peer `scene.json` has (`../shared/data/peer-cycles`), the file's, a view's and a
#: light's: others are warned as ignored.
PEER_FIELDS = (
    "generator",
    "axes",
    "mesh",
    "shape",
    "views",
    "lights",
    "environment_radiance_rgb",
    "material",
    "notes",
)
VIEW_FIELDS = ("image", "origin", "target", "up", "fov_x_deg", "width", "height")
VIEW_FIELDS += ("blender_matrix_world",)
LIGHT_FIELDS = ("type", "center", "emit_direction", "u_axis", "v_axis", "size", "radiance_rgb")
LIGHT_FIELDS += ("one_sided",)


#: Fields another exporter may write that change the picture, by table (the file, a view, a
#: light), with the values that do not (a perspective camera, no lens shift, a rectangle light
#: that emits to its hemisphere, no map): any other value is refused (they were warned as
#: ignored, and the fit went ahead).
PICTURE_FIELDS = {
    "the file": {"environment_map": lambda v: not v},
    "views": {
        "type": lambda v: str(v).lower() in ("persp", "perspective"),
        "shift_x": lambda v: v == 0,
        "shift_y": lambda v: v == 0,
    },
    "lights": {
        "shape": lambda v: str(v).lower() in ("rectangle", "square"),
        "spread_deg": lambda v: v == 180,
    },
}


def load_peer_scene(path: str | Path) -> Scene:
    """Read a peer `scene.json`: cameras, rectangle lights, constant environment, mesh.

    Its values pass the checks of a capture manifest's `[scene]` (`parse_scene`: numbers and
    their ranges, a camera's field of view, up and target, a light's size and radiance, a camera
    inside the object), its errors named by the JSON's fields. The returned scene's `meta` keeps
    the peer's `material` table and each view's image path.
    """
    path = Path(path)
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        raise CaptureError(f"{path}: no such file") from None
    if raw[:2] in (b"\xff\xfe", b"\xfe\xff") or (len(raw) > 1 and b"\x00" in raw[:4]):
        raise CaptureError(  # PowerShell's default ("Unicode"): a decode error said nothing
            f"{path}: is UTF-16 text; save it as UTF-8 (e.g. Out-File -Encoding utf8)"
        )
    try:
        doc = json.loads(raw.decode("utf-8-sig"))
    except UnicodeDecodeError as err:
        raise CaptureError(f"{path}: is not UTF-8 text ({err.reason}); save it as UTF-8") from None
    except json.JSONDecodeError as err:
        raise CaptureError(f"{path}: not valid JSON ({err})") from None

    def field(table, key: str, where: str):
        if not isinstance(table, dict):
            raise CaptureError(f"{path}: {where} is {table!r}, not an object")
        if key not in table:
            raise CaptureError(f"{path}: {where} has no field {key!r}")
        return table[key]

    warnings = []

    def unknown(table, known: tuple, where: str) -> None:  # another exporter's extra fields
        changing = PICTURE_FIELDS[where.split("[")[0]]  # ones that change the picture: refused
        for key, harmless in changing.items():
            if isinstance(table, dict) and key in table and not harmless(table[key]):
                named = key if where == "the file" else f"{where}.{key}"
                raise CaptureError(
                    f"{path}: {named} = {json.dumps(table[key])} changes the picture and "
                    "this version does not read it; render without it, or describe the scene "
                    "as a capture.toml (orthographic cameras, principal points, point lights "
                    "and environment maps are there)"
                )
        extra = sorted(k for k in table if k not in known) if isinstance(table, dict) else []
        if extra:
            warnings.append(
                f"{path}: {where} has field(s) {', '.join(map(repr, extra))} this version does "
                f"not read: ignored (it reads {', '.join(known)})"
            )

    unknown(doc, PEER_FIELDS, "the file")
    views = field(doc, "views", "the file")
    if not isinstance(views, list) or not views:
        raise CaptureError(f"{path}: views must be a list of one or more views")
    keys = ("origin", "target", "up", "fov_x_deg", "width", "height")
    for i, view in enumerate(views):  # another exporter's vertical field of view
        if isinstance(view, dict) and "fov_x_deg" not in view and "fov_y_deg" in view:
            raise CaptureError(
                f"{path}: views[{i}] has fov_y_deg but no fov_x_deg; give the horizontal field "
                "of view, fov_x = 2 atan(tan(fov_y / 2) width / height)"
            )
    cameras = [{k: field(view, k, f"views[{i}]") for k in keys} for i, view in enumerate(views)]
    for camera in cameras:  # a script's computed size (160.0) is a whole number of pixels
        for k in ("width", "height"):
            if isinstance(camera[k], float) and camera[k].is_integer():
                camera[k] = int(camera[k])
    for i, view in enumerate(views):
        problem = _matrix_problem(view.get("blender_matrix_world"), cameras[i])
        if problem is not None:
            raise CaptureError(f"{path}: views[{i}].blender_matrix_world {problem}")
    images = []
    for i, view in enumerate(views):
        name = field(view, "image", f"views[{i}]")
        if not isinstance(name, str) or not name.strip():  # null or a number named "peer/None"
            raise CaptureError(
                f"{path}: views[{i}].image is {json.dumps(name)}; give the view's image file name"
            )
        images.append(path.parent / _forward(name))
    for i, view in enumerate(views):
        unknown(view, VIEW_FIELDS, f"views[{i}]")
    lights = doc.get("lights", [])
    if not isinstance(lights, list):
        raise CaptureError(f"{path}: lights must be a list")
    keys = ("center", "u_axis", "v_axis", "size", "emit_direction")
    tables = []
    for i, light in enumerate(lights):
        kind = field(light, "type", f"lights[{i}]")
        if kind != "rectangle":
            raise CaptureError(
                f"{path}: lights[{i}].type = {kind!r}; a peer scene's lights are rectangles: "
                "describe the scene as a capture.toml for point and directional lights"
            )
        unknown(light, LIGHT_FIELDS, f"lights[{i}]")
        if light.get("one_sided", True) is not True:
            raise CaptureError(
                f"{path}: lights[{i}].one_sided = {light['one_sided']!r}: layerfit's rectangle "
                "lights emit from one side (emit_direction), as Cycles' area lights; give two "
                "lights back to back for a two-sided one"
            )
        table = {k: field(light, k, f"lights[{i}]") for k in keys}
        radiance = field(light, "radiance_rgb", f"lights[{i}]")
        tables.append({"type": "rectangle", **table, "radiance": radiance})
    name = _forward(str(field(doc, "mesh", "the file")))
    if not (path.parent / name).is_file():
        raise CaptureError(f"{path}: mesh {name!r} does not exist next to it")
    if "environment_radiance_rgb" not in doc:
        warnings.append(
            f"{path}: no environment_radiance_rgb: the environment is taken as black (a view's "
            "background that is not black then fits as the object's light)"
        )
    environment = doc.get("environment_radiance_rgb", [0.0, 0.0, 0.0])
    if not isinstance(environment, list) or len(environment) != 3:
        raise CaptureError(
            f"{path}: environment_radiance_rgb: expected 3 numbers, got {environment!r}"
        )
    table = {
        "geometry": {"type": "obj", "file": name},  # relative to the scene.json
        "cameras": cameras,
        "lights": tables,
        "environment": environment,
    }
    try:
        scene = parse_scene(table, path, _peer_names)
    except CaptureError as err:
        raise CaptureError(_peer_names(str(err))) from None
    meta = {"material": doc.get("material", {}), "images": images, "warnings": warnings}
    return replace(scene, meta=meta)


#: How far a view's `blender_matrix_world` may be from its origin (a fraction of the distance to
#: its target) and its axes from its look-at frame (degrees) before they disagree: the exporter
#: writes both from one camera, in float32.
MATRIX_POSITION, MATRIX_DEGREES = 1e-3, 0.1


def _matrix_problem(matrix, camera: dict) -> str | None:
    """Why a view's Blender camera matrix (world from camera: its columns the camera's x, y (up)
    and z (backward) axes and its position) disagrees with its origin, target and up (None
    where it agrees or is absent, or where those are not numbers: the scene's checks name
    them). A matrix left from another camera was silent, and the look-at values were used."""
    if matrix is None:
        return None
    try:
        m = np.asarray(matrix, np.float64)
    except (TypeError, ValueError):
        m = None
    if m is None or m.shape != (4, 4) or not np.all(np.isfinite(m)):
        return f"= {json.dumps(matrix)[:80]}: expected a 4x4 matrix (rows of 4 numbers)"
    try:
        origin, target, up = (np.asarray(camera[k], np.float64) for k in ("origin", "target", "up"))
    except (TypeError, ValueError):
        return None
    if not all(v.shape == (3,) and np.all(np.isfinite(v)) for v in (origin, target, up)):
        return None
    forward = target - origin
    upright = up - (up @ forward) / max(forward @ forward, 1e-300) * forward  # look-at's up
    found = []
    if np.linalg.norm(m[:3, 3] - origin) > MATRIX_POSITION * np.linalg.norm(forward):
        shown = ", ".join(f"{x:.4g}" for x in m[:3, 3])
        found.append(f"puts the camera at [{shown}], not at origin")
    look, roll = _degrees(-m[:3, 2], forward), _degrees(m[:3, 1], upright)
    if look > MATRIX_DEGREES:
        found.append(f"looks {look:.2f} degrees away from target")
    elif roll > MATRIX_DEGREES:
        found.append(f"turns the camera {roll:.2f} degrees about its view from up")
    if not found:
        return None
    return (
        f"{' and '.join(found)}: the two describe different cameras; export them from one "
        "camera again, or drop blender_matrix_world (origin, target and up are read)"
    )


def _degrees(a: np.ndarray, b: np.ndarray) -> float:
    """The angle between two vectors (0 where either is zero: the scene's checks name it)."""
    norms = np.linalg.norm(a) * np.linalg.norm(b)
    if not norms > 0:
        return 0.0
    return float(np.degrees(np.arccos(np.clip(a @ b / norms, -1.0, 1.0))))


def _peer_names(message: str) -> str:
    """A `[scene]` error in the peer file's own field names."""
    message = re.sub(r"scene\.lights\[(\d+)\]\.radiance\b", r"lights[\1].radiance_rgb", message)
    for ours, theirs in (
        ("scene.cameras[", "views["),
        ("scene.lights[", "lights["),
        ("scene.environment.radiance", "environment_radiance_rgb"),
        ("scene.environment", "environment_radiance_rgb"),
        ("scene.geometry.file", "mesh"),
        ("scene.geometry", "mesh"),
        ("add [[scene.lights]] or an environment", "add lights or environment_radiance_rgb"),
        (": scene: ", ": "),
    ):
        message = message.replace(ours, theirs)
    return message


def _forward(name: str) -> str:
    """A relative path written on Windows (`renders\\view_00.exr`) with forward slashes: a
    backslash is a character of a file name here, and the file was "not found"."""
    return name.replace("\\", "/") if "\\" in name and not Path(name).is_absolute() else name
