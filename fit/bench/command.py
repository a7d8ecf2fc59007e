"""`layerfit bench` without its command line: the options checked before any work, the Mitsuba
variant chosen, the tables asked for run, and their plot and Markdown written."""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

from captures.errors import InputError

from .common import CUP_SCENE, DEFAULT_SCENE, Table

#: The scenes the speed tables read (from the working directory): never one of a run's outputs.
SCENES = (DEFAULT_SCENE, CUP_SCENE)
#: The most samples per pixel of a timed render: one render (no passes) of the 480x360 scene,
#: its samples under Mitsuba's 2^32 a render.
MAX_SPP = 2**14
#: The tables `only` names. Without `only` the first two run; the others take minutes to hours.
TABLES = (
    "bsdf",
    "cup",
    "fit",
    "long",
    "recovery",
    "grid",
    "profile",
    "versus",
    "relight",
    "quality",
    "texture-step",
)
#: The fit config a table reads by default (`fit_config` None).
FIT_CONFIGS = {"relight": Path("configs/diligent-pot1.toml")}
#: The tables that keep their finished cases in a results file (a rerun resumes).
RESUMABLE = ("recovery", "grid", "versus", "quality")
#: The tables drawn to a PNG besides.
PLOTTED = ("long", "grid", "versus", "quality")
#: The tables on the recovery sweep's cases (`size` and `shapes` apply).
ON_CASES = ("recovery", "grid", "profile")


class Report(NamedTuple):
    """What a bench run made: its tables, and the files it wrote (a plot, the Markdown)."""

    tables: list[Table]
    written: list[Path]


def run(
    spp: int = 64,
    repeats: int = 7,
    only: str | None = None,
    fit_config: Path | None = None,
    steps: int = 1000,
    size: str = "160x120",
    shapes: str = "sphere,torus",
    widths: str = "64,128,256",
    seeds: int | None = None,
    cases: str | None = None,
    results: Path | None = None,
    out: Path | None = None,
    force: bool = False,
    ray: bool = False,
    address: str | None = None,
    variant: str | None = None,
    progress=None,
) -> Report:
    """Run the bench tables `only` names (None: the BSDF and cup speed tables), the options as
    `layerfit bench` takes them. Every option and output is checked first (an `InputError`
    naming the option and the fix), then the variant is chosen (`fit.commands.common.start`)
    and the tables run, shown on `progress` (a `rich.progress.Progress`; None: none shown).
    `fit_config`: None for each table's default (`FIT_CONFIGS`). `results`: the resumable
    tables' JSON (default bench-<table>.json); the long, grid and versus tables draw a PNG
    beside `out` (or bench-<table>.png); `out`: the tables as Markdown. Bad input met during
    the work (a fit config's free keys, a results file of another setting) is an `InputError`
    too; Ctrl-C, `fit.errors.Stopped` saying what was kept. Returns the tables and the files
    written."""
    from captures.files import check_output, write_text

    from ..commands.common import start
    from ..output.figures import drawn_by_layerfit

    if only not in (None, *TABLES):
        choices = ", ".join(TABLES[:-1]) + " or " + TABLES[-1]
        raise InputError(f"--only {only!r}: unknown table; choose {choices}")
    if fit_config is None:
        fit_config = FIT_CONFIGS.get(only or "", Path("configs/peer-sphere.toml"))
    if seeds is None:  # the recovery sweep's table is seed 0's; the others compare medians
        seeds = 1 if only == "recovery" else 3
    for option, value, low, high in (
        ("--spp", spp, 1, MAX_SPP),
        ("--repeats", repeats, 1, None),
        ("--steps", steps, 2, None),
        ("--seeds", seeds, 1, None),
    ):
        if value < low or (high is not None and value > high):
            most = "" if high is None else f" and at most {high}"
            raise InputError(f"{option} {value}: give at least {low}{most}")
    from .quality import QUALITY_CASES

    needed = [path for _, path in QUALITY_CASES] if only == "quality" else list(SCENES)
    missing = [s for s in needed if not s.is_file()]
    if only in (None, "bsdf", "cup", "quality") and missing:
        raise InputError(
            f"{missing[0]}: not found from {Path.cwd()}; run layerfit bench from the repository "
            "root (it reads the bundled configs)"
        )
    width, height = parse_size(size) if only in ON_CASES else (0, 0)
    shape_list = parse_shapes(shapes) if only in ON_CASES else []
    chosen = pick_cases(shape_list, cases) if only == "recovery" else []
    grid_widths = parse_widths(widths) if only == "grid" else ()
    plot = None
    if only in PLOTTED:
        plot = out.with_suffix(".png") if out else Path(f"bench-{only}.png")
    results = results or Path(f"bench-{only}.json")
    if results.is_dir():
        raise InputError(f"--results {results}: is a folder; give a JSON file name")
    inputs = [fit_config, *SCENES]
    if only in RESUMABLE:
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
    if only in RESUMABLE:  # resumed: rewritten, its cases kept
        check_output(results, "--results", force=True)

    start(variant)
    from ..commands.common import stopping
    from .bsdfs import bsdf_speed_table, cup_speed_table
    from .grid import grid_cells, grid_table
    from .long_runs import long_run, long_run_table, plot_long_run
    from .profile import profile_table
    from .quality import quality_table
    from .recovery import recovery_table
    from .relight import relight_table
    from .schedules import fit_trade_table
    from .texture_step import texture_step_table
    from .versus import versus_table

    tables: list[Table] = []
    kept = f"the finished cases are kept in {results}" if only in RESUMABLE else "nothing written"
    with stopping(lambda: kept):
        try:  # the scenes are read from configs/ under the working directory
            if only in (None, "bsdf"):
                tables.append(bsdf_speed_table(spp=spp, repeats=repeats, progress=progress))
            if only in (None, "cup"):
                tables.append(cup_speed_table(spp=spp, repeats=repeats, progress=progress))
            if only == "fit":
                tables.append(fit_trade_table(fit_config, None, progress, ray, address))
            if only == "long":
                long = long_run(steps=steps, progress=progress)
                tables.append(long_run_table(long))
                plot_long_run(long, plot)
            if only == "recovery":
                tables.append(recovery_table(chosen, width, height, results, progress, seeds=seeds))
            if only == "profile":
                tables.append(profile_table(width))
            if only == "grid":
                cells = grid_cells(tuple(shape_list), grid_widths)
                tables.append(grid_table(cells, results, progress, plot=plot))
            if only == "versus":
                tables.append(versus_table(seeds, results, progress, plot=plot))
            if only == "relight":
                tables.append(relight_table(fit_config, progress))
            if only == "quality":
                tables.extend(quality_table(seeds, results, progress, plot=plot))
            if only == "texture-step":
                tables.append(texture_step_table(progress=progress))
        except InputError:
            raise
        except ValueError as err:  # bad input met during the work (pydantic's errors among it)
            raise InputError(str(err)) from err
    written = [] if plot is None else [plot]
    if out is not None:
        write_text(out, "\n".join(t.markdown() for t in tables))
        written.append(out)
    return Report(tables, written)


def parse_size(text: str) -> tuple[int, int]:
    """`size` (WIDTHxHEIGHT) as numbers, each at least 8."""
    parts = text.lower().split("x")
    if len(parts) != 2 or not all(p.isdigit() and int(p) >= 8 for p in parts):
        raise InputError(
            f"--size {text!r}: not a size; give WIDTHxHEIGHT, each at least 8 (160x120)"
        )
    return int(parts[0]), int(parts[1])


def pick_cases(shapes: list[str], labels: str | None) -> list:
    """The recovery sweep's cases of `shapes` (`fit.recovery.sweep`) whose labels `labels`
    names (comma-separated: `alpha 0.01,ior 1.05`), in the sweep's order; None: all of them."""
    from ..recovery import sweep

    cases = sweep(tuple(shapes))
    if labels is None:
        return cases
    known = list(dict.fromkeys(c.label for c in cases))
    wanted = [t.strip() for t in labels.split(",") if t.strip()]
    unknown = [t for t in wanted if t not in known]
    if unknown or not wanted:
        what = f"no case {unknown[0]!r}" if unknown else "names no case"
        raise InputError(f"--cases {labels!r}: {what}; choose from " + ", ".join(known))
    return [c for c in cases if c.label in wanted]


def parse_shapes(text: str) -> list[str]:
    """`shapes` (comma-separated names of `fit.recovery.SHAPES`) as a list."""
    from ..recovery import SHAPES

    names = [s.strip() for s in text.split(",") if s.strip()]
    if not names or any(s not in SHAPES for s in names):
        raise InputError(f"--shapes {text!r}: unknown shape; choose from {', '.join(SHAPES)}")
    return names


def parse_widths(text: str) -> tuple[int, ...]:
    """`widths` (comma-separated image widths, each at least 16) as numbers."""
    parts = [p.strip() for p in text.split(",") if p.strip()]
    if not parts or not all(p.isdigit() and int(p) >= 16 for p in parts):
        raise InputError(f"--widths {text!r}: not widths; give comma-separated numbers, each >= 16")
    return tuple(int(p) for p in parts)
