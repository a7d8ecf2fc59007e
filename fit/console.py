"""What the command line shows: one-line messages, progress bars and the results tables.

Progress and messages go to stderr, a command's results (a fit's table, held-out scores, the run
folder) to stdout: `layerfit fit CONFIG > results.txt` keeps the table. Redirected, a table is
laid out 160 columns wide (rich's 80 cut its numbers short)."""

from __future__ import annotations

import logging
import sys
from pathlib import Path

import numpy as np
from rich.console import Console
from rich.markup import escape
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table
from rich.text import Text

console = Console(stderr=True)
results = Console(width=None if sys.stdout.isatty() else 160)

#: Whether this run has said it was interrupted (the entry says so where nothing did).
said = {"interrupted": False}


def say(label: str, style: str, text: str) -> None:
    """One unwrapped line `label text`, the text plain (brackets in it are shown, not markup)."""
    said["interrupted"] |= "interrupted" in f"{label} {text}"
    console.print(Text.assemble((label, style), " ", str(text)), highlight=False, soft_wrap=True)


def wrote(path: Path | str, suffix: str = "") -> None:
    """`wrote PATH`, plain."""
    console.print(f"wrote {path}{suffix}", markup=False, highlight=False)


class _Bars(Progress):
    """Progress bars shown from their first task on: a command that fails before its work
    prints its one line alone."""

    def __enter__(self) -> _Bars:
        return self

    def add_task(self, *args, **kwargs):
        if not self.live.is_started:
            self.start()
        return super().add_task(*args, **kwargs)

    def stop(self) -> None:
        if self.live.is_started:
            super().stop()


def progress() -> Progress:
    """The progress bars of a command's long work (on stderr)."""
    return _Bars(
        TextColumn("{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        console=console,
        transient=False,
    )


class Plain(logging.Formatter):
    """Log records as the CLI's own lines: `warning: the message`."""

    def format(self, record: logging.LogRecord) -> str:
        return f"{record.levelname.lower()}: {record.getMessage()}"


def _numbers(value, digits: str = ".4f") -> str:
    if value is None:
        return "-"
    value = np.ravel(value)
    if value.size > 3:  # a texture
        return f"{value.size} texels, mean {value.mean():.3f}, |max| {np.abs(value).max():.3f}"
    return ", ".join(f"{v:{digits}}" for v in value)


def fit_results(config: Path, out: Path, summary: dict) -> None:
    """A fit's table (start, fitted, sd, known value, error, error/sd per parameter), then what
    needs a look (poorly determined values, bounds, failed phases), held-out scores and the run
    folder."""
    from .material.free import bound_note

    solvers = "+".join(p["solver"] for p in summary["phases"])
    table = Table(title=escape(f"{config}: {solvers}, {summary['wall_time_s']:.1f} s"))
    table.add_column("parameter", no_wrap=True)
    for column in ("start", "fitted", "std", "known", "error", "error/std"):
        table.add_column(column)
    std = summary["std"] or {}
    for key, value in summary["values"].items():
        cells = (summary["start"].get(key), value, std.get(key), summary["truth"].get(key))
        errors = (summary["error"].get(key), summary["error_over_std"].get(key))
        table.add_row(escape(key), *map(_numbers, cells + errors))
    results.print(table)
    if summary["poorly_determined"]:
        say("poorly determined:", "yellow", ", ".join(summary["poorly_determined"]))
    for bound in summary["at_bounds"]:
        say("at a bound:", "yellow", bound_note(bound, len(summary.get("starts") or ()) or 1))
    if summary["std"] is None:
        results.print(
            "no standard deviations: every free parameter is a texture, or too many free "
            "components for a Jacobian"
        )
    for key, texture in (summary.get("textures") or {}).items():
        median = texture["median_sd"]
        said = "none seen" if median is None else f"median sd {median:.4f} where seen"
        results.print(
            f"{key}: texels' {said} ({texture['sd_file']})",
            highlight=False,
            markup=False,
        )
    for report in summary["outcomes"]:
        if report["outcome"] in ("diverged", "failed") or report["rejected"]:
            say(f"{report['solver']}:", "yellow", f"{report['outcome']}: {report['message']}")
    if "starts" in summary:
        _starts(summary["starts"])
    held = [v for v in summary["views"] if v["held_out"]]
    if held:
        scores = ", ".join(f"{v['name']} {v['rmse']:.3f}" for v in held)
        results.print(f"held-out views, relative RMSE: {scores}", highlight=False, markup=False)
    results.print(
        f"run folder: {out} (preset.toml, summary.json, report.html)", highlight=False, markup=False
    )


def _starts(rows: list[dict]) -> None:
    """The multi-start spread: each start's start and fitted values and its common loss."""
    table = Table(title="starts (the best by the common high-spp loss)")
    for column in ("start", "from", "fitted", "loss", "wall s"):
        table.add_column(column)
    for row in rows:
        table.add_row(
            f"{row['start']}{' (best)' if row['best'] else ''}",
            "; ".join(f"{k} {_numbers(v, '.4g')}" for k, v in row["start_values"].items()),
            "; ".join(f"{k} {_numbers(v, '.4g')}" for k, v in row["values"].items()),
            f"{row['loss']:.6g}" if row["loss"] is not None else escape(f"failed: {row['error']}"),
            f"{row['wall_time_s']:.0f}",
        )
    results.print(table)


def inspection(capture: Path, found) -> None:
    """`inspect`'s table of the views, its warning, and the sheet written."""
    table = Table(
        title=escape(f"{capture}: {len(found.rows)} views, {_geometry(found.capture.scene)}")
    )
    for column in ("view", "size", "gain", "valid", "max", "iou"):
        table.add_column(column)
    for row in found.rows:
        table.add_row(
            escape(row["view"]),
            row["size"],
            f"{row['gain']:.3g}",
            f"{row['valid']:.1%}",
            f"{row['max']:.3g}",
            f"{row['iou']:.3f}" if "iou" in row else "-",
        )
    console.print(table)
    if found.warning:
        say("warning:", "yellow", found.warning)
    n = len(found.capture.views)
    wrote(found.sheet, "" if found.shown == n else f" (the first {found.shown} views)")


def _geometry(scene) -> str:
    """The capture's object in a few words."""
    from captures.scene import Cup, MeshArrays, ObjFile, Sphere

    geometry = scene.geometry
    if isinstance(geometry, Sphere):
        return f"a sphere of radius {geometry.radius:.4g}"
    if isinstance(geometry, Cup):
        return "the procedural cup"
    if isinstance(geometry, ObjFile):
        return f"mesh {Path(geometry.path).name}"
    if isinstance(geometry, MeshArrays):
        return f"a height field of {len(geometry.data.faces)} triangles"
    return type(geometry).__name__
