"""The `layerfit` command line."""

from __future__ import annotations

import contextlib
import errno
import functools
import logging
import math
import os
import shlex
import signal
import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Annotated

import numpy as np
import typer
from rich.console import Console
from rich.markup import escape
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from rich.text import Text

from captures.errors import InputError

from .limits import MAX_SEED, MAX_SPP
from .variant import BackendError, VariantError, select_variant

# rich_markup_mode=None: help texts are plain (a "[truth]" in them is shown, not read as markup)
app = typer.Typer(
    add_completion=False,
    no_args_is_help=True,
    help=__doc__,
    rich_markup_mode=None,
    pretty_exceptions_enable=False,
)
console = Console(stderr=True)
#: A fit's results (its table, held-out scores, the run folder) go to stdout, progress and
#: messages to stderr: `layerfit fit CONFIG > results.txt` keeps the table. Redirected, the table
#: is laid out 160 columns wide (rich's 80 cut its numbers short).
results = Console(width=None if sys.stdout.isatty() else 160)

VariantOption = Annotated[
    str | None,
    typer.Option(
        "--variant", envvar="LAYERFIT_VARIANT", help="Mitsuba variant (default llvm_ad_rgb)."
    ),
]


#: The scenes `bench` reads (`fit.commands.bench`): never one of its outputs.
BENCH_SCENES = (Path("configs/glazed-sphere.toml"), Path("configs/cup.toml"))
#: The most samples per pixel of a `bench` timed render: one render (no passes) of the 480x360
#: scene, its samples under Mitsuba's 2^32 a render.
BENCH_MAX_SPP = 2**14
#: Image types `render --out` writes.
IMAGE_SUFFIXES = (".png", ".exr", ".tif", ".tiff", ".jpg", ".jpeg")


#: Whether this run has said it was interrupted (`_run` says so where nothing did).
_said = {"interrupted": False}


#: Where a path holds a name longer than the file system allows (it was an internal error).
NAME_TOO_LONG = (
    "a name in this path is longer than the file system allows (255 bytes on most); choose a "
    "shorter one"
)


#: `inspect` notes views above this many pixels, with the `--downscale` that shows them at 1 M.
LARGE_VIEW = 2_000_000


def _say(label: str, style: str, text: str) -> None:
    """One unwrapped line `label text`, the text plain (brackets in it are shown, not markup)."""
    _said["interrupted"] |= "interrupted" in f"{label} {text}"
    console.print(Text.assemble((label, style), " ", str(text)), highlight=False, soft_wrap=True)


def _fail(err: Exception | str, code: int) -> typer.Exit:
    """Print one unwrapped error line; return the exit to raise."""
    _say("error:", "red", str(err))
    return typer.Exit(code)


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


@contextlib.contextmanager
def _interruptible(what: Callable[[], str]) -> Iterator[None]:
    """Ctrl-C (or SIGTERM) inside: one line saying what was kept (`what()`), exit 130."""
    try:
        yield
    except KeyboardInterrupt:
        raise _fail(f"interrupted: {what()}", 130) from None


def _check_capture_cameras(scene, path: Path) -> None:
    """Refuse cameras whose views a capture cannot hold (what its loader refuses: synth wrote
    them, and inspect and fit then refused the capture): under `MIN_SIDE` pixels a side, or not
    seeing the object."""
    from captures.capture import MIN_SIDE, check_cameras_see

    for i, camera in enumerate(scene.cameras):
        if min(camera.width, camera.height) < MIN_SIDE:
            raise InputError(
                f"{path}: scene.cameras[{i}] is {camera.width}x{camera.height}: a capture's views "
                f"need at least {MIN_SIDE} pixels a side; give a larger width and height"
            )
    check_cameras_see(scene, lambda i: f"{path}: scene.cameras[{i}]")


def _scene_and_material(config: Path, scene: Path | None):
    """(scene, material, spp) of a render config or a preset, the scene replaced by `scene`'s."""
    from captures import CaptureError, parse_scene
    from captures.model import toml_kind

    from .config import load_render_config
    from .material import check_uvs, load_preset, read_toml

    doc = read_toml(config)
    kind = toml_kind(doc)
    if kind in ("a fit config", "a batch spec", "a capture manifest"):
        raise CaptureError(
            f"{config}: is {kind}; give a render config (a material and a [scene]) or a preset "
            "with --scene SCENE.toml"
        )
    if "schema" in doc:  # a preset: the material only
        if scene is None:
            raise CaptureError(f"{config}: is a preset (a material); give --scene SCENE.toml")
        material, spp = load_preset(config).material, 64
    else:
        cfg = load_render_config(config)
        material, spp = cfg.material, cfg.spp
        if scene is None:
            check_uvs(cfg.scene, material)
            return cfg.scene, material, spp
    try:
        table = read_toml(scene)
        if "scene" not in table:
            raise CaptureError(f"{scene}: no [scene] table; give a TOML file with one")
        if toml_kind(table) == "a capture manifest":  # its cameras are its views'
            raise CaptureError(
                f"{scene}: is a capture manifest (its cameras are in its [[views]]); give a "
                "TOML file with a [scene] and its [[scene.cameras]] (configs/glazed-sphere-"
                "views.toml is one)"
            )
        the_scene = parse_scene(table["scene"], scene)
        check_uvs(the_scene, material)
        return the_scene, material, spp
    except InputError as err:  # name the option the file came from
        raise CaptureError(f"--scene {err}") from None


def _start(variant: str | None) -> None:
    """Select the variant and register the plugins, or stop with one line. A Ctrl-C meanwhile
    waits until they are done (`entry.deferred`), and one a library swallowed earlier is
    honoured here."""
    from . import entry

    with entry.deferred():
        try:
            select_variant(variant)
        except VariantError as err:
            raise _fail(err, 2) from None
        except BackendError as err:
            raise _fail(err, 1) from None
        import materials

        materials.register()
    if entry.asked():
        raise KeyboardInterrupt


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
        int | None,
        typer.Option(min=1, max=MAX_SPP, help="Samples per pixel (overrides the config)."),
    ] = None,
    seed: Annotated[int, typer.Option(min=0, max=MAX_SEED, help="Random seed.")] = 0,
    force: Annotated[bool, typer.Option("--force", help="Replace existing output images.")] = False,
    variant: VariantOption = None,
) -> None:
    """Render a config's scene with its material (or a preset's material in --scene's scene): a
    linear EXR and an sRGB PNG per view."""
    from captures.files import check_output
    from captures.images import write_image

    try:
        the_scene, material, config_spp = _scene_and_material(config, scene)
        views = len(the_scene.cameras)
        paths = []
        if out.is_dir():
            raise InputError(f"--out {out}: is a folder; give an image file name (e.g. a.png)")
        base = out.name[: -len(out.suffix)] if out.suffix else out.name  # only the last suffix
        for view in range(views):
            name = base if views == 1 else f"{base}_{view:02d}"
            # the linear EXR, and the image asked for (b.EXR is that EXR: written once)
            suffixes = (out.suffix,) if out.suffix.lower() == ".exr" else (".exr", out.suffix)
            files = dict.fromkeys(out.with_name(name + s) for s in suffixes)
            paths.append(list(files))
        inputs = _inputs(config, scene, the_scene, material)
        for path in (p for files in paths for p in files):
            check_output(path, "--out", force=force, inputs=inputs, suffixes=IMAGE_SUFFIXES)
    except InputError as err:
        raise _fail(err, 2) from None
    _start(variant)

    from .render import load_scene, scene_dict
    from .render import render as render_image

    spp = spp or config_spp
    written = 0
    n_files = sum(map(len, paths))
    with _interruptible(lambda: f"wrote {written} of {n_files} images"), _progress() as bar:
        for view in range(views):
            task = bar.add_task(f"view {view}", total=spp)
            loaded = load_scene(scene_dict(the_scene, material.bsdf, view, spp))
            image = render_image(loaded, spp, seed, lambda n, t=task: bar.update(t, completed=n))
            for path in paths[view]:
                write_image(path, image)
                written += 1
                console.print(f"wrote {path}", markup=False, highlight=False)


def _inputs(config: Path, scene_file: Path | None, scene, material) -> list[Path]:
    """Every file a render reads: the config, the scene file, textures, mesh, environment."""
    from captures.scene import EnvMap, ObjFile

    files = [config, *material.texture_files().values()]
    if scene_file is not None:
        files.append(scene_file)
    if isinstance(scene.geometry, ObjFile):
        files.append(scene.geometry.path)
    if isinstance(scene.environment, EnvMap):
        files.append(scene.environment.path)
    return files


@app.command()
def bench(
    spp: Annotated[
        int,
        typer.Option(min=1, max=BENCH_MAX_SPP, help="Samples per pixel of each timed render."),
    ] = 64,
    repeats: Annotated[
        int, typer.Option(min=1, help="Timed renders per case (median reported).")
    ] = 7,
    only: Annotated[
        str | None,
        typer.Option(
            help="Run one table: bsdf, cup, fit, long, recovery, grid, profile or versus (the "
            "last six take minutes to hours: not run by default)."
        ),
    ] = None,
    fit_config: Annotated[
        Path, typer.Option(help="--only fit: the fit config whose schedules are compared.")
    ] = Path("configs/peer-sphere.toml"),
    steps: Annotated[int, typer.Option(help="--only long: Adam steps of the long run.")] = 1000,
    size: Annotated[
        str, typer.Option(help="--only recovery, profile: each view's WIDTHxHEIGHT.")
    ] = "160x120",
    shapes: Annotated[
        str,
        typer.Option(help="--only recovery, grid: comma-separated shapes (sphere, torus, cup)."),
    ] = "sphere,torus",
    widths: Annotated[
        str, typer.Option(help="--only grid: comma-separated image widths (height: 3/4 of it).")
    ] = "64,128,256",
    seeds: Annotated[
        int, typer.Option(min=1, help="--only versus: runs of each method (seeds 0, 1, ...).")
    ] = 3,
    results: Annotated[
        Path | None,
        typer.Option(
            help="--only recovery, grid, versus: JSON of finished cases (kept: a rerun resumes; "
            "default bench-<table>.json)."
        ),
    ] = None,
    out: Annotated[Path | None, typer.Option(help="Also write the tables (Markdown) here.")] = None,
    force: Annotated[bool, typer.Option("--force", help="Replace an existing --out.")] = False,
    ray: Annotated[
        bool, typer.Option("--ray", help="--only fit: each schedule a Ray task (a whole node).")
    ] = False,
    address: Annotated[
        str | None, typer.Option(help="--ray: join this Ray cluster (default: start one here).")
    ] = None,
    variant: VariantOption = None,
) -> None:
    """Speed tables: our BSDFs vs Mitsuba's built-ins, the cup's stack vs its layers, (with
    --only fit, minutes) fit schedules' wall time vs accuracy, and (with --only long) time and
    memory per step over a long Adam run, plotted to a PNG beside --out (or bench-long.png)."""
    from captures.files import check_output, write_text

    from .output.figures import drawn_by_layerfit

    if only not in (None, "bsdf", "cup", "fit", "long", "recovery", "grid", "profile", "versus"):
        raise _fail(
            f"--only {only!r}: unknown table; choose bsdf, cup, fit, long, recovery, grid, "
            "profile or versus",
            2,
        )
    if steps < 2:
        raise _fail(f"--steps {steps}: give at least 2", 2)
    missing = [s for s in BENCH_SCENES if not s.is_file()]
    if only in (None, "bsdf", "cup") and missing:
        raise _fail(
            f"{missing[0]}: not found from {Path.cwd()}; run layerfit bench from the repository "
            "root (it reads the bundled configs)",
            2,
        )
    width, height, shape_list = (
        _recovery_options(size, shapes) if only in ("recovery", "grid", "profile") else (0, 0, [])
    )
    if only == "grid":
        _widths(widths)
    plot = (
        (out.with_suffix(".png") if out else Path(f"bench-{only}.png"))
        if only in ("long", "grid", "versus")
        else None
    )
    results = results or Path(f"bench-{only}.json")
    if results.is_dir():
        raise _fail(f"--results {results}: is a folder; give a JSON file name", 2)
    try:
        inputs = [fit_config, *BENCH_SCENES]
        if only in ("recovery", "grid", "versus"):
            inputs.append(results)  # a resumable run's finished cases are never overwritten
        if out is not None:
            check_output(out, "--out", force=force, inputs=inputs)
            if plot is not None and out.resolve() == plot.resolve():
                raise InputError(
                    f"--out {out}: the tables and the plot would share it (the plot is PNG); "
                    "give the tables a .md name"
                )
        if plot is not None:
            # a resumed run redraws its own plot (tagged by layerfit); never a user's file
            redraw = force or drawn_by_layerfit(plot)
            check_output(plot, "--out (its plot)", force=redraw, inputs=inputs)
        if only in ("recovery", "grid", "versus"):  # resumed: rewritten, its cases kept
            check_output(results, "--results", force=True)
    except InputError as err:
        raise _fail(err, 2) from None
    _start(variant)
    from .commands.bench import (
        bsdf_speed_table,
        cup_speed_table,
        fit_trade_table,
        grid_cells,
        grid_table,
        long_run,
        long_run_table,
        plot_long_run,
        profile_table,
        recovery_table,
        versus_table,
    )

    tables = []
    with _progress() as bar:
        try:  # the scenes are read from configs/ under the working directory
            if only in (None, "bsdf"):
                tables.append(bsdf_speed_table(spp=spp, repeats=repeats, progress=bar))
            if only in (None, "cup"):
                tables.append(cup_speed_table(spp=spp, repeats=repeats, progress=bar))
            if only == "fit":
                tables.append(fit_trade_table(fit_config, None, bar, ray, address))
            if only == "long":
                run = long_run(steps=steps, progress=bar)
                tables.append(long_run_table(run))
                console.print(f"wrote {plot_long_run(run, plot)}", markup=False)
            if only == "recovery":
                from .recovery import sweep

                cases = sweep(tuple(shape_list))
                tables.append(recovery_table(cases, width, height, results, bar))
            if only == "profile":
                tables.append(profile_table(width))
            if only == "grid":
                cells = grid_cells(tuple(shape_list), _widths(widths))
                tables.append(grid_table(cells, results, bar, plot=plot))
                console.print(f"wrote {plot}", markup=False)
            if only == "versus":
                tables.append(versus_table(seeds, results, bar, plot=plot))
                console.print(f"wrote {plot}", markup=False)
        except (InputError, ValueError) as err:
            raise _fail(err, 2) from None
    for table in tables:
        console.print(table.rich())
    if out is not None:
        write_text(out, "\n".join(t.markdown() for t in tables))
        console.print(f"wrote {out}", markup=False, highlight=False)


def _widths(text: str) -> tuple[int, ...]:
    """--widths, checked (exit 2 with the fix)."""
    parts = [p.strip() for p in text.split(",") if p.strip()]
    if not parts or not all(p.isdigit() and int(p) >= 16 for p in parts):
        raise _fail(f"--widths {text!r}: not widths; give comma-separated numbers, each >= 16", 2)
    return tuple(int(p) for p in parts)


def _recovery_options(size: str, shapes: str) -> tuple[int, int, list[str]]:
    """--size WxH and --shapes, checked (exit 2 with the fix)."""
    from .recovery import SHAPES

    parts = size.lower().split("x")
    if len(parts) != 2 or not all(p.isdigit() and int(p) >= 8 for p in parts):
        raise _fail(f"--size {size!r}: not a size; give WIDTHxHEIGHT, each at least 8 (160x120)", 2)
    names = [s.strip() for s in shapes.split(",") if s.strip()]
    unknown = [s for s in names if s not in SHAPES]
    if not names or unknown:
        raise _fail(f"--shapes {shapes!r}: unknown shape; choose from {', '.join(SHAPES)}", 2)
    return int(parts[0]), int(parts[1]), names


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
        int | None,
        typer.Option(min=1, max=MAX_SPP, help="Samples per pixel (default: the config's)."),
    ] = None,
    seed: Annotated[
        int, typer.Option(min=0, max=MAX_SEED, help="Seed of the renders and the degradations.")
    ] = 0,
    shot: Annotated[
        float,
        typer.Option(
            callback=_finite(0, 1e6), help="Shot noise: variance = shot x signal (0 to 1e6)."
        ),
    ] = 0.0,
    read: Annotated[
        float,
        typer.Option(callback=_finite(0, 1e6), help="Read noise standard deviation (0 to 1e6)."),
    ] = 0.0,
    exposure_ev: Annotated[
        float,
        typer.Option(
            callback=_finite(0, 10), help="Random exposure offset per view, +- EV (0 to 10)."
        ),
    ] = 0.0,
    exposure_base: Annotated[
        float,
        typer.Option(
            callback=_finite(-20, 20),
            help="Exposure of every view, EV, -20 to 20 (negative: darker, fewer clipped).",
        ),
    ] = 0.0,
    force: Annotated[
        bool, typer.Option("--force", help="Replace an existing capture folder at --out.")
    ] = False,
    variant: VariantOption = None,
) -> None:
    """Render a synthetic capture (images, manifest, [truth]) from a config (or a preset with
    --scene)."""
    from captures.files import check_output, refuse_foreign

    try:
        the_scene, material, config_spp = _scene_and_material(config, scene)
        _check_capture_cameras(the_scene, scene or config)
        if fmt not in ("exr", "png", "jpg"):
            raise InputError(f"--format {fmt!r}: unknown format; choose one of exr, png, jpg")
        inputs = _inputs(config, scene, the_scene, material)
        check_output(out, "--out", force=force, inputs=inputs, folder=True)
        if out.is_dir() and any(out.iterdir()) and not (out / "capture.toml").is_file():
            raise InputError(
                f"--out {out}: is a folder but not a capture (no capture.toml); --force replaces "
                "only a capture folder: choose another path"
            )
        if out.is_dir() and (out / "capture.toml").is_file() and not _synthetic(out):
            raise InputError(
                f"--out {out}: holds photographs (its capture.toml has no [truth]); --force "
                "replaces only a capture made by synth: choose another path"
            )
        if out.is_dir() and (out / "capture.toml").is_file():
            refuse_foreign(out, out / "capture.toml", "synth")
    except InputError as err:
        raise _fail(err, 2) from None
    _start(variant)
    from .commands.synth import Degradation, synthesize

    spp = spp or config_spp
    with _interruptible(lambda: "nothing written"), _progress() as bar:
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
                replace=force,
            )
        except (InputError, FileExistsError) as err:
            raise _fail(err, 2) from None
    console.print(f"wrote {path}", markup=False, highlight=False)


def _synthetic(folder: Path) -> bool:
    """Whether a capture folder was made by `synth` (its manifest holds the [truth]); an
    unreadable manifest counts as not."""
    import tomllib

    try:
        return "truth" in tomllib.loads((folder / "capture.toml").read_text(encoding="utf-8-sig"))
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError):
        return False


@app.command()
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
    variant: VariantOption = None,
) -> None:
    """A table of the views (size, gain, valid pixels, silhouette IoU) and a contact sheet."""
    from rich.table import Table as RichTable

    from captures import open_capture
    from captures.capture import MIN_SIDE
    from captures.files import check_output

    from .output.figures import drawn_by_layerfit

    named = capture.resolve()  # `.` is named by its folder (the sheet was "inspect-.png")
    if named.name in ("scene.json", "capture.toml"):
        named = named.parent
    given, sheet = sheet is not None, sheet or Path("out") / f"inspect-{named.stem}.png"
    try:
        cap = open_capture(capture, downscale, "--downscale")
        small = min(cap.views, key=lambda v: min(v.camera.width, v.camera.height))
        if min(small.camera.width, small.camera.height) < MIN_SIDE:
            raise InputError(
                f"--downscale {downscale}: leaves view {small.name} "
                f"{small.camera.width}x{small.camera.height}: at least {MIN_SIDE} pixels a "
                "side; give a smaller factor"
            )
        folder = Path(cap.path or capture)
        folder = folder if folder.is_dir() else folder.parent
        if sheet.resolve().is_relative_to(folder.resolve()):
            what = f"--sheet {sheet}" if given else f"the default sheet {sheet} (give --sheet)"
            raise InputError(
                f"{what}: is inside the capture folder {folder}; write the sheet "
                "elsewhere (a capture's files are never overwritten)"
            )
        # run again, inspect redraws its own default sheet (tagged by layerfit); a sheet named
        # with --sheet, or a file layerfit did not draw, only with --force
        redraw = force or (not given and drawn_by_layerfit(sheet))
        check_output(sheet, "--sheet", force=redraw, inputs=[capture], suffixes=(".png",))
    except InputError as err:
        raise _fail(err, 2) from None
    big = max(cap.views, key=lambda v: v.camera.width * v.camera.height).camera
    if silhouette and big.width * big.height > LARGE_VIEW:  # 6000x4000 x 3: 2 min, 7 GB, silent
        factor = downscale * math.ceil(math.sqrt(big.width * big.height / 1e6))
        _say(
            "note:",
            "yellow",
            f"views of up to {big.width}x{big.height}: rendering their silhouettes takes "
            f"minutes and gigabytes; --downscale {factor} shows them at about 1 M pixels (or "
            "--no-silhouette)",
        )
    _start(variant)
    from .commands.inspect import contact_sheet, silhouettes, summary

    with _interruptible(lambda: "no sheet written"):
        coverage = silhouettes(cap) if silhouette else None
        rows = summary(cap, coverage)
        table = RichTable(
            title=escape(f"{capture}: {len(rows)} views, {_geometry_text(cap.scene.geometry)}")
        )
        for column in ("view", "size", "gain", "valid", "max", "iou"):
            table.add_column(column)
        for row in rows:
            table.add_row(
                escape(row["view"]),
                row["size"],
                f"{row['gain']:.3g}",
                f"{row['valid']:.1%}",
                f"{row['max']:.3g}",
                f"{row['iou']:.3f}" if "iou" in row else "-",
            )
        console.print(table)
        from .render.scene import overlap_warning

        overlaps = {row["view"]: row["iou"] for row in rows if "iou" in row}
        if low := overlap_warning(str(capture), overlaps, len(rows)):  # as `fit` warns
            _say("warning:", "yellow", low)
        out = contact_sheet(cap, coverage, sheet, SHEET_VIEWS)
    shown = "" if len(cap.views) <= SHEET_VIEWS else f" (the first {SHEET_VIEWS} views)"
    console.print(f"wrote {out}{shown}", markup=False, highlight=False)


#: The views a contact sheet shows (the table lists all).
SHEET_VIEWS = 8


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
    starts: Annotated[
        int | None,
        typer.Option(min=1, help="Fit from this many starts on Ray workers, keep the best."),
    ] = None,
    variant: VariantOption = None,
) -> None:
    """Fit the free material parameters to a capture into a run folder (preset, summary, report);
    print fitted vs known values."""
    from rich.table import Table as RichTable

    from .config import load_fit_config

    out = out or Path("out") / config.stem
    first_new = out  # the outermost folder this command would create
    while not first_new.parent.exists() and first_new.parent != first_new:
        first_new = first_new.parent
    created = not out.exists()
    try:
        cfg = load_fit_config(config)
        if starts is not None:
            cfg = _with_starts(cfg, starts, resume)
        from .commands.fit import check_output

        check_output(out, cfg, resume, force)
    except InputError as err:
        raise _fail(err, 2) from None

    def forget_out() -> None:  # a failed start leaves no empty run folder (nor its parents)
        folder = out
        while created and folder.is_dir() and not any(folder.iterdir()):
            folder.rmdir()
            if folder == first_new:
                break
            folder = folder.parent

    try:
        _start(variant)
    except typer.Exit:
        forget_out()
        raise
    except KeyboardInterrupt:
        forget_out()
        raise _fail("interrupted before the fit began: nothing written", 130) from None
    from . import entry
    from .batch import Cancelled
    from .commands.fit import Interrupted, check_resume, prepare, run_fit
    from .errors import OutputError

    try:
        prepared = prepare(cfg, holdout)  # reads the photos: a Ctrl-C stops it at once
        if entry.asked():  # one that JAX's gc callback swallowed meanwhile
            raise KeyboardInterrupt
        if resume:  # before any progress bar: a checkpoint of another fit is one line
            check_resume(prepared, cfg, out)
    except InputError as err:
        forget_out()
        raise _fail(err, 2) from None
    except KeyboardInterrupt:
        forget_out()
        raise _fail("interrupted before the fit began: nothing written", 130) from None
    except Exception:  # an internal error: reported by the caller, no empty run folder left
        forget_out()
        raise
    with _progress() as bar:
        tasks = [
            bar.add_task(
                f"fit {k + 1}/{len(cfg.phases)}: {p.describe(cfg.downscale)}",
                total=p.steps,
            )
            for k, p in enumerate(cfg.phases if cfg.starts == 1 else ())
        ]
        if cfg.starts > 1:
            tasks.append(bar.add_task(f"{cfg.starts} starts on Ray workers", total=cfg.starts))
        try:
            summary = run_fit(
                cfg,
                out,
                lambda k, n, loss: bar.update(tasks[k], completed=n),
                resume,
                holdout,
                prepared,
                lambda k, row: bar.advance(tasks[-1]),
            )
        except InputError as err:  # a run folder that cannot be written: not bad input
            forget_out()
            raise _fail(err, 1 if isinstance(err, OutputError) else 2) from None
        except (Interrupted, KeyboardInterrupt) as err:
            bar.stop()
            forget_out()
            if getattr(err, "unwritten", None):  # a full disk: the partial report is not there
                _say("error:", "red", err.unwritten)
            _say("interrupted:", "yellow", _stopped(err, config, out, holdout, variant, starts))
            raise typer.Exit(130) from None
        except Cancelled as err:  # --starts: the Ray tasks were cancelled
            bar.stop()
            forget_out()
            _say("interrupted:", "yellow", f"{err}; nothing written")
            raise typer.Exit(130) from None
        except Exception:  # an internal error (a checkpoint already saved is kept)
            bar.stop()
            forget_out()
            raise
    from .material.free import bound_note

    solvers = "+".join(p.solver for p in cfg.phases)
    table = RichTable(title=escape(f"{config}: {solvers}, {summary['wall_time_s']:.1f} s"))
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
            escape(key),
            fmt(summary["start"].get(key)),
            fmt(value),
            fmt(std.get(key)),
            fmt(summary["truth"].get(key)),
            fmt(summary["error"].get(key)),
            fmt(summary["error_over_std"].get(key)),
        )
    results.print(table)
    if summary["poorly_determined"]:
        _say("poorly determined:", "yellow", ", ".join(summary["poorly_determined"]))
    for bound in summary["at_bounds"]:
        _say("at a bound:", "yellow", bound_note(bound, len(summary.get("starts") or ()) or 1))
    if summary["std"] is None:
        results.print("no uncertainty: too many free components for a Jacobian (textures)")
    for report in summary["outcomes"]:
        if report["outcome"] in ("diverged", "failed") or report["rejected"]:
            _say(f"{report['solver']}:", "yellow", f"{report['outcome']}: {report['message']}")
    if "starts" in summary:
        _print_starts(summary["starts"])
    held = [v for v in summary["views"] if v["held_out"]]
    if held:
        scores = ", ".join(f"{v['name']} {v['rmse']:.3f}" for v in held)
        results.print(f"held-out views, relative RMSE: {scores}", highlight=False, markup=False)
    results.print(
        f"run folder: {out} (preset.toml, summary.json, report.html)", highlight=False, markup=False
    )


def _stopped(err, config, out, holdout, variant, starts) -> str:
    """What a stopped fit left: its checkpoint (the stop's own state, or an earlier one when a
    full disk kept that from being written) and how to resume it."""
    if not (out / "checkpoint.npz").exists():
        return "nothing to resume (stopped before the first checkpoint)"
    what = (
        "checkpoint saved"
        if getattr(err, "saved", True)
        else "the stop's state could not be saved (an earlier checkpoint is kept)"
    )
    return f"{what}; resume with: {_resume_command(config, out, holdout, variant, starts)}"


def _resume_command(
    config: Path, out: Path, holdout: int | None, variant: str | None, starts: int | None = None
) -> str:
    """The command that resumes this fit: its config, run folder and the options that change
    what is fitted (a resume without `--holdout` is refused as another fit), each quoted for a
    shell."""
    words = ["layerfit", "fit", str(config), "--out", str(out), "--resume"]
    words += ["--holdout", str(holdout)] if holdout is not None else []
    words += ["--variant", variant] if variant else []
    words += ["--starts", str(starts)] if starts is not None else []  # 1 over a config's many
    return shlex.join(words)


def _with_starts(cfg, starts: int, resume: bool):
    """`cfg` with `--starts` in place of `fit.starts`."""
    import dataclasses

    if starts > 1 and resume:
        raise InputError(f"--starts {starts}: a multi-start fit has no checkpoint to --resume")
    return dataclasses.replace(cfg, settings=cfg.settings.model_copy(update={"starts": starts}))


def _print_starts(rows: list[dict]) -> None:
    """The multi-start spread: each start's start and fitted values and its common loss."""
    from rich.table import Table as RichTable

    def fmt(value):
        return ", ".join(f"{v:.4g}" for v in np.ravel(value))

    table = RichTable(title="starts (the best by the common high-spp loss)")
    for column in ("start", "from", "fitted", "loss", "wall s"):
        table.add_column(column)
    for row in rows:
        table.add_row(
            f"{row['start']}{' (best)' if row['best'] else ''}",
            "; ".join(f"{k} {fmt(v)}" for k, v in row["start_values"].items()),
            "; ".join(f"{k} {fmt(v)}" for k, v in row["values"].items()),
            f"{row['loss']:.6g}" if row["loss"] is not None else escape(f"failed: {row['error']}"),
            f"{row['wall_time_s']:.0f}",
        )
    results.print(table)


@app.command()
def batch(
    spec: Annotated[Path, typer.Argument(help="Batch spec (TOML): configs x captures x seeds.")],
    address: Annotated[
        str | None, typer.Option(help="Join this Ray cluster (default: start one here).")
    ] = None,
    num_cpus: Annotated[
        int | None, typer.Option(min=1, help="CPUs of the local Ray instance (default: all).")
    ] = None,
    variant: VariantOption = None,
) -> None:
    """Run a batch of fits as Ray tasks: one run folder per fit and an index (JSON, CSV, HTML);
    finished fits are skipped, a failed one is reported and the others run on."""
    from .batch import Cancelled, load_batch, run_batch
    from .batch.cluster import check_address

    try:
        the_batch = load_batch(spec)
        if address is not None:
            check_address(address)
        elif os.environ.get("RAY_ADDRESS"):
            check_address(os.environ["RAY_ADDRESS"], "RAY_ADDRESS")
    except InputError as err:
        raise _fail(err, 2) from None
    _start(variant)
    with _progress() as bar:
        task = bar.add_task(f"{len(the_batch.jobs)} fits", total=len(the_batch.jobs))

        def progress(entry: dict, done: int, total: int) -> None:
            bar.update(task, completed=done)
            if entry["status"] == "failed":
                _say("failed:", "red", f"{entry['name']}: {entry['error']}")

        try:
            entries = run_batch(the_batch, progress, address, num_cpus)
        except InputError as err:
            bar.stop()
            raise _fail(err, 2) from None
        except Cancelled as err:
            bar.stop()
            _say("interrupted:", "yellow", str(err))
            raise typer.Exit(130) from None
    counts = {s: sum(e["status"] == s for e in entries) for s in ("done", "skipped", "failed")}
    console.print(
        f"{counts['done']} done, {counts['skipped']} already done, {counts['failed']} failed; "
        f"index: {the_batch.out / 'index.html'}",
        highlight=False,
        markup=False,
    )
    if counts["failed"]:
        raise typer.Exit(1)


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
    size: Annotated[
        int,
        typer.Option(
            min=1,
            max=8192,
            help="Texels per side of baked images (8192: about 0.8 GB per baked colour).",
        ),
    ] = 1024,
    variant: VariantOption = None,
) -> None:
    """Export a preset to Mitsuba XML, MaterialX (OpenPBR) or USD (UsdPreviewSurface); what each
    target holds exactly, approximates or loses: README, "Export"."""
    from .export import TARGETS, check_output, inputs_of
    from .material import load_preset

    name = preset.resolve().parent.name if preset.stem == "preset" else preset.stem
    out = out or Path("out") / f"{name}-{to}{'-portable' if portable else ''}"
    try:
        if to not in TARGETS:
            raise InputError(f"--to {to!r}: choose one of {', '.join(TARGETS)}")
        loaded = load_preset(preset)
        check_output(out, force, inputs_of(loaded))
    except InputError as err:
        raise _fail(err, 2) from None
    _start(variant)
    from .export import export as export_preset

    what = f"nothing written ({out} as it was)"
    with _interruptible(lambda: what), _progress() as bar:
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
    console.print(f"wrote {path}", highlight=False, markup=False)


def _geometry_text(geometry) -> str:
    """The capture's object in a few words, for `inspect`'s title."""
    from captures.scene import Cup, MeshArrays, ObjFile, Sphere

    if isinstance(geometry, Sphere):
        return f"a sphere of radius {geometry.radius:.4g}"
    if isinstance(geometry, Cup):
        return "the procedural cup"
    if isinstance(geometry, ObjFile):
        return f"mesh {Path(geometry.path).name}"
    if isinstance(geometry, MeshArrays):
        return f"a height field of {len(geometry.data.faces)} triangles"
    return type(geometry).__name__


class _Plain(logging.Formatter):
    """Log records as the CLI's own lines: `warning: the message` (each said once)."""

    def format(self, record: logging.LogRecord) -> str:
        return f"{record.levelname.lower()}: {record.getMessage()}"


def _terminate(signum, frame) -> None:
    """SIGTERM stops like Ctrl-C: partial outputs are removed (a fit keeps its checkpoint)."""
    raise KeyboardInterrupt


def main(argv: list[str] | None = None) -> None:
    """The `layerfit` entry point: every failure is one line on stderr and an exit status (2 for
    bad input or usage, 130 when interrupted, 1 otherwise); `LAYERFIT_DEBUG=1` shows
    tracebacks of unexpected errors."""
    logging.basicConfig(level=logging.WARNING, format="%(message)s")
    logging.getLogger().handlers[0].setFormatter(_Plain())
    previous = None
    with contextlib.suppress(ValueError):  # only the main thread may set handlers
        previous = signal.signal(signal.SIGTERM, _terminate)
    try:
        code = _run(argv)
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
    sys.exit(code)


@functools.cache
def _command():
    """The app's click command, built once (typer rebuilds it on every call otherwise)."""
    return typer.main.get_command(app)


def _run(argv: list[str] | None) -> int:
    """Run the app; the exit status, every failure printed as one line."""
    _said["interrupted"] = False
    code = _run_app(argv)
    if code == 130 and not _said["interrupted"]:  # typer returns 130 for a KeyboardInterrupt
        _say("interrupted:", "yellow", "stopped by Ctrl-C or SIGTERM")  # that left a command
    return code


def _run_app(argv: list[str] | None) -> int:
    """`_run`'s work: the app's exit status, a failure printed as one line."""
    from . import entry

    try:
        code = _command().main(args=argv, prog_name="layerfit", standalone_mode=False)
    except typer.TyperException as err:  # usage: an unknown option, a value out of range
        if type(err).__name__ == "NoArgsIsHelpError":  # `layerfit` alone: the help
            err.show()
        else:
            ctx = getattr(err, "ctx", None)
            where = f"; see '{ctx.command_path} --help'" if ctx is not None else ""
            _say("error:", "red", f"{err.format_message().rstrip('.')}{where}")
        code = err.exit_code
    except typer.Abort:  # Ctrl-C before a command's own handling (click's)
        _say("interrupted:", "yellow", "stopped by Ctrl-C or SIGTERM")
        code = 130
    except KeyboardInterrupt:  # outside click's own handling (typer building the command)
        code = 130  # `_run` says so
    except BackendError as err:  # raised outside _start, e.g. by a library call
        _say("error:", "red", str(err))
        code = 1
    except InputError as err:  # a command that let one through
        from .errors import OutputError

        _say("error:", "red", str(err))
        code = 1 if isinstance(err, OutputError) else 2
    except Exception as err:
        if entry.asked():  # a Ctrl-C inside a library's import or callback, surfaced as another
            return 130  # error (drjit's import: a NameError)
        if isinstance(err, OSError) and err.errno == errno.ENAMETOOLONG:  # a path's long name
            _say("error:", "red", f"{err.filename}: {NAME_TOO_LONG}")
            return 2
        if os.environ.get("LAYERFIT_DEBUG"):
            raise
        first = (str(err).strip().splitlines() or [""])[0][:300]
        _say(
            "error:",
            "red",
            f"internal error ({type(err).__name__}: {first}); please report it with the "
            "command (LAYERFIT_DEBUG=1 shows the traceback)",
        )
        code = 1
    return code if isinstance(code, int) else 0
