"""The bench grid: resolution x spp x solver on the recovery sphere (and a diagonal on other
shapes), the tutorial loop among them; three views fitted, a fourth held out; the Pareto front
of wall time against error."""

from __future__ import annotations

import functools
import json
import time
from pathlib import Path

import numpy as np

from ..render import load_scene, scene_dict
from .common import Table, complete, legend_once, machine, resumed, schedule_key, short
from .problems import recovery_problem, relative_errors
from .tutorial import TUTORIAL_WARM_UP, tutorial_loop

GRID_WIDTHS = (64, 128, 256)
GRID_SPPS = (4, 16, 64)
GRID_SOLVERS = ("adam", "lm", "bfgs", "default")
#: The diagonal subset of other shapes (the cup, for one): (width, spp) pairs, each with
#: every solver.
DIAGONAL = ((64, 4), (128, 16), (256, 64))
#: The tutorial loop runs at the grid's widths up to this one (and at least at the smallest).
TUTORIAL_MAX_WIDTH = 128


def grid_schedule(solver: str, spp: int) -> tuple:
    """A cell's schedule: one phase of `solver` at `spp` (Adam 150 steps, lr 0.05, the last half
    averaged; LM 10 steps, its Jacobian decorrelated at `spp`; BFGS 30 steps, one seed), or the
    default schedule with its sample counts scaled so that its last phase renders at `spp`."""
    from ..solvers import DEFAULT_SCHEDULE, Phase

    if solver == "adam":
        return (Phase(solver="adam", steps=150, spp=spp, lr=0.05, average=0.5),)
    if solver == "lm":
        return (Phase(solver="lm", steps=10, spp=spp, jacobian_spp=spp),)
    if solver == "bfgs":
        return (Phase(solver="bfgs", steps=30, spp=spp),)
    if solver == "default":
        scale = spp / DEFAULT_SCHEDULE[-1].spp
        return tuple(_scaled(p, max(1, round(p.spp * scale))) for p in DEFAULT_SCHEDULE)
    raise ValueError(f"solver {solver!r}")


def _scaled(phase, spp: int):
    """`phase` at `spp`, a `gn` phase's `spp_limit` the same multiple of it."""
    fields = phase.model_dump()  # its options too (extra fields), validated again
    if fields.get("spp_limit"):
        fields["spp_limit"] = max(spp + 1, round(fields["spp_limit"] * spp / phase.spp))
    return type(phase)(**{**fields, "spp": spp})


def grid_cells(
    shapes=("sphere", "cup"), widths: tuple[int, ...] = GRID_WIDTHS
) -> list[tuple[str, int, int, str]]:
    """(shape, width, spp, solver) of every cell: the full grid on the sphere, the diagonal on
    other shapes (its pairs whose width is among `widths`), and the tutorial loop (its own spp)
    on the sphere at widths up to `TUTORIAL_MAX_WIDTH` and at the smallest (it re-traces the
    scene every iteration: 777-837 s at 64x48 and 128x96 on 2 cores, 5-15x the default's
    dearest cell there)."""
    cells = []
    if "sphere" in shapes:
        for width in widths:
            cells += [("sphere", width, s, v) for s in GRID_SPPS for v in GRID_SOLVERS]
        tutorial = [w for w in widths if w <= TUTORIAL_MAX_WIDTH] or [min(widths)]
        cells += [("sphere", w, 0, "tutorial") for w in tutorial]
    for shape in [s for s in shapes if s != "sphere"]:
        pairs = [(w, s) for w, s in DIAGONAL if w in widths]
        cells += [(shape, w, s, v) for w, s in pairs for v in GRID_SOLVERS]
    return cells


def _cell_name(shape: str, width: int, spp: int, solver: str) -> str:
    return f"{shape} {width} {'16+64' if solver == 'tutorial' else spp} {solver}"


def _counting(renderer) -> list[int]:
    """Count the per-view passes (primal, adjoint, forward) a `Renderer` makes."""
    count = [0]
    views = sum(len(g.views) for g in renderer.groups)
    render, vjp, jacobian = renderer.render, renderer.vjp, renderer.jacobian

    def counted_render(*args, **kwargs):
        count[0] += views
        return render(*args, **kwargs)

    def counted_vjp(*args, **kwargs):
        count[0] += views
        return vjp(*args, **kwargs)

    def counted_jacobian(*args, **kwargs):
        count[0] += views * renderer.n_params
        return jacobian(*args, **kwargs)

    renderer.render, renderer.vjp, renderer.jacobian = counted_render, counted_vjp, counted_jacobian
    return count


def grid_cell(shape: str, width: int, spp: int, solver: str) -> dict:
    """One cell: the case's three views fitted (after an untimed warm-up of one step per phase,
    which compiles the kernels), then a fourth, held-out view rendered at 256 spp with the
    fitted values against its own target (relative RMSE over the object)."""
    from .. import recovery
    from ..solvers import run_schedule

    case = recovery.Case(shape)
    capture = recovery.capture(case, width, width * 3 // 4)

    def problem():
        return recovery_problem(capture)

    if solver == "tutorial":
        tutorial_loop(problem(), recovery.START, TUTORIAL_WARM_UP)
        seconds, values, renders = tutorial_loop(problem(), recovery.START)
    else:
        schedule = grid_schedule(solver, spp)
        run_schedule(problem(), recovery.START, short(schedule), 0, uncertainty_spp=4)
        p = problem()
        counts = [_counting(p.renderer(d)) for d in (1, 2)]
        began = time.perf_counter()
        values = run_schedule(p, recovery.START, schedule, 0).values
        seconds = time.perf_counter() - began
        renders = sum(c[0] for c in counts)
    errors = relative_errors(values, case.truth())
    return {
        "seconds": seconds,
        "renders": renders,
        "errors": errors,
        "max_relative_error": max(errors.values()),
        "held_out_rmse": held_out_error(shape, width, values),
        "values": values,
    }


def held_out_error(shape: str, width: int, values: dict) -> float:
    """Relative RMSE over the object of a fourth, held-out view (a camera between the front and
    the right one, a little higher) rendered with `values` against
    the truth's render, both at 256 spp with the same seed (the noise mostly cancels: what
    remains is the parameters' error)."""
    import dataclasses

    from .. import recovery
    from ..render import render

    studio = recovery.studio(shape, width, width * 3 // 4)
    center, radius = _bounding(studio)
    camera = dataclasses.replace(
        studio.cameras[0],
        origin=tuple(float(c) for c in center + radius * np.array([2.0, -4.6, 2.0])),
    )
    held = dataclasses.replace(studio, cameras=(camera,))
    truth = recovery.Case(shape).truth()
    target = render(load_scene(scene_dict(held, recovery.glaze(truth), 0, 256)), 256, 7)
    fitted = render(load_scene(scene_dict(held, recovery.glaze(values), 0, 256)), 256, 7)
    mask = target.max(axis=2) > 0.2 * float(np.median(target))
    return float(np.sqrt(np.mean((fitted - target)[mask] ** 2)) / np.mean(target[mask]))


def _bounding(scene):
    from captures.scene import bounding_sphere

    return bounding_sphere(scene.geometry)


def pareto_front(points: list[tuple[float, float]]) -> list[bool]:
    """Which (time, error) points no other point beats (at most as slow and as wrong, and better
    in one); equal points are both on the front."""
    return [
        not any(
            (t2 <= t and e2 <= e) and (t2 < t or e2 < e)
            for j, (t2, e2) in enumerate(points)
            if j != i
        )
        for i, (t, e) in enumerate(points)
    ]


def grid_table(
    cells, results: Path, progress=None, replace: bool = False, plot: Path | None = None
):
    """Run (or read back from `results`) every cell; the table, and the Pareto plot of wall time
    against max relative error per shape (the front marked)."""
    from .. import recovery
    from ..solvers import DEFAULT_SCHEDULE

    setting = {"default": schedule_key(DEFAULT_SCHEDULE)}
    required = ("seconds", "renders", "max_relative_error", "held_out_rmse")
    done = resumed(
        results,
        setting,
        "cells",
        "a grid of another default schedule or fitting code (its constants)",
        replace,
        required,
    )
    names = [_cell_name(*c) for c in cells]
    jobs = {n: functools.partial(grid_cell, *c) for n, c in zip(names, cells, strict=True)}
    complete(results, setting, "cells", done, jobs, progress, "bench: grid")
    rows = []
    fronts = {}
    for shape in {c[0] for c in cells}:
        mine = [n for n, c in zip(names, cells, strict=True) if c[0] == shape]
        points = [(done[n]["seconds"], done[n]["max_relative_error"]) for n in mine]
        fronts.update(dict(zip(mine, pareto_front(points), strict=True)))
    for name, (shape, width, spp, solver) in zip(names, cells, strict=True):
        d = done[name]
        rows.append(
            [
                shape,
                f"{width}x{width * 3 // 4}",
                "16, 64" if solver == "tutorial" else str(spp),
                solver,
                f"{d['seconds']:.1f}",
                str(d["renders"]),
                f"{100 * d['max_relative_error']:.2f} %",
                f"{100 * d['held_out_rmse']:.2f} %",
                "yes" if fronts[name] else "",
            ]
        )
    if plot is not None:
        _plot_grid(cells, names, done, fronts, plot)
    return Table(
        title="Bench grid: resolution x spp x solver (3 views fitted, 1 held out)",
        columns=[
            "shape",
            "size",
            "spp",
            "solver",
            "wall s",
            "renders",
            "max rel. error",
            "held-out RMSE",
            "Pareto front",
        ],
        rows=rows,
        notes=[
            "adam: 150 steps lr 0.05, last half averaged; lm: 10 steps, Jacobian decorrelated at "
            "the cell's spp; bfgs: 30 steps, one seed; default: the default schedule with its "
            "last phase at the cell's spp; tutorial: Mitsuba's Adam on raw values, 200 x 16 spp "
            "lr 0.05 + 100 x 64 spp lr 0.01, seeds i and i + 1000003",
            "wall s: the fit after an untimed one-step warm-up (kernels compiled), the "
            "uncertainty included for layerfit's solvers; renders: per-view passes (primal, "
            "adjoint, forward-mode columns); max rel. error: over pigment channels, alpha and "
            "ior; held-out RMSE: a fourth view at 256 spp, relative to its mean",
            f"start {json.dumps(recovery.START)}; truth: the default job's blue glaze, "
            "alpha 0.1, ior 1.5",
            machine(),
        ],
    )


def _plot_grid(cells, names, done, fronts, out: Path) -> None:
    from ..output.figures import pyplot, save_figure

    plt = pyplot()
    shapes = sorted({c[0] for c in cells})
    fig, axes = plt.subplots(1, len(shapes), figsize=(6.5 * len(shapes), 5), squeeze=False)
    markers = {"adam": "o", "lm": "s", "bfgs": "^", "default": "*", "tutorial": "X"}
    colours = dict(
        zip(markers, ("tab:blue", "tab:orange", "tab:green", "tab:red", "tab:purple"), strict=True)
    )
    for ax, shape in zip(axes[0], shapes, strict=True):
        for name, (s, width, spp, solver) in zip(names, cells, strict=True):
            if s != shape:
                continue
            d = done[name]
            ax.scatter(
                d["seconds"],
                max(d["max_relative_error"], 1e-5),
                marker=markers[solver],
                color=colours[solver],
                s=120 if solver in ("default", "tutorial") else 50,
                edgecolors="black" if fronts[name] else "none",
                label=solver,
            )
            ax.annotate(
                f"{width}/{spp or '16+64'}",
                (d["seconds"], d["max_relative_error"]),
                fontsize=7,
                xytext=(3, 3),
                textcoords="offset points",
            )
        front = sorted(
            (done[n]["seconds"], done[n]["max_relative_error"])
            for n, c in zip(names, cells, strict=True)
            if c[0] == shape and fronts[n]
        )
        ax.step(*zip(*front, strict=True), where="post", color="grey", lw=1)
        ax.set(
            xscale="log",
            yscale="log",
            xlabel="wall time, s",
            ylabel="max relative error",
            title=f"{shape}: time vs error (outlined: Pareto front; label: width/spp)",
        )
        legend_once(ax)
    fig.tight_layout()
    save_figure(fig, out)
