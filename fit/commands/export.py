"""`layerfit export`: a preset to Mitsuba XML, MaterialX (OpenPBR) or USD (UsdPreviewSurface), and
with `--with-scene` the object's USD stage from the capture it was fitted to."""

from __future__ import annotations

from pathlib import Path

from captures.errors import InputError

from .common import Quiet, start, stopping


def default_out(preset: Path, to: str, portable: bool = False) -> Path:
    """`out/<preset name>-<target>` (a run's `preset.toml` is named by its run folder)."""
    name = preset.resolve().parent.name if preset.stem == "preset" else preset.stem
    return Path("out") / f"{name}-{to}{'-portable' if portable else ''}"


def preset_file(path: Path) -> Path:
    """The preset of a run folder (its `preset.toml`), or `path` itself."""
    if not path.is_dir():
        return path
    if not (path / "preset.toml").is_file():
        raise InputError(
            f"{path}: a folder without preset.toml; give a preset file or a run folder holding "
            "one (an interrupted fit writes none: finish it with `layerfit fit ... --resume`)"
        )
    return path / "preset.toml"


def scene_capture(preset, capture: Path | None) -> Path:
    """The capture whose scene `--with-scene` writes: `capture` where given, else the one the
    preset's provenance names (a fit's preset names its capture; relative to the preset)."""
    if capture is not None:
        return Path(capture)
    named = preset.provenance.get("capture")
    if not isinstance(named, str) or not named.strip():
        raise InputError(
            f"--with-scene: {preset.path} names no capture (provenance.capture: a fit's preset "
            "names its own); give one with --capture (a capture folder, a peer scene.json or a "
            "DiLiGenT folder)"
        )
    path = Path(preset.path).parent / named
    if not path.exists():
        raise InputError(
            f"--with-scene: {preset.path}: provenance.capture = {named!r} does not exist (moved "
            "or deleted?); give the capture with --capture"
        )
    return path


def export(
    preset: Path,
    to: str,
    out: Path | None = None,
    portable: bool = False,
    force: bool = False,
    size: int = 1024,
    variant: str | None = None,
    progress=None,
    with_scene: bool = False,
    capture: Path | None = None,
) -> Path:
    """Export `preset` (a preset file or a run folder) to the target `to` (mitsuba, materialx or
    usd) in the new folder `out` (default `default_out`; an existing non-empty one only with
    `force`). `portable`: Mitsuba's built-in plugins only; `size`: texels per side of baked
    images. `with_scene` (USD): the object's stage too, `scene.usda` (mesh, material, cameras,
    lights; `fit.export.usd_scene`) from `capture` or, without it, the capture the preset's
    provenance names. What each target holds exactly, approximates or loses: docs/exports.md.
    Returns the main file written (`scene.usda` with the scene)."""
    from captures import open_capture

    from ..export import TARGETS, check_output, inputs_of
    from ..material import load_preset

    progress = progress or Quiet()
    preset = preset_file(Path(preset))
    out = out or default_out(preset, to, portable)
    if to not in TARGETS:
        raise InputError(f"--to {to!r}: choose one of {', '.join(TARGETS)}")
    if with_scene and to != "usd":
        raise InputError(f"--with-scene: applies to --to usd only (got --to {to})")
    if capture is not None and not with_scene:
        raise InputError("--capture: names the scene's capture; add --with-scene, or drop it")
    loaded = load_preset(preset)
    scene = scene_capture(loaded, capture) if with_scene else None
    check_output(out, force, inputs_of(loaded) + ([scene] if scene else []))
    start(variant)
    from ..export import export as export_preset

    with stopping(lambda: f"nothing written ({out} as it was)"):
        captured = open_capture(scene) if scene else None  # its own checks, one line each
        baked = to != "mitsuba" or portable
        task = progress.add_task(f"{to}: bake {size}x{size}" if baked else to, total=None)
        return export_preset(
            loaded,
            to,
            out,
            portable,
            force,
            size,
            lambda done, total: progress.update(task, completed=done, total=total),
            captured,
        )
