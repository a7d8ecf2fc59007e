"""The `layerfit` command line: each command parses its options and calls its function in
`fit.commands` (usable from Python: docs/commands.md); failures are one line and an exit status."""

from __future__ import annotations

import enum
import functools
import math
from collections.abc import Callable
from pathlib import Path
from typing import Annotated

import typer

from captures.errors import InputError

from . import console as ui
from .errors import OutputError, Stopped
from .limits import MAX_SEED, MAX_SPP, QUALITIES
from .variant import BackendError, VariantError

# rich_markup_mode=None: help texts are plain (a "[truth]" in them is shown, not read as markup)
app = typer.Typer(
    add_completion=False,
    no_args_is_help=True,
    help=__doc__,
    rich_markup_mode=None,
    pretty_exceptions_enable=False,
)


def command(function: Callable) -> Callable:
    """A command of the app whose failures are one line and an exit status (2 for bad input, 1
    for what cannot run here or be written, 130 when stopped), however it is called."""

    @functools.wraps(function)
    def run(*args, **kwargs):
        try:
            return function(*args, **kwargs)
        except Stopped as err:  # a command stopped by Ctrl-C: what it kept
            if err.unwritten:  # a full disk: the partial report is not there
                ui.say("error:", "red", err.unwritten)
            ui.say("interrupted:", "yellow", str(err))
            raise typer.Exit(130) from None
        except (InputError, BackendError) as err:  # bad input, or what cannot run here
            ui.say("error:", "red", str(err))
            bad_input = isinstance(err, InputError | VariantError)
            raise typer.Exit(2 if bad_input and not isinstance(err, OutputError) else 1) from None

    return app.command()(run)


Variant = Annotated[
    str | None,
    typer.Option(
        "--variant", envvar="LAYERFIT_VARIANT", help="Mitsuba variant (default llvm_ad_rgb)."
    ),
]


#: `layerfit fit --quality`'s choices
Quality = enum.StrEnum("Quality", {name: name for name in QUALITIES})


Force = Annotated[bool, typer.Option("--force", help="Replace existing outputs.")]
Seed = Annotated[int, typer.Option(min=0, max=MAX_SEED, help="Random seed.")]


def _finite(low: float, high: float) -> Callable[[float], float]:
    """A float option's check: a finite number within [low, high] (click's own range check
    answered NaN with 'should be <= high')."""

    def check(value: float) -> float:
        if value is not None and not math.isfinite(value):
            raise typer.BadParameter(
                f"{value} is not a finite number; give one in [{low:g}, {high:g}]"
            )
        if value is not None and not low <= value <= high:
            raise typer.BadParameter(f"{value:g} is not in [{low:g}, {high:g}]")
        return value

    return check


def _number(low: float, high: float, text: str) -> typer.Option:
    return typer.Option(callback=_finite(low, high), help=text)


@command
def render(
    config: Annotated[
        Path, typer.Argument(help="Render config (TOML: scene, material) or a preset (--scene).")
    ],
    scene: Annotated[
        Path | None, typer.Option(help="TOML whose [scene] replaces the config's (a preset's).")
    ] = None,
    out: Annotated[
        Path, typer.Option(help="Output PNG (sRGB); a linear EXR is written beside it.")
    ] = Path("out/render.png"),
    spp: Annotated[
        int | None, typer.Option(min=1, max=MAX_SPP, help="Samples per pixel (the config's).")
    ] = None,
    seed: Seed = 0,
    force: Force = False,
    variant: Variant = None,
) -> None:
    """Render a config's scene with its material (or a preset's material in --scene's scene): a
    linear EXR and an sRGB PNG per view."""
    from .commands.render import render as run

    with ui.progress() as bar:
        run(config, scene, out, spp, seed, force, variant, bar, ui.wrote)


@command
def bench(
    spp: Annotated[
        int,  # at most 2^14: one render of the 480x360 scene under Mitsuba's 2^32 samples
        typer.Option(min=1, max=2**14, help="Samples per pixel of each timed render."),
    ] = 64,
    repeats: Annotated[int, typer.Option(min=1, help="Timed renders per case (median).")] = 7,
    only: Annotated[
        str | None,
        typer.Option(
            help="Run one table: bsdf, cup, fit, long, recovery, grid, profile, versus or "
            "relight (the last seven take minutes to hours: not run by default)."
        ),
    ] = None,
    fit_config: Annotated[
        Path | None,
        typer.Option(
            help="--only fit: the fit config whose schedules are compared (default "
            "configs/peer-sphere.toml); --only relight: a DiLiGenT fit config with held-out "
            "lights (default configs/diligent-pot1.toml)."
        ),
    ] = None,
    steps: Annotated[int, typer.Option(help="--only long: Adam steps of the long run.")] = 1000,
    size: Annotated[str, typer.Option(help="--only recovery, profile: WIDTHxHEIGHT.")] = "160x120",
    shapes: Annotated[
        str,
        typer.Option(help="--only recovery, grid: comma-separated shapes (sphere, torus, cup)."),
    ] = "sphere,torus",
    widths: Annotated[
        str, typer.Option(help="--only grid: comma-separated image widths (height: 3/4 of it).")
    ] = "64,128,256",
    seeds: Annotated[
        int | None,
        typer.Option(
            min=1,
            help="--only versus, quality: runs of each method (seeds; default 3); --only "
            "recovery: fit seeds of each case (default 1, the sweep's seed 0).",
        ),
    ] = None,
    cases: Annotated[
        str | None,
        typer.Option(
            help="--only recovery: comma-separated case labels (alpha 0.01, ior 1.05, dark "
            "pigment; default all)."
        ),
    ] = None,
    results: Annotated[
        Path | None,
        typer.Option(
            help="--only recovery, grid, versus, quality: JSON of finished cases (kept: a rerun "
            "resumes; default bench-<table>.json)."
        ),
    ] = None,
    out: Annotated[Path | None, typer.Option(help="Also write the tables (Markdown) here.")] = None,
    force: Force = False,
    ray: Annotated[
        bool, typer.Option("--ray", help="--only fit: each schedule a Ray task (a whole node).")
    ] = False,
    address: Annotated[str | None, typer.Option(help="--ray: join this Ray cluster.")] = None,
    variant: Variant = None,
) -> None:
    """Speed and accuracy tables: our BSDFs vs Mitsuba's built-ins, the cup's stack vs its layers,
    and (--only, minutes to hours) fit schedules, long runs, the recovery sweep, the grid, the
    profile of a fit, the default against the loop a Mitsuba user writes, relighting real
    photographs against per-pixel models (docs/benchmarks.md)."""
    options = dict(locals())
    from .bench import run

    with ui.progress() as bar:
        tables, written = run(**options, progress=bar)
    for table in tables:
        ui.console.print(table.rich())
    for path in written:
        ui.wrote(path)


@command
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
        int | None, typer.Option(min=1, max=MAX_SPP, help="Samples per pixel (the config's).")
    ] = None,
    seed: Annotated[
        int, typer.Option(min=0, max=MAX_SEED, help="Seed of the renders and the degradations.")
    ] = 0,
    shot: Annotated[
        float, _number(0, 1e6, "Shot noise: variance = shot x signal (0 to 1e6).")
    ] = 0.0,
    read: Annotated[float, _number(0, 1e6, "Read noise standard deviation (0 to 1e6).")] = 0.0,
    exposure_ev: Annotated[
        float, _number(0, 10, "Random exposure offset per view, +- EV (0 to 10).")
    ] = 0.0,
    exposure_base: Annotated[
        float, _number(-20, 20, "Exposure of every view, EV, -20 to 20 (negative: darker).")
    ] = 0.0,
    force: Annotated[
        bool, typer.Option("--force", help="Replace an existing capture folder at --out.")
    ] = False,
    variant: Variant = None,
) -> None:
    """Render a synthetic capture (images, manifest, [truth]) from a config (or a preset with
    --scene)."""
    from .commands.synth import Degradation
    from .commands.synth import synth as run

    degradation = Degradation(shot, read, exposure_ev, exposure_base)
    with ui.progress() as bar:
        path = run(config, out, scene, fmt, spp, seed, degradation, force, variant, bar)
    ui.wrote(path)


@command
def inspect(
    capture: Annotated[
        Path,
        typer.Argument(
            help="capture.toml (or its folder), a peer scene.json (or its folder), or a "
            "DiLiGenT folder."
        ),
    ],
    sheet: Annotated[
        Path | None, typer.Option(help="Contact sheet PNG (default: out/inspect-<name>.png).")
    ] = None,
    silhouette: Annotated[bool, typer.Option(help="Render the scene's silhouette (IoU).")] = True,
    downscale: Annotated[
        int, typer.Option(min=1, help="Area-average the images by this factor first.")
    ] = 1,
    force: Annotated[bool, typer.Option("--force", help="Replace an existing sheet.")] = False,
    variant: Variant = None,
) -> None:
    """A table of the views (size, gain, valid pixels, silhouette IoU) and a contact sheet."""
    from .commands.inspect import inspect as run

    note = functools.partial(ui.say, "note:", "yellow")
    ui.inspection(capture, run(capture, sheet, silhouette, downscale, force, variant, note))


@command
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
    starts: Annotated[
        int | None,
        typer.Option(min=1, help="Fit from this many starts on Ray workers, keep the best."),
    ] = None,
    quality: Annotated[
        Quality | None,
        typer.Option(help="Trade time for accuracy (default: the config's fit.quality)."),
    ] = None,
    seed: Annotated[
        int | None,
        typer.Option(min=0, max=MAX_SEED, help="Random seed (default: the config's fit.seed)."),
    ] = None,
    variant: Variant = None,
) -> None:
    """Fit the free material parameters to a capture into a run folder (preset, summary, report);
    print fitted vs known values."""
    from .commands.fit import fit as run

    quality = None if quality is None else quality.value
    with ui.progress() as bar:
        summary, folder = run(
            config, out, resume, force, holdout, starts, variant, bar, quality=quality, seed=seed
        )
    ui.fit_results(config, folder, summary)


@command
def batch(
    spec: Annotated[Path, typer.Argument(help="Batch spec (TOML): configs x captures x seeds.")],
    address: Annotated[
        str | None, typer.Option(help="Join this Ray cluster (default: start one here).")
    ] = None,
    num_cpus: Annotated[
        int | None, typer.Option(min=1, help="CPUs of the local Ray instance (default: all).")
    ] = None,
    variant: Variant = None,
) -> None:
    """Run a batch of fits as Ray tasks: one run folder per fit and an index (JSON, CSV, HTML);
    finished fits are skipped, a failed one is reported and the others run on."""
    from .commands.batch import batch as run

    def failed(entry: dict) -> None:
        ui.say("failed:", "red", f"{entry['name']}: {entry['error']}")

    with ui.progress() as bar:
        entries, index = run(spec, address, num_cpus, variant, bar, failed)
    counts = {s: sum(e["status"] == s for e in entries) for s in ("done", "skipped", "failed")}
    ui.console.print(
        f"{counts['done']} done, {counts['skipped']} already done, {counts['failed']} failed; "
        f"index: {index}",
        highlight=False,
        markup=False,
    )
    if counts["failed"]:
        raise typer.Exit(1)


@command
def export(
    preset: Annotated[
        Path,
        typer.Argument(help="Preset (TOML) to export, or a run folder (its preset.toml)."),
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
    size: Annotated[
        int,
        typer.Option(
            min=1, max=8192, help="Texels per side of baked images (8192: about 0.8 GB a colour)."
        ),
    ] = 1024,
    with_scene: Annotated[
        bool,
        typer.Option(
            "--with-scene",
            help="USD: the object's stage too (mesh, material, cameras, lights: scene.usda).",
        ),
    ] = False,
    capture: Annotated[
        Path | None,
        typer.Option(
            help="The capture of --with-scene (default: the one the preset's provenance names)."
        ),
    ] = None,
    variant: Variant = None,
) -> None:
    """Export a preset to Mitsuba XML, MaterialX (OpenPBR) or USD (UsdPreviewSurface), with
    --with-scene the object's USD stage too; what each target holds exactly, approximates or
    loses: docs/exports.md."""
    from .commands.export import export as run

    with ui.progress() as bar:
        path = run(preset, to, out, portable, force, size, variant, bar, with_scene, capture)
    ui.wrote(path)
