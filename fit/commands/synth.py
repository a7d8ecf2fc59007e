"""Synthetic captures: render a config's views and write a capture folder with its `[truth]`."""

from __future__ import annotations

import logging
import shutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from captures import Scene
from captures.capture import manifest_text
from captures.files import atomic_path
from captures.images import write_image
from captures.scene import EnvMap, ObjFile
from captures.schema import camera_to_table, scene_to_table

from ..material import Material
from .common import Quiet, check_capture_cameras, render_inputs, scene_and_material, start, stopping

FORMATS = {"exr": ("exr", "linear"), "png": ("png", "srgb"), "jpg": ("jpg", "srgb")}


@dataclass(frozen=True)
class Degradation:
    """Seeded photographic degradations: shot noise (variance `shot * signal`), read noise (std
    `read`), a random exposure offset per view (uniform in +-`exposure_ev`, recorded in the
    manifest) around a fixed `base_ev` for every view (negative: darker photos whose highlights do
    not clip). JPEG compression comes with the jpg format."""

    shot: float = 0.0
    read: float = 0.0
    exposure_ev: float = 0.0
    base_ev: float = 0.0


log = logging.getLogger(__name__)

#: The share of clipped pixels in a view (8/16-bit formats) above which synth warns.
CLIP_WARNING = 0.01


def synthesize(
    scene: Scene,
    material: Material,
    out: Path,
    spp: int = 256,
    seed: int = 0,
    fmt: str = "exr",
    degradation: Degradation = Degradation(),
    progress: Callable[[int, int], None] | None = None,
    replace: bool = False,
) -> Path:
    """Render every camera of `scene` with `material` and write a capture folder at `out`.

    The folder appears whole or not at all: it is written next to `out`, then renamed (with
    `replace`, over an existing folder, removed only then). `progress(view, spp_done)` is
    called as views render.
    """
    from ..render import load_scene, render, scene_dict

    if fmt not in FORMATS:
        raise ValueError(f"format {fmt!r}; choose one of {', '.join(FORMATS)}")
    suffix, encoding = FORMATS[fmt]
    rng = np.random.default_rng(seed)
    # the capture's own files: a scene file of one of these names is copied under another (an
    # environment map named view_00.exr was overwritten by the first view, lighting the capture)
    written = {f"view_{i:02d}.{suffix}" for i in range(len(scene.cameras))} | {"capture.toml"}

    def free_name(path: Path) -> str:
        return path.name if path.name not in written else f"scene-{path.name}"

    with atomic_path(out, folder=True, replace=replace) as staging:
        # Files the scene refers to move into the capture folder
        if isinstance(scene.geometry, ObjFile):
            target = staging / free_name(scene.geometry.path)
            shutil.copy(scene.geometry.path, target)
            scene = _replace_geometry(scene, target)
        if isinstance(scene.environment, EnvMap):
            target = staging / free_name(scene.environment.path)
            shutil.copy(scene.environment.path, target)
            scene = _replace_env(scene, target)
        views = []
        for i, camera in enumerate(scene.cameras):
            loaded = load_scene(scene_dict(scene, material.bsdf, i, spp))
            view_seed = (seed + 1000 * i) % 2**32  # the sampler's seeds are 32-bit
            image = render(
                loaded, spp, view_seed, (lambda n, i=i: progress(i, n)) if progress else None
            )
            ev = degradation.base_ev + float(rng.uniform(-1, 1) * degradation.exposure_ev)
            image = image * 2.0**ev
            if degradation.shot > 0 or degradation.read > 0:
                std = np.sqrt(degradation.shot * np.clip(image, 0, None) + degradation.read**2)
                image = image + std * rng.standard_normal(image.shape).astype(np.float32)
            image = np.clip(image, 0.0, None)
            name = f"view_{i:02d}.{suffix}"
            clipped = float(np.mean(np.any(image >= 1.0, axis=-1))) if encoding != "linear" else 0
            if clipped > CLIP_WARNING:
                log.warning(
                    f"{out / name}: {100 * clipped:.1f} % of its pixels clip at the format's "
                    "white (a fit gives them no weight); lower --exposure-base (each -1 halves "
                    "the image) until under 1 % do"
                )
            write_image(staging / name, image)
            views.append({"image": name, "exposure_ev": ev, "camera": camera_to_table(camera)})
        # the diffuse lobe gives `sigma` its meaning (radians, or EON's roughness)
        lobes = {k: v for k, v in material.options.items() if k.endswith(".diffuse")}
        text = manifest_text(
            {"encoding": encoding},
            scene_to_table(scene, staging),
            views,
            material.values(),
            lobes,
            _truth_textures(material, staging),
        )
        (staging / "capture.toml").write_text(text, encoding="utf-8")
    return out


def _truth_textures(material, folder: Path) -> dict[str, str]:
    """The material's masks' painted textures copied into the capture `folder` (a fitted mask
    is scored against them: `mask_iou`), by key: file name."""
    out = {}
    for key, param in material.params.items():
        if key.endswith(".mask.texture") and param.texture is not None:
            name = f"truth_{key}{Path(param.texture).suffix}"
            shutil.copy(param.texture, folder / name)
            out[key] = name
    return out


def _replace_geometry(scene: Scene, path: Path) -> Scene:
    from dataclasses import replace

    return replace(scene, geometry=replace(scene.geometry, path=path))


def _replace_env(scene: Scene, path: Path) -> Scene:
    from dataclasses import replace

    return replace(scene, environment=EnvMap(path, scene.environment.scale))


def synth(
    config: Path,
    out: Path,
    scene: Path | None = None,
    fmt: str = "exr",
    spp: int | None = None,
    seed: int = 0,
    degradation: Degradation = Degradation(),
    force: bool = False,
    variant: str | None = None,
    progress=None,
) -> Path:
    """`layerfit synth`: render a synthetic capture of `config` (a render config whose material
    is the truth, or a preset with `scene`) into the new folder `out`; `force` replaces a
    capture synth made, never one of photographs. `progress`: a `rich.progress.Progress`
    (default: none shown). Returns the manifest's path."""
    from captures.errors import InputError
    from captures.files import check_output, refuse_foreign

    progress = progress or Quiet()
    the_scene, material, config_spp = scene_and_material(config, scene)
    check_capture_cameras(the_scene, scene or config)
    if fmt not in FORMATS:
        raise InputError(f"--format {fmt!r}: unknown format; choose one of exr, png, jpg")
    inputs = render_inputs(config, scene, the_scene, material)
    check_output(out, "--out", force=force, inputs=inputs, folder=True)
    manifest = out / "capture.toml"
    if out.is_dir() and any(out.iterdir()) and not manifest.is_file():
        raise InputError(
            f"--out {out}: is a folder but not a capture (no capture.toml); --force replaces "
            "only a capture folder: choose another path"
        )
    if out.is_dir() and manifest.is_file() and not _synthetic(out):
        raise InputError(
            f"--out {out}: holds photographs (its capture.toml has no [truth]); --force "
            "replaces only a capture made by synth: choose another path"
        )
    if out.is_dir() and manifest.is_file():
        refuse_foreign(out, manifest, "synth")
    start(variant)
    spp = spp or config_spp
    with stopping(lambda: "nothing written"):
        tasks = [progress.add_task(f"view {i}", total=spp) for i in range(len(the_scene.cameras))]
        try:
            return synthesize(
                the_scene,
                material,
                out,
                spp,
                seed,
                fmt,
                degradation,
                lambda view, n: progress.update(tasks[view], completed=n),
                replace=force,
            )
        except FileExistsError as err:
            raise InputError(str(err)) from None


def _synthetic(folder: Path) -> bool:
    """Whether a capture folder was made by `synth` (its manifest holds the [truth]); an
    unreadable manifest counts as not."""
    import tomllib

    try:
        return "truth" in tomllib.loads((folder / "capture.toml").read_text(encoding="utf-8-sig"))
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError):
        return False
