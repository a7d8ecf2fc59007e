"""Photo sets: the capture manifest (TOML), loading it into linear arrays, writing capture folders.

```toml
[capture]
encoding = "linear"          # linear | srgb | raw (camera RAW, developed by captures.raw)
white_balance = "camera"     # RAW only: camera (as shot) | none | [r, g, b] multipliers
downscale = 1                # integer area-averaging factor for fitting (cameras follow)
dilate = 2                   # saturated pixels invalidate this many neighbouring pixels

[scene]                      # as in render configs, but the cameras come from the views
geometry = "sphere"
environment = [0.06, 0.06, 0.07]

[[views]]
image = "view_00.exr"        # relative to this file, never outside its folder
mask = "mask_00.png"         # optional object mask
exposure_ev = 0.0            # or gain = 1.0: the image is divided by 2^ev (or gain)
[views.camera]               # a camera table; width and height default to the image's
origin = [0, -5, 1.2]
target = [0, 0, 0]
fov_x_deg = 39.6

[truth]                      # synthetic captures only, used to score fits
"glaze.roughness" = 0.0625
```
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from .errors import CaptureError
from .images import ENCODINGS, read_linear, read_mask
from .raw import develop, read_raw
from .scene import Camera, Scene, bounding_sphere, sees
from .schema import Table, load_toml, parse_scene
from .weights import downscale, validity

log = logging.getLogger(__name__)


@dataclass
class View:
    """One photograph: linear RGB (H, W, 3) float32, validity weight (H, W) float32, its camera,
    the gain it was divided by, (for photometric-stereo sets) its own lights, and the object's
    pixels when known: `mask` marks pixels whose coverage exceeds `mask_coverage`."""

    name: str
    image: np.ndarray
    weight: np.ndarray
    camera: Camera
    gain: float = 1.0
    lights: tuple | None = None
    mask: np.ndarray | None = None
    mask_coverage: float = 0.5


@dataclass
class Capture:
    """A scene (its cameras are the views'), the views, and the truth of a synthetic capture."""

    scene: Scene
    views: list[View]
    truth: dict[str, float | list[float]] = field(default_factory=dict)
    path: Path | None = None
    warnings: list[str] = field(default_factory=list)

    def scene_of(self, view: int) -> Scene:
        """The scene as seen by one view (its camera; its own lights if it has them)."""
        v = self.views[view]
        lights = v.lights if v.lights is not None else self.scene.lights
        return replace(self.scene, cameras=(v.camera,), lights=lights)

    def downscaled(self, factor: int) -> Capture:
        """A copy area-averaged by an integer `factor` (weights become each block's valid share,
        masks keep blocks more than half covered); the cameras follow (same field of view, fewer
        pixels), so a render of the copy is the area average of a render of the original."""
        if factor == 1:
            return self
        views, cameras = [], []
        for view in self.views:
            try:
                image, weight = downscale(view.image, view.weight, factor)
            except CaptureError as error:
                raise CaptureError(f"{self.path}: view {view.name}: {error}") from None
            mask = view.mask
            if mask is not None:
                h, w = mask.shape
                block = downscale(mask[..., None].astype(np.float32), np.ones((h, w)), factor)[0]
                mask = block[..., 0] > 0.5
            camera = replace(
                view.camera, width=view.camera.width // factor, height=view.camera.height // factor
            )
            views.append(replace(view, image=image, weight=weight, camera=camera, mask=mask))
            cameras.append(camera)
        scene = replace(self.scene, cameras=tuple(cameras[: len(self.scene.cameras)]))
        return replace(self, scene=scene, views=views)


def _inside(folder: Path, value, where: str, file: Path) -> Path:
    if not isinstance(value, str):
        raise CaptureError(f"{file}: {where} must be a file name")
    path = (folder / value).resolve()
    if not path.is_relative_to(folder.resolve()):
        raise CaptureError(
            f"{file}: {where} = {value!r} points outside the capture folder; "
            "copy the file into the folder"
        )
    if not path.exists():
        raise CaptureError(f"{file}: {where} = {value!r} does not exist")
    return path


def _gain(t: Table) -> float:
    if t.has("exposure_ev") and t.has("gain"):
        raise t.error("gain", "and exposure_ev both given; give one")
    if t.has("gain"):
        gain = t.number("gain")
        if gain <= 0:
            raise t.error("gain", f"= {gain} must be > 0 (a relative exposure)")
        return gain
    return 2.0 ** t.number("exposure_ev", default=0.0)


def load_capture(path: str | Path) -> Capture:
    """Read a capture manifest and its images into linear arrays with validity weights."""
    path = Path(path)
    if path.is_dir():
        path = path / "capture.toml"
    doc = load_toml(path, "capture manifest")
    unknown = sorted(set(doc) - {"capture", "scene", "views", "truth"})
    if unknown:
        raise CaptureError(
            f"{path}: unknown table(s) {', '.join(unknown)}; known: capture, scene, views, truth"
        )
    settings = Table(
        doc.get("capture", {}),
        path,
        "capture",
        ("encoding", "white_balance", "downscale", "dilate"),
    )
    encoding = settings.string("encoding", "linear", ENCODINGS)
    wb = settings._get("white_balance", "camera", False)
    if isinstance(wb, list):
        wb = np.array(settings.vec("white_balance"))
        if np.any(wb <= 0):
            raise settings.error("white_balance", "multipliers must be > 0")
    elif wb not in ("camera", "none"):
        raise settings.error("white_balance", f"= {wb!r}; use camera, none or [r, g, b]")
    if encoding != "raw" and settings.has("white_balance"):
        raise settings.error("white_balance", 'applies to encoding = "raw" only')
    factor = settings.number("downscale", int, 1, 1)
    dilate = settings.number("dilate", int, 2, 0)

    views_doc = doc.get("views", [])
    if not isinstance(views_doc, list) or not views_doc:
        raise CaptureError(f"{path}: the photo set is empty: add [[views]] with an image each")
    folder = path.parent
    views, warnings, cameras = [], [], []
    for i, item in enumerate(views_doc):
        t = Table(item, path, f"views[{i}]", ("image", "mask", "exposure_ev", "gain", "camera"))
        image_path = _inside(folder, t._get("image", None, True), f"views[{i}].image", path)
        if encoding == "raw":
            raw = read_raw(image_path)
            image, saturated = develop(raw, wb), raw.saturated
        else:
            image, saturated, warned = read_linear(image_path, encoding)
            warnings += warned
        h, w = image.shape[:2]
        if not np.all(np.isfinite(image)):
            bad = int(np.sum(~np.all(np.isfinite(image), axis=-1)))
            warnings.append(f"{image_path}: {bad} NaN/Inf pixels get weight 0")
        mask = None
        if t.has("mask"):
            mask_path = _inside(folder, t.data["mask"], f"views[{i}].mask", path)
            mask = read_mask(mask_path)
            if mask.shape != (h, w):
                raise CaptureError(
                    f"{path}: views[{i}].mask is {mask.shape[1]}x{mask.shape[0]} but the image "
                    f"is {w}x{h}; masks must match their image"
                )
        gain = _gain(t)
        image, weight = validity(image / gain, saturated, mask, dilate)
        camera = dict(t._get("camera", None, True))
        camera.setdefault("width", w)
        camera.setdefault("height", h)
        if (camera["width"], camera["height"]) != (w, h):
            raise CaptureError(
                f"{path}: views[{i}].camera is {camera['width']}x{camera['height']} but "
                f"{image_path.name} is {w}x{h}"
            )
        cameras.append(camera)
        views.append(View(image_path.stem, image, weight, None, gain, mask=mask))  # camera below
        if weight.mean() == 0:
            raise CaptureError(f"{path}: views[{i}] ({image_path.name}) has no valid pixel")

    scene_table = dict(doc.get("scene", {}))
    if "cameras" in scene_table:
        raise CaptureError(f"{path}: [scene] takes no cameras in a capture: each view has one")
    scene = parse_scene({**scene_table, "cameras": cameras}, path)
    for view, camera in zip(views, scene.cameras, strict=True):
        view.camera = camera
    center, radius = bounding_sphere(scene.geometry)
    for i, camera in enumerate(scene.cameras):
        if not sees(camera, center, radius):
            raise CaptureError(
                f"{path}: views[{i}].camera does not see the object (centre {center.round(3)}, "
                f"radius {radius:.3g}): check its origin, target and field of view"
            )
    truth = _truth(doc.get("truth", {}), path)
    for message in warnings:
        log.warning(message)
    return Capture(scene, views, truth, path, warnings).downscaled(factor)


def _truth(table, path: Path) -> dict:
    if not isinstance(table, dict):
        raise CaptureError(f"{path}: [truth] must be a table of parameter values")
    out = {}
    for key, value in table.items():
        ok = isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)
        ok |= isinstance(value, list) and all(isinstance(x, int | float) for x in value)
        if not ok:
            raise CaptureError(f"{path}: truth.{key} = {value!r} must be a number or numbers")
        out[key] = value
    return out


# Writing -----------------------------------------------------------------------------------------


def _toml_value(value) -> str:
    if isinstance(value, str):
        return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int | float):
        return repr(float(value)) if isinstance(value, float) else str(value)
    if isinstance(value, list | tuple):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    raise TypeError(f"cannot write {value!r} to TOML")


def manifest_text(capture_table: dict, scene_table: dict, views: list[dict], truth: dict) -> str:
    """The TOML text of a manifest (flat values, nested tables one level deep)."""
    lines = ["# layerfit capture manifest", "", "[capture]"]
    lines += [f"{k} = {_toml_value(v)}" for k, v in capture_table.items()]
    lines += ["", "[scene]"]
    nested = {
        k: v for k, v in scene_table.items() if isinstance(v, list) and v and isinstance(v[0], dict)
    }
    lines += [
        f"{k} = {_toml_value(v)}"
        for k, v in scene_table.items()
        if k not in nested and not isinstance(v, dict)
    ]
    for k, v in scene_table.items():
        if isinstance(v, dict):
            lines += ["", f"[scene.{k}]"] + [f"{kk} = {_toml_value(vv)}" for kk, vv in v.items()]
    for k, items in nested.items():
        for item in items:
            lines += ["", f"[[scene.{k}]]"] + [
                f"{kk} = {_toml_value(vv)}" for kk, vv in item.items()
            ]
    for view in views:
        lines += ["", "[[views]]"]
        lines += [f"{k} = {_toml_value(v)}" for k, v in view.items() if k != "camera"]
        lines += ["[views.camera]"] + [f"{k} = {_toml_value(v)}" for k, v in view["camera"].items()]
    if truth:
        lines += ["", "[truth]"] + [f'"{k}" = {_toml_value(v)}' for k, v in truth.items()]
    return "\n".join(lines) + "\n"
