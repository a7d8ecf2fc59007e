"""`layerfit export`: a preset to Mitsuba XML, MaterialX (OpenPBR) or USD (UsdPreviewSurface)."""

from __future__ import annotations

from pathlib import Path

from captures.errors import InputError

from .common import Quiet, start, stopping


def default_out(preset: Path, to: str, portable: bool = False) -> Path:
    """`out/<preset name>-<target>` (a run's `preset.toml` is named by its run folder)."""
    name = preset.resolve().parent.name if preset.stem == "preset" else preset.stem
    return Path("out") / f"{name}-{to}{'-portable' if portable else ''}"


def export(
    preset: Path,
    to: str,
    out: Path | None = None,
    portable: bool = False,
    force: bool = False,
    size: int = 1024,
    variant: str | None = None,
    progress=None,
) -> Path:
    """Export `preset` to the target `to` (mitsuba, materialx or usd) in the new folder `out`
    (default `default_out`; an existing non-empty one only with `force`). `portable`: Mitsuba's
    built-in plugins only; `size`: texels per side of baked images. What each target holds
    exactly, approximates or loses: docs/exports.md. Returns the main file written."""
    from ..export import TARGETS, check_output, inputs_of
    from ..material import load_preset

    progress = progress or Quiet()
    out = out or default_out(preset, to, portable)
    if to not in TARGETS:
        raise InputError(f"--to {to!r}: choose one of {', '.join(TARGETS)}")
    loaded = load_preset(preset)
    check_output(out, force, inputs_of(loaded))
    start(variant)
    from ..export import export as export_preset

    with stopping(lambda: f"nothing written ({out} as it was)"):
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
        )
