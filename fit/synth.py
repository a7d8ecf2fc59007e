"""Synthetic captures: render a config's views and write a capture folder with its `[truth]`."""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import mitsuba as mi
import numpy as np

from captures import Scene
from captures.capture import manifest_text
from captures.images import write_image
from captures.scene import EnvMap, ObjFile
from captures.schema import camera_to_table, scene_to_table

from .render import render
from .scene import scene_dict

FORMATS = {"exr": ("exr", "linear"), "png": ("png", "srgb"), "jpg": ("jpg", "srgb")}


@dataclass(frozen=True)
class Degradation:
    """Seeded photographic degradations: shot noise (variance `shot * signal`), read noise (std
    `read`), a random exposure offset per view (uniform in +-`exposure_ev`, recorded in the
    manifest). JPEG compression comes with the jpg format."""

    shot: float = 0.0
    read: float = 0.0
    exposure_ev: float = 0.0


def truth_of(material: dict, prefix: str = "") -> dict:
    """The declared parameter values of a material dict, keyed as the fitter names them
    (`glaze.roughness`, `lime.mask.threshold`, `bump`)."""
    out: dict = {}
    if material["type"] == "layered":
        for name in material["layers"].split(","):
            out |= truth_of(material[name], f"{prefix}{name}.")
            mask = material.get(f"{name}_mask")
            if isinstance(mask, dict):
                out |= {
                    f"{prefix}{name}.mask.{k}": v
                    for k, v in mask.items()
                    if k in ("threshold", "softness")
                }
        if "bump" in material:
            out[f"{prefix}bump"] = material["bump"]
        return out
    prefix = prefix or f"{material['type']}."
    for key, value in material.items():
        if key == "type" or isinstance(value, str):
            continue
        if isinstance(value, dict):
            if value.get("type") == "rgb":
                out[prefix + key] = list(value["value"])
        elif isinstance(value, int | float) and not key.endswith(("_scale", "_seed")):
            out[prefix + key] = value
    return out


def synthesize(
    scene: Scene,
    material: dict,
    out: Path,
    spp: int = 256,
    seed: int = 0,
    fmt: str = "exr",
    degradation: Degradation = Degradation(),
    progress: Callable[[int, int], None] | None = None,
) -> Path:
    """Render every camera of `scene` with `material` and write a capture folder at `out`.

    The folder appears whole or not at all: it is written next to `out`, then renamed.
    `progress(view, spp_done)` is called as views render.
    """
    if fmt not in FORMATS:
        raise ValueError(f"format {fmt!r}; choose one of {', '.join(FORMATS)}")
    if out.exists():
        raise FileExistsError(f"{out} exists; choose a new folder (nothing was overwritten)")
    suffix, encoding = FORMATS[fmt]
    rng = np.random.default_rng(seed)
    out.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{out.name}-", dir=out.parent))
    try:
        # Files the scene refers to move into the capture folder
        if isinstance(scene.geometry, ObjFile):
            shutil.copy(scene.geometry.path, staging / scene.geometry.path.name)
            scene = _replace_geometry(scene, staging / scene.geometry.path.name)
        if isinstance(scene.environment, EnvMap):
            target = staging / scene.environment.path.name
            shutil.copy(scene.environment.path, target)
            scene = _replace_env(scene, target)
        views = []
        for i, camera in enumerate(scene.cameras):
            loaded = mi.load_dict(scene_dict(scene, material, i, spp))
            image = render(
                loaded, spp, seed + 1000 * i, (lambda n, i=i: progress(i, n)) if progress else None
            )
            ev = float(rng.uniform(-1, 1) * degradation.exposure_ev)
            image = image * 2.0**ev
            if degradation.shot > 0 or degradation.read > 0:
                std = np.sqrt(degradation.shot * np.clip(image, 0, None) + degradation.read**2)
                image = image + std * rng.standard_normal(image.shape).astype(np.float32)
            image = np.clip(image, 0.0, None)
            name = f"view_{i:02d}.{suffix}"
            write_image(staging / name, image)
            views.append({"image": name, "exposure_ev": ev, "camera": camera_to_table(camera)})
        text = manifest_text(
            {"encoding": encoding}, scene_to_table(scene, staging), views, truth_of(material)
        )
        (staging / "capture.toml").write_text(text)
        umask = os.umask(0)
        os.umask(umask)
        staging.chmod(0o777 & ~umask)  # mkdtemp's 0700 is for secrets
        staging.rename(out)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    return out


def _replace_geometry(scene: Scene, path: Path) -> Scene:
    from dataclasses import replace

    return replace(scene, geometry=ObjFile(path))


def _replace_env(scene: Scene, path: Path) -> Scene:
    from dataclasses import replace

    return replace(scene, environment=EnvMap(path, scene.environment.scale))
