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
[truth_options]              # the options the truth's values mean something under
"glaze.diffuse" = "qualitative"
[truth_textures]             # true textures (files in the folder): fitted masks are scored
"glaze.mask.texture" = "truth_glaze.mask.texture.exr"
```
"""

from __future__ import annotations

import logging
import re
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import AfterValidator, Field, ValidationInfo, model_validator

from .errors import CaptureError
from .images import ENCODINGS, read_linear, read_mask
from .model import (
    ExistingPath,
    FieldError,
    FiniteFloat,
    NonNegativeInt,
    PositiveFloat,
    PositiveInt,
    PositiveVec3,
    StrictModel,
    by_shape,
    config_folder,
    expect_kind,
    parse_model,
)
from .raw import develop, read_raw
from .scene import Camera, Scene, bounding_sphere, sees
from .schema import load_toml, parse_scene
from .weights import downscale, downscaled_size, validity

log = logging.getLogger(__name__)

#: The fewest pixels a side of a view once area-averaged (a fit's phases check the same).
MIN_SIDE = 4

#: The largest exposure offset a view may declare, in EV (2^40: far beyond any camera).
MAX_EV = 40.0


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
    truth_options: dict[str, str] = field(default_factory=dict)
    """The options of the model the truth holds values of, by key (`glaze.diffuse = "eon"`: a
    peer's diffuse roughness is EON's): a fit whose material differs does not score them."""
    truth_textures: dict[str, Path] = field(default_factory=dict)
    """The true textures of a synthetic capture by key (a mask's painted texture), as files."""

    def scene_of(self, view: int) -> Scene:
        """The scene as seen by one view (its camera; its own lights if it has them)."""
        v = self.views[view]
        lights = v.lights if v.lights is not None else self.scene.lights
        return replace(self.scene, cameras=(v.camera,), lights=lights)

    def check_factor(self, factor: int, name: str) -> None:
        """Refuse an area-averaging `factor` (named `name` in the message: the field or option
        that gave it) that leaves a view under `MIN_SIDE` pixels a side."""
        for view in self.views:
            w, h = downscaled_size(view.camera.width, view.camera.height, factor)
            if min(w, h) < MIN_SIDE and factor == 1:
                raise CaptureError(
                    f"{self.path or name}: view {view.name} is {w}x{h}: at least {MIN_SIDE} "
                    "pixels a side; give larger photos"
                )
            if min(w, h) < MIN_SIDE:
                raise CaptureError(
                    f"{name} = {factor} leaves view {view.name} {w}x{h} (from "
                    f"{view.camera.width}x{view.camera.height}): at least {MIN_SIDE} pixels a "
                    "side; give a smaller factor"
                )

    def downscaled(self, factor: int) -> Capture:
        """A copy area-averaged by an integer `factor`, any image size (weights become each output
        pixel's valid share, masks keep pixels covered more than the view's `mask_coverage`; see
        `weights.downscale`); the cameras follow (same field of view, fewer pixels), so a render
        of the copy is the area average of a render of the original.

        An output pixel partly over a pixel left out of the weights for what a render there
        takes in gets weight 0: the background beside a view's mask, a clipped highlight. The
        photo's mean would be of the rest alone, a render's of the whole area. Kept at its valid
        share, the DiLiGenT ball's outline at a quarter of its resolution relit 0.04-0.08
        (relative RMSE, per light) against 0.005-0.009 of a per-pixel model, the whole ball 0.043
        against its 0.029 (BENCHMARKS, "DiLiGenT pot"). A pixel left out as clipped black keeps
        the valid share: its true value is about a render's, and leaving out its neighbours too
        lost the DiLiGenT pot's shadows' edges (relit 0.078 against 0.061). A pixel left out here
        is black with weight 0 in the copy, so a copy of the copy (a phase's own downscale)
        keeps it at the valid share: leaving it out there too took the pot's coarse Adam phase
        off its edges (relit 0.077)."""
        if factor == 1:
            return self
        views, cameras = [], []
        for view in self.views:
            try:
                image, weight = downscale(view.image, view.weight, factor)
            except CaptureError as error:
                raise CaptureError(f"{self.path}: view {view.name}: {error}") from None
            # what a render takes in: the background beside a mask, a clipped highlight
            left = (view.weight <= 0) & ~np.all(view.image <= 0, axis=-1)
            if view.mask is not None:
                left |= ~view.mask & (view.weight <= 0)
            if left.any():
                share = downscale(
                    left.astype(np.float32)[..., None], np.ones(left.shape, np.float32), factor
                )[0][..., 0]
                image = np.where(share[..., None] > 1e-6, 0.0, image).astype(np.float32)
                weight = np.where(share > 1e-6, 0.0, weight).astype(np.float32)
            mask = view.mask
            if mask is not None:
                h, w = mask.shape
                block = downscale(mask[..., None].astype(np.float32), np.ones((h, w)), factor)[0]
                mask = block[..., 0] > view.mask_coverage  # its meaning kept (a peer's: any)
            width, height = downscaled_size(view.camera.width, view.camera.height, factor)
            camera = view.camera.resized(width, height)
            views.append(replace(view, image=image, weight=weight, camera=camera, mask=mask))
            cameras.append(camera)
        scene = replace(self.scene, cameras=tuple(cameras[: len(self.scene.cameras)]))
        return replace(self, scene=scene, views=views)


def pixel_warnings(image: np.ndarray, name) -> list[str]:
    """One line each for an image's pixels that are not finite and those below 0 (what a fit
    does with them)."""
    out = []
    finite = np.isfinite(image)
    if not np.all(finite):
        bad = int(np.sum(~np.all(finite, axis=-1)))
        out.append(f"{name}: {bad} NaN/Inf pixels get weight 0")
    negative = np.any(finite & (image < 0), axis=-1)
    if negative.any():  # dropped: negative, every channel finite and none above 0
        dropped = int(np.sum(negative & np.all(finite, -1) & np.all(image <= 0, -1)))
        out.append(
            f"{name}: {int(negative.sum())} pixels have negative values (the lowest "
            f"{float(image[finite].min()):.3g}): {dropped} of them with no channel above 0 "
            "get weight 0 as clipped black, the others are fitted as they are; a linear "
            "image with its black level subtracted keeps noise below 0, a denoiser or "
            "resampling rings"
        )
    return out


def check_view_names(images: list[Path], where) -> None:
    """Refuse two views whose image files share a name (a view is named by its file's stem:
    their names, and their gains' keys, would collide); `where`: the file listing them."""
    first: dict[str, int] = {}
    for i, image in enumerate(images):
        j = first.setdefault(Path(image).stem, i)
        if j != i:
            raise CaptureError(
                f"{where}: views[{i}].image: {Path(image).name} has the name of views[{j}].image "
                f"({Path(images[j]).name}); a view is named by its file's name: rename one"
            )


def check_cameras_see(scene: Scene, where: Callable[[int], str]) -> None:
    """Refuse a camera that does not see the object (`where(i)`: the field of camera i)."""
    center, radius = bounding_sphere(scene.geometry)
    for i, camera in enumerate(scene.cameras):
        if not sees(camera, center, radius):
            raise CaptureError(
                f"{where(i)} does not see the object (centre {center.round(3)}, radius "
                f"{radius:.3g}); check its origin, target and field of view"
            )


def check_valid(weight: np.ndarray, where: str) -> None:
    """Refuse a view with no valid pixel (`where`: the file and field that name it)."""
    if weight.mean() == 0:
        raise CaptureError(
            f"{where} has no valid pixel (every one is saturated, black, not finite or outside "
            "the mask); check the image, its exposure and its mask"
        )


def _in_folder(path: Path, info: ValidationInfo) -> Path:
    folder = config_folder(info).resolve()
    if not path.is_relative_to(folder):
        raise ValueError(
            f"{path} points outside the capture folder {folder}; copy the file into the folder"
        )
    return path


def _not_tiny(gain: float) -> float:
    if gain < 2.0**-MAX_EV:
        raise ValueError(f"got {gain}; should be at least 2^-{MAX_EV:g} (a plausible exposure)")
    return gain


FileInFolder = Annotated[ExistingPath, AfterValidator(_in_folder)]
WhiteBalance = by_shape(text=Literal["camera", "none"], array=PositiveVec3)
TruthValue = by_shape(number=FiniteFloat, array=list[FiniteFloat])


class CaptureSettings(StrictModel):
    encoding: Literal[ENCODINGS] = "linear"
    """How the images encode light: linear, srgb or raw (camera RAW, developed here)."""
    white_balance: WhiteBalance = "camera"
    """RAW only: camera (as shot), none, or [r, g, b] multipliers."""
    downscale: PositiveInt = 1
    """Integer area-averaging factor for fitting (the cameras follow)."""
    dilate: Annotated[NonNegativeInt, Field(le=64)] = 2
    """Saturated pixels invalidate this many neighbouring pixels (at most 64)."""

    @model_validator(mode="after")
    def _raw_only(self):
        if self.encoding != "raw" and "white_balance" in self.model_fields_set:
            raise FieldError("white_balance", 'applies to encoding = "raw" only; drop it')
        return self


class ViewSpec(StrictModel):
    image: FileInFolder
    """The photograph, relative to the manifest, inside its folder."""
    mask: FileInFolder | None = None
    """An optional object mask of the image's size."""
    exposure_ev: Annotated[FiniteFloat, Field(ge=-MAX_EV, le=MAX_EV)] | None = None
    """The image is divided by 2^exposure_ev (or give gain)."""
    gain: Annotated[PositiveFloat, Field(le=2.0**MAX_EV), AfterValidator(_not_tiny)] | None = None
    """The image is divided by this relative exposure (or give exposure_ev)."""
    camera: dict[str, Any]
    """A camera table as in [[scene.cameras]]; width and height default to the image's."""

    @model_validator(mode="after")
    def _one_exposure(self):
        if self.gain is not None and self.exposure_ev is not None:
            raise FieldError("gain", "and exposure_ev both given; give one")
        return self


class Manifest(StrictModel):
    capture: CaptureSettings = CaptureSettings()
    """How to read the images."""
    scene: dict[str, Any] = Field(default_factory=dict)
    """The scene as in render configs, without cameras (the views have them)."""
    views: tuple[ViewSpec, ...] = ()
    """The photographs ([[views]])."""
    truth: dict[str, TruthValue] = Field(default_factory=dict)
    """Synthetic captures only: the true parameter values, to score fits."""
    truth_options: dict[str, str] = Field(default_factory=dict)
    """The options of the model the truth's values belong to (`"glaze.diffuse" = "eon"`: its
    sigma is EON's roughness): a fit with another option does not score those values."""
    truth_textures: dict[str, FileInFolder] = Field(default_factory=dict)
    """Synthetic captures only: the true textures by key (`"glaze.mask.texture" =
    "truth_glaze.mask.texture.exr"`, inside the folder), to score fitted masks (`mask_iou`)."""

    @model_validator(mode="after")
    def _complete(self):
        if not self.views:
            raise FieldError("views", "the photo set is empty; add [[views]] with an image each")
        if "cameras" in self.scene:
            raise FieldError("scene.cameras", "not in a capture; each view has its camera")
        return self


#: What to give where another kind of file was given as a capture.
GIVE_A_CAPTURE = (
    "give a capture (a folder holding capture.toml with [[views]], a peer scene.json or a "
    "DiLiGenT folder)"
)


def load_capture(path: str | Path) -> Capture:
    """Read a capture manifest and its images into linear arrays with validity weights."""
    path = Path(path)
    if path.is_dir():
        path = path / "capture.toml"
    doc = load_toml(path, "capture manifest")
    expect_kind(doc, path, "a capture manifest", GIVE_A_CAPTURE, CaptureError)
    manifest = parse_model(Manifest, doc, path)
    settings = manifest.capture
    check_view_names([spec.image for spec in manifest.views], path)
    views, warnings, cameras = [], [], []
    for i, spec in enumerate(manifest.views):
        try:
            if settings.encoding == "raw":
                raw = read_raw(spec.image)
                image, saturated = develop(raw, settings.white_balance), raw.saturated
            else:
                image, saturated, warned = read_linear(spec.image, settings.encoding)
                warnings += warned
        except CaptureError as err:  # name the manifest and the view
            raise CaptureError(f"{path}: views[{i}].image: {err}") from None
        h, w = image.shape[:2]
        warnings += pixel_warnings(image, spec.image)
        mask = None
        if spec.mask is not None:
            try:
                mask = read_mask(spec.mask)
            except CaptureError as err:
                raise CaptureError(f"{path}: views[{i}].mask: {err}") from None
            if mask.shape != (h, w):
                raise CaptureError(
                    f"{path}: views[{i}].mask is {mask.shape[1]}x{mask.shape[0]} but the image "
                    f"is {w}x{h}; masks must match their image"
                )
        gain = spec.gain if spec.gain is not None else 2.0 ** (spec.exposure_ev or 0.0)
        image, weight = validity(image / gain, saturated, mask, settings.dilate)
        camera = {"width": w, "height": h, **spec.camera}
        sizes = (camera["width"], camera["height"])
        for name, size in zip(("width", "height"), sizes, strict=True):
            if type(size) is int and size < 1:
                raise CaptureError(
                    f"{path}: views[{i}].camera.{name} = {size}: must be a positive number of "
                    f"pixels; give the image's ({w}x{h}) or drop width and height"
                )
        if all(type(x) is int for x in sizes) and sizes != (w, h):
            raise CaptureError(
                f"{path}: views[{i}].camera is {camera['width']}x{camera['height']} but "
                f"{spec.image.name} is {w}x{h}; make them match (or drop width and height)"
            )
        cameras.append(camera)
        views.append(View(spec.image.stem, image, weight, None, gain, mask=mask))  # camera below
        check_valid(weight, f"{path}: views[{i}].image: {spec.image.name}")

    try:
        scene = parse_scene({**manifest.scene, "cameras": cameras}, path)
    except CaptureError as err:  # the cameras are the views' here: name the manifest's keys
        message = re.sub(r"scene\.cameras\[(\d+)\]", r"views[\1].camera", str(err))
        raise CaptureError(message) from None
    folder = path.parent.resolve()
    for key, file in _scene_files(scene):
        if not file.resolve().is_relative_to(folder):
            raise CaptureError(
                f"{path}: scene.{key}: {file} points outside the capture folder {folder}; copy "
                "the file into the folder"
            )
    for view, camera in zip(views, scene.cameras, strict=True):
        view.camera = camera
    check_cameras_see(scene, lambda i: f"{path}: views[{i}].camera")
    for message in warnings:
        log.warning(message)
    warnings += getattr(scene.geometry, "warnings", ())  # the mesh's, said as it was read
    capture = Capture(
        scene,
        views,
        dict(manifest.truth),
        path,
        warnings,
        dict(manifest.truth_options),
        {k: Path(v).resolve() for k, v in manifest.truth_textures.items()},
    )
    capture.check_factor(settings.downscale, f"{path}: capture.downscale")
    return capture.downscaled(settings.downscale)


def _scene_files(scene: Scene) -> list[tuple[str, Path]]:
    """(key, path) of the files a scene reads: its mesh and its environment map."""
    from .scene import EnvMap, ObjFile

    files = []
    if isinstance(scene.geometry, ObjFile):
        files.append(("geometry", Path(scene.geometry.path)))
    if isinstance(scene.environment, EnvMap):
        files.append(("environment.file", Path(scene.environment.path)))
    return files


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


def manifest_text(
    capture_table: dict,
    scene_table: dict,
    views: list[dict],
    truth: dict,
    truth_options: dict | None = None,
    truth_textures: dict | None = None,
) -> str:
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
    if truth_options:
        lines += ["", "[truth_options]"]
        lines += [f'"{k}" = {_toml_value(v)}' for k, v in truth_options.items()]
    if truth_textures:
        lines += ["", "[truth_textures]"]
        lines += [f'"{k}" = {_toml_value(str(v))}' for k, v in truth_textures.items()]
    return "\n".join(lines) + "\n"
