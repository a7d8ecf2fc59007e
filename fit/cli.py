"""The `layerfit` command line."""

from __future__ import annotations

import logging
import sys
from pathlib import Path
from typing import Annotated

import numpy as np
import typer
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from captures.errors import InputError

from .variant import BackendError, select_variant

app = typer.Typer(add_completion=False, no_args_is_help=True, help=__doc__)
console = Console(stderr=True)

VariantOption = Annotated[
    str | None,
    typer.Option(
        "--variant", envvar="LAYERFIT_VARIANT", help="Mitsuba variant (default llvm_ad_rgb)."
    ),
]


def _fail(err: Exception, code: int) -> typer.Exit:
    """Print one unwrapped error line; return the exit to raise."""
    console.print(f"[red]error:[/] {err}", highlight=False, soft_wrap=True)
    return typer.Exit(code)


def _scene_and_material(config: Path, scene: Path | None):
    """(scene, material, spp) of a render config or a preset, the scene replaced by `scene`'s."""
    from captures import CaptureError, parse_scene

    from .config import load_render_config
    from .material import load_preset, read_toml

    doc = read_toml(config)
    if "schema" in doc:  # a preset: the material only
        if scene is None:
            raise CaptureError(f"{config}: is a preset (a material); give --scene SCENE.toml")
        material, spp = load_preset(config).material, 64
    else:
        cfg = load_render_config(config)
        material, spp = cfg.material, cfg.spp
        if scene is None:
            return cfg.scene, material, spp
    table = read_toml(scene)
    if "scene" not in table:
        raise CaptureError(f"{scene}: no [scene] table")
    return parse_scene(table["scene"], scene), material, spp


def _start(variant: str | None) -> None:
    """Select the variant and register the plugins, or stop with one line."""
    try:
        select_variant(variant)
    except BackendError as err:
        raise _fail(err, 1) from None
    import materials

    materials.register()


def _progress() -> Progress:
    return Progress(
        TextColumn("{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        console=console,
        transient=False,
    )


@app.command()
def render(
    config: Annotated[
        Path,
        typer.Argument(help="Render config (TOML: scene, material, render) or a preset (--scene)."),
    ],
    scene: Annotated[
        Path | None,
        typer.Option(help="TOML whose scene table replaces the config's (needed for a preset)."),
    ] = None,
    out: Annotated[
        Path, typer.Option(help="Output PNG (sRGB); a linear EXR is written beside it.")
    ] = Path("out/render.png"),
    spp: Annotated[
        int | None, typer.Option(help="Samples per pixel (overrides the config).")
    ] = None,
    seed: Annotated[int, typer.Option(help="Random seed.")] = 0,
    variant: VariantOption = None,
) -> None:
    """Render a config's scene with its material (or a preset's material in --scene's scene): a
    linear EXR and an sRGB PNG per view."""
    from captures.images import write_image

    try:
        the_scene, material, config_spp = _scene_and_material(config, scene)
    except InputError as err:
        raise _fail(err, 2) from None
    _start(variant)
    import mitsuba as mi

    from .render import render as render_image
    from .render import scene_dict

    spp = spp or config_spp
    views = len(the_scene.cameras)
    with _progress() as bar:
        for view in range(views):
            task = bar.add_task(f"view {view}", total=spp)
            loaded = mi.load_dict(scene_dict(the_scene, material.bsdf, view, spp))
            image = render_image(loaded, spp, seed, lambda n, t=task: bar.update(t, completed=n))
            stem = out.with_suffix("") if views == 1 else out.with_name(f"{out.stem}_{view:02d}")
            for path in (stem.with_suffix(".exr"), stem.with_suffix(out.suffix or ".png")):
                write_image(path, image)
                console.print(f"wrote {path}")


@app.command()
def bench(
    spp: Annotated[int, typer.Option(help="Samples per pixel of each timed render.")] = 64,
    repeats: Annotated[int, typer.Option(help="Timed renders per case (median reported).")] = 7,
    only: Annotated[
        str | None,
        typer.Option(help="Run one table: bsdf, cup, fit or long (fit, long: not run by default)."),
    ] = None,
    fit_config: Annotated[
        Path, typer.Option(help="--only fit: the fit config whose schedules are compared.")
    ] = Path("configs/peer-sphere.toml"),
    steps: Annotated[int, typer.Option(help="--only long: Adam steps of the long run.")] = 1000,
    out: Annotated[Path | None, typer.Option(help="Also write the tables (Markdown) here.")] = None,
    variant: VariantOption = None,
) -> None:
    """Speed tables: our BSDFs vs Mitsuba's built-ins, the cup's stack vs its layers, (with
    --only fit, minutes) fit schedules' wall time vs accuracy, and (with --only long) time and
    memory per step over a long Adam run, plotted to a PNG beside --out (or bench-long.png)."""
    if only not in (None, "bsdf", "cup", "fit", "long"):
        raise _fail(ValueError(f"--only {only!r}: choose bsdf, cup, fit or long"), 2)
    if steps < 2:
        raise _fail(ValueError(f"--steps {steps}: give at least 2"), 2)
    _start(variant)
    from .commands.bench import (
        bsdf_speed_table,
        cup_speed_table,
        fit_trade_table,
        long_run,
        long_run_table,
        plot_long_run,
    )

    tables = []
    with _progress() as bar:
        try:  # the scenes are read from configs/ under the working directory
            if only in (None, "bsdf"):
                tables.append(bsdf_speed_table(spp=spp, repeats=repeats, progress=bar))
            if only in (None, "cup"):
                tables.append(cup_speed_table(spp=spp, repeats=repeats, progress=bar))
            if only == "fit":
                tables.append(fit_trade_table(fit_config, progress=bar))
            if only == "long":
                run = long_run(steps=steps, progress=bar)
                tables.append(long_run_table(run))
                plot = out.with_suffix(".png") if out else Path("bench-long.png")
                console.print(f"wrote {plot_long_run(run, plot)}")
        except (InputError, ValueError) as err:
            raise _fail(err, 2) from None
    for table in tables:
        console.print(table.rich())
    if out is not None:
        out.write_text("\n".join(t.markdown() for t in tables))
        console.print(f"wrote {out}")


@app.command()
def synth(
    config: Annotated[
        Path, typer.Argument(help="Render config (TOML) whose material is the truth, or a preset.")
    ],
    out: Annotated[Path, typer.Option(help="New capture folder to write.")],
    scene: Annotated[
        Path | None, typer.Option(help="TOML whose [scene] replaces the config's.")
    ] = None,
    fmt: Annotated[
        str, typer.Option("--format", help="exr (linear), png (16-bit sRGB), jpg (8-bit sRGB).")
    ] = "exr",
    spp: Annotated[
        int | None, typer.Option(help="Samples per pixel (default: the config's).")
    ] = None,
    seed: Annotated[int, typer.Option(help="Seed of the renders and the degradations.")] = 0,
    shot: Annotated[float, typer.Option(help="Shot noise: variance = shot * signal.")] = 0.0,
    read: Annotated[float, typer.Option(help="Read noise standard deviation.")] = 0.0,
    exposure_ev: Annotated[
        float, typer.Option(help="Random exposure offset per view, +- EV.")
    ] = 0.0,
    exposure_base: Annotated[
        float, typer.Option(help="Exposure of every view, EV (negative: darker, fewer clipped).")
    ] = 0.0,
    variant: VariantOption = None,
) -> None:
    """Render a synthetic capture (images, manifest, [truth]) from a config (or a preset with
    --scene)."""
    try:
        the_scene, material, config_spp = _scene_and_material(config, scene)
    except InputError as err:
        raise _fail(err, 2) from None
    _start(variant)
    from .commands.synth import FORMATS, Degradation, synthesize

    if fmt not in FORMATS:
        raise _fail(ValueError(f"--format {fmt!r}: choose one of {', '.join(FORMATS)}"), 2)
    spp = spp or config_spp
    with _progress() as bar:
        tasks = [bar.add_task(f"view {i}", total=spp) for i in range(len(the_scene.cameras))]
        try:
            path = synthesize(
                the_scene,
                material,
                out,
                spp,
                seed,
                fmt,
                Degradation(shot, read, exposure_ev, exposure_base),
                lambda view, n: bar.update(tasks[view], completed=n),
            )
        except (FileExistsError, ValueError) as err:
            raise _fail(err, 2) from None
    console.print(f"wrote {path}")


@app.command()
def inspect(
    capture: Annotated[
        Path,
        typer.Argument(
            help="capture.toml (or its folder), a peer scene.json, or a DiLiGenT folder."
        ),
    ],
    sheet: Annotated[
        Path | None, typer.Option(help="Contact sheet PNG (default: out/inspect-<name>.png).")
    ] = None,
    silhouette: Annotated[bool, typer.Option(help="Render the scene's silhouette (IoU).")] = True,
    downscale: Annotated[int, typer.Option(help="DiLiGenT only: area-average by this factor.")] = 1,
    variant: VariantOption = None,
) -> None:
    """A table of the views (size, gain, valid pixels, silhouette IoU) and a contact sheet."""
    from rich.table import Table as RichTable

    from captures import open_capture

    _start(variant)
    from .commands.inspect import contact_sheet, silhouettes, summary

    try:
        cap = open_capture(capture, downscale)
    except InputError as err:
        raise _fail(err, 2) from None
    for warning in cap.warnings:
        console.print(f"[yellow]warning:[/] {warning}", highlight=False, soft_wrap=True)
    coverage = silhouettes(cap) if silhouette else None
    rows = summary(cap, coverage)
    table = RichTable(title=f"{capture}: {len(rows)} views")
    for column in ("view", "size", "gain", "valid", "max", "iou"):
        table.add_column(column)
    for row in rows:
        table.add_row(
            row["view"],
            row["size"],
            f"{row['gain']:.3g}",
            f"{row['valid']:.1%}",
            f"{row['max']:.3g}",
            f"{row['iou']:.3f}" if "iou" in row else "-",
        )
    console.print(table)
    name = capture.stem if capture.name != "scene.json" else capture.parent.name
    out = contact_sheet(cap, coverage, sheet or Path("out") / f"inspect-{name}.png")
    console.print(f"wrote {out}")


@app.command()
def fit(
    config: Annotated[Path, typer.Argument(help="Fit config (TOML): capture, material, fit.")],
    out: Annotated[
        Path | None, typer.Option(help="Run folder (default out/<config name>).")
    ] = None,
    resume: Annotated[
        bool, typer.Option("--resume", help="Continue a killed run from its checkpoint.")
    ] = False,
    force: Annotated[
        bool, typer.Option("--force", help="Replace the results in an existing run folder.")
    ] = False,
    holdout: Annotated[
        int | None,
        typer.Option(min=0, help="Views kept out of the fit and scored (default: the config's)."),
    ] = None,
    variant: VariantOption = None,
) -> None:
    """Fit the free material parameters to a capture into a run folder (preset, summary, report);
    print fitted vs known values."""
    from rich.table import Table as RichTable

    from .config import load_fit_config

    out = out or Path("out") / config.stem
    try:
        cfg = load_fit_config(config)
        from .commands.fit import check_output

        check_output(out, cfg, resume, force)
    except InputError as err:
        raise _fail(err, 2) from None
    _start(variant)
    from .commands.fit import Interrupted, run_fit

    with _progress() as bar:
        tasks = [
            bar.add_task(
                f"fit {k + 1}/{len(cfg.phases)}: {p.describe()}",
                total=p.steps,
            )
            for k, p in enumerate(cfg.phases)
        ]
        try:
            summary = run_fit(
                cfg, out, lambda k, n, loss: bar.update(tasks[k], completed=n), resume, holdout
            )
        except (InputError, KeyError) as err:  # before any work: leave no empty run folder
            if out.is_dir() and not any(out.iterdir()):
                out.rmdir()
            if isinstance(err, KeyError):  # a free key: name the config it came from
                err = ValueError(f"{config}: fit.free: {err.args[0]}")
            raise _fail(err, 2) from None
        except Interrupted:
            bar.stop()
            console.print(
                f"interrupted: checkpoint saved; resume with: layerfit fit {config} --out {out} "
                "--resume",
                highlight=False,
                soft_wrap=True,
            )
            raise typer.Exit(130) from None
    solvers = "+".join(p.solver for p in cfg.phases)
    table = RichTable(title=f"{config}: {solvers}, {summary['wall_time_s']:.1f} s")
    table.add_column("parameter", no_wrap=True)
    for column in ("start", "fitted", "std", "known", "error", "error/std"):
        table.add_column(column)

    def fmt(value):
        if value is None:
            return "-"
        value = np.ravel(value)
        if value.size > 3:  # a texture
            return f"{value.size} texels, mean {value.mean():.3f}, |max| {np.abs(value).max():.3f}"
        return ", ".join(f"{v:.4f}" for v in value)

    std = summary["std"] or {}
    for key, value in summary["values"].items():
        table.add_row(
            key,
            fmt(summary["start"].get(key)),
            fmt(value),
            fmt(std.get(key)),
            fmt(summary["truth"].get(key)),
            fmt(summary["error"].get(key)),
            fmt(summary["error_over_std"].get(key)),
        )
    console.print(table)
    if summary["poorly_determined"]:
        console.print(f"[yellow]poorly determined:[/] {', '.join(summary['poorly_determined'])}")
    if summary["std"] is None:
        console.print("no uncertainty: too many free components for a Jacobian (textures)")
    for report in summary["outcomes"]:
        if report["outcome"] in ("diverged", "failed") or report["rejected"]:
            console.print(
                f"[yellow]{report['solver']}:[/] {report['outcome']}: {report['message']}",
                highlight=False,
            )
    held = [v for v in summary["views"] if v["held_out"]]
    if held:
        scores = ", ".join(f"{v['name']} {v['rmse']:.3f}" for v in held)
        console.print(f"held-out views, relative RMSE: {scores}", highlight=False)
    console.print(f"run folder: {out} (preset.toml, summary.json, report.html)", highlight=False)


@app.command()
def export(
    preset: Annotated[
        Path, typer.Argument(help="Preset (TOML) to export, e.g. a run's preset.toml.")
    ],
    to: Annotated[str, typer.Option("--to", help="Target: mitsuba, materialx or usd.")],
    out: Annotated[
        Path | None, typer.Option(help="New output folder (default out/<preset name>-<target>).")
    ] = None,
    portable: Annotated[
        bool, typer.Option("--portable", help="Mitsuba: built-in plugins only (baked textures).")
    ] = False,
    force: Annotated[
        bool, typer.Option("--force", help="Replace an existing non-empty output folder.")
    ] = False,
    size: Annotated[int, typer.Option(help="Texels per side of baked images.")] = 1024,
    variant: VariantOption = None,
) -> None:
    """Export a preset to Mitsuba XML, MaterialX (OpenPBR) or USD (UsdPreviewSurface); what each
    target holds exactly, approximates or loses: README, "Export"."""
    from .export import TARGETS, check_output
    from .material import load_preset

    name = preset.parent.name if preset.stem == "preset" else preset.stem
    out = out or Path("out") / f"{name}-{to}{'-portable' if portable else ''}"
    try:
        if to not in TARGETS:
            raise InputError(f"--to {to!r}: choose one of {', '.join(TARGETS)}")
        check_output(out, force)
        loaded = load_preset(preset)
    except InputError as err:
        raise _fail(err, 2) from None
    _start(variant)
    from .export import export as export_preset

    with _progress() as bar:
        task = bar.add_task(
            f"{to}: bake {size}x{size}" if to != "mitsuba" or portable else to, total=None
        )
        try:
            path = export_preset(
                loaded,
                to,
                out,
                portable,
                force,
                size,
                lambda done, total: bar.update(task, completed=done, total=total),
            )
        except InputError as err:
            raise _fail(err, 2) from None
    console.print(f"wrote {path}", highlight=False)


def main() -> None:
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    try:
        app()
    except BackendError as err:  # raised outside _start, e.g. by a library call
        console.print(f"[red]error:[/] {err}", highlight=False, soft_wrap=True)
        sys.exit(1)
