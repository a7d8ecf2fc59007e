"""Exports of a preset to the tools artists render with: Mitsuba XML (native or `portable`),
MaterialX (OpenPBR surface) and USD (UsdPreviewSurface; with a capture, `usd_scene` adds the
object's stage). One module per target; `bake` holds the shared baking, `mapping` the fitted
lobe maps. Import after the Mitsuba variant is chosen and `materials.register()` ran (baking
evaluates the plugins)."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from pathlib import Path

from captures.capture import Capture
from captures.errors import InputError, listing
from captures.files import atomic_path, foreign_entries, refuse_foreign
from captures.files import check_output as check_path
from captures.scene import EnvMap, ObjFile

from ..errors import ConfigError
from ..material import Preset, load_preset
from .bake import Progress
from .usd_scene import FILE as SCENE_FILE  # the stage `--with-scene` writes; the marker names it

#: The targets, by `--to` name.
TARGETS = ("mitsuba", "materialx", "usd")
#: Texels per side of baked images by default (the cup's finest fbm octave: ~5 texels a cell).
BAKE_SIZE = 1024
#: The largest: a baked colour is size^2 x 12 bytes in memory (8192: 0.8 GB; the cup bakes up to
#: five images, its masks a third of that each).
MAX_BAKE_SIZE = 8192
#: The main file each target writes: a folder holding one of them is an earlier export, the only
#: kind of non-empty folder `--force` replaces.
MAIN_FILES = ("material.xml", "material.mtlx", "material.usda")
#: The file every export writes beside its main file: with it, a folder is an export of
#: layerfit's (a user's own `material.xml` and the textures it names are not one).
MARKER = ".layerfit-export"


def check_output(out: Path, force: bool, inputs=()) -> None:
    """Refuse an output that is a file, one of the export's `inputs` (the preset, its textures)
    or a folder holding one, a place that cannot be written, an existing non-empty folder
    without `force`, and with `force` one that holds no earlier export (a user's own folder)."""
    if out.exists() and not out.is_dir():
        raise ConfigError(f"{out}: is a file; give --out a folder (new or empty)")
    check_path(out, "--out", force=True, inputs=inputs, folder=True)
    if not out.is_dir() or not any(out.iterdir()):
        return
    if not force:
        raise ConfigError(f"{out}: exists and is not empty; pass --force to replace it")
    main = next((out / name for name in MAIN_FILES if (out / name).is_file()), None)
    if main is None:
        names = sorted(p.name for p in out.iterdir())
        shown = listing(names)
        raise ConfigError(
            f"--out {out}: is not a layerfit export (it holds {shown}, no "
            f"{' / '.join(MAIN_FILES)}); --force replaces only an earlier export: choose "
            "another path"
        )
    if not (out / MARKER).is_file():
        raise ConfigError(
            f"--out {out}: holds {main.name} but no {MARKER}, which every layerfit export "
            "writes: it is not replaced (a material of your own, or an export of a layerfit "
            "before 2026-12-02: delete it yourself); choose another path"
        )
    scene = out / SCENE_FILE
    if not (scene.is_file() and SCENE_FILE in (out / MARKER).read_text(errors="replace")):
        refuse_foreign(out, main, "the earlier export", extra=(MARKER,))
        return
    # the stage names its mesh and the material, the material its maps: ours if either names it
    foreign = set(foreign_entries(out, main, (MARKER,))) & set(
        foreign_entries(out, scene, (MARKER,))
    )
    if foreign:
        raise InputError(
            f"--out {out}: also holds {listing(sorted(foreign))}, which the earlier export did "
            f"not write (its {main.name} and {SCENE_FILE} name no such file); --force replaces "
            "the whole folder: move them out or choose another path"
        )


def inputs_of(preset: Preset, capture: Capture | None = None) -> list[Path]:
    """The files an export of `preset` reads: the preset file and its textures, and with a
    capture its file or folder, its mesh file and its environment map."""
    files = list(preset.material.texture_files().values())
    files += [preset.path] if preset.path is not None else []
    if capture is not None:
        files += [capture.path] if capture.path is not None else []
        scene = capture.scene
        files += [scene.geometry.path] if isinstance(scene.geometry, ObjFile) else []
        files += [scene.environment.path] if isinstance(scene.environment, EnvMap) else []
    return files


@contextlib.contextmanager
def output_folder(out: Path, force: bool, inputs=()) -> Iterator[Path]:
    """A temporary folder to write into that becomes `out` on success (the previous `out`
    removed only then); on any error nothing is left behind and `out` is as it was."""
    check_output(out, force, inputs)
    with atomic_path(out, folder=True, replace=True) as new:
        yield new


def export(
    preset: Preset | Path,
    to: str,
    out: Path,
    portable: bool = False,
    force: bool = False,
    size: int = BAKE_SIZE,
    progress: Progress | None = None,
    capture: Capture | None = None,
) -> Path:
    """Export a preset (or its file) to `to` in the folder `out`; the main file's path.

    `portable` (Mitsuba only): built-in plugins only. `size`: texels per side of baked images.
    `progress(done, total)`: after each baked image. `capture` (USD only): the object's stage
    too, `scene.usda` (`usd_scene`; the main file then). The folder appears whole or not at
    all.
    """
    from . import materialx, mitsuba, usd, usd_scene

    if to not in TARGETS:
        raise ConfigError(f"--to {to!r}: choose one of {', '.join(TARGETS)}")
    if portable and to != "mitsuba":
        raise ConfigError(f"--portable: applies to --to mitsuba only (got --to {to})")
    if capture is not None and to != "usd":
        raise ConfigError(f"--with-scene: applies to --to usd only (got --to {to})")
    if not 1 <= size <= MAX_BAKE_SIZE:
        raise ConfigError(f"--size {size}: give texels per side from 1 to {MAX_BAKE_SIZE}")
    if not isinstance(preset, Preset):
        preset = load_preset(preset)
    material = preset.material
    with output_folder(out, force, inputs_of(preset, capture)) as folder:
        if to == "mitsuba" and not portable:
            path = mitsuba.export_native(material, folder)
        elif to == "mitsuba":
            path = mitsuba.export_portable(material, folder, size, progress)
        elif to == "materialx":
            path = materialx.export(material, folder, size, progress)
        else:
            path = usd.export(material, folder, size, progress)
            if capture is not None:
                path = usd_scene.export(capture, path.name, folder)
        kind = f"{to} (portable)" if portable else f"{to} with its scene" if capture else to
        (folder / MARKER).write_text(f"layerfit export: {kind}, {path.name}\n", encoding="utf-8")
        name = path.name
    return out / name


__all__ = [
    "BAKE_SIZE",
    "MAIN_FILES",
    "MARKER",
    "MAX_BAKE_SIZE",
    "SCENE_FILE",
    "TARGETS",
    "check_output",
    "export",
    "inputs_of",
    "output_folder",
]
