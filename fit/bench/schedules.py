"""Fit schedules on one fit config: wall time against error to the known values (the
speed/accuracy trade of solver, spp, resolution and step choices), locally or as Ray tasks."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from captures.errors import InputError

from .common import Table, machine, short, ticker


def fit_schedules() -> dict:
    """Named schedules compared by `fit_trade_table`: the default, cheaper and dearer variants,
    the plain Adam loop of ../shared/FACTS.md, and the LM and BFGS polishes."""
    from ..solvers import DEFAULT_SCHEDULE, Phase

    first = DEFAULT_SCHEDULE[0]
    return {
        "default": DEFAULT_SCHEDULE,
        "default, half the steps": (
            first.model_copy(update={"steps": 50}),
            Phase(solver="adam", steps=30, spp=32, lr=0.02, average=0.5),
        ),
        "default, full resolution throughout": (
            first.model_copy(update={"downscale": 1}),
            *DEFAULT_SCHEDULE[1:],
        ),
        "plain Adam: 200 x 16 spp + 100 x 64 spp": (
            Phase(solver="adam", steps=200, spp=16, lr=0.05),
            Phase(solver="adam", steps=100, spp=64, lr=0.01, average=0.5),
        ),
        "Adam, then LM (shared seed, 64 spp)": (first, Phase(solver="lm", steps=6, spp=64)),
        "Adam, then LM (128 spp, decorrelated 16-spp Jacobian)": (
            first,
            Phase(solver="lm", steps=6, spp=128, jacobian_spp=16),
        ),
        "Adam, then BFGS (shared seed, 64 spp)": (first, Phase(solver="bfgs", steps=20, spp=64)),
    }


def _fit_setup(config: Path):
    """(config, capture, free parameters, start) of a fit config whose capture has the truth."""
    from captures import open_capture

    from ..config import load_fit_config
    from ..material import resolve, start_values

    cfg = load_fit_config(config)
    capture = open_capture(cfg.capture, cfg.downscale)
    try:
        free = resolve(cfg.material, cfg.free)
    except KeyError as err:  # a free key: name the config it came from
        raise InputError(f"{config}: fit.free: {err.args[0]}") from None
    missing = [f.key for f in free if f.key not in capture.truth]
    if missing:
        raise InputError(
            f"{config}: fit.free: the capture has no known value for {', '.join(missing)}; "
            "the bench compares against a capture's [truth]"
        )
    return cfg, capture, free, start_values(free)


def fit_cell(config: Path, name: str) -> tuple[float, dict]:
    """One cell of the schedule table: the schedule `name` of `fit_schedules()` on `config`
    after an untimed one-step-per-phase warm-up (it compiles every kernel the run needs): the
    wall time and the fitted values."""
    from ..solvers import Problem, run_schedule

    cfg, capture, free, start = _fit_setup(config)
    schedule = fit_schedules()[name]
    problem = Problem(capture, cfg.material, free, cfg.gains, cfg.loss, cfg.loss_scale)
    run_schedule(problem, start, short(schedule), cfg.seed, None, cfg.uncertainty_spp)
    problem = Problem(capture, cfg.material, free, cfg.gains, cfg.loss, cfg.loss_scale)
    began = time.perf_counter()
    result = run_schedule(problem, start, schedule, cfg.seed, None, cfg.uncertainty_spp)
    return time.perf_counter() - began, result.values


def _fit_cell_task(config: Path, name: str, variant: str | None, cpus: int):
    """In a Ray worker: `fit_cell` with the driver's variant and the task's CPUs as threads."""
    from ..cluster import DEFAULT_KERNEL_CACHE, prepare_worker

    prepare_worker(cpus, variant, DEFAULT_KERNEL_CACHE)
    return fit_cell(config, name)


def _ray_cells(config: Path, names: list[str], address: str | None, advance) -> dict:
    """`fit_cell` of each schedule as a Ray task holding a whole node's CPUs (cells never share
    a node, so their wall times are not distorted; a cluster's nodes run several at once)."""
    from ..cluster import connect, driver_variant

    with connect(address):
        import ray

        cpus = int(min(n["Resources"].get("CPU", 1) for n in ray.nodes() if n["Alive"]))
        task = ray.remote(max_retries=0)(_fit_cell_task).options(num_cpus=cpus)
        refs = {task.remote(config.resolve(), n, driver_variant(), cpus): n for n in names}
        out, pending = {}, list(refs)
        while pending:
            ready, pending = ray.wait(pending, num_returns=1)
            out[refs[ready[0]]] = ray.get(ready[0])
            advance()
    return out


def fit_trade_table(
    config: Path,
    names: list[str] | None = None,
    progress=None,
    ray: bool = False,
    address: str | None = None,
) -> Table:
    """Wall time and error against the known values of each schedule on one fit config (its
    capture must carry the truth): the speed/accuracy trade of the solver, spp, resolution and
    step choices. Each schedule starts from the config's material with the config's seed. With
    `ray`, each cell runs as a Ray task holding a whole node (`address`: a cluster's)."""
    _, capture, free, _ = _fit_setup(config)  # fails here, before any work
    names = names or list(fit_schedules())
    advance = ticker(progress, "bench: fit schedules", len(names))
    if ray:
        cells = _ray_cells(config, names, address, advance)
    else:
        cells = {}
        for name in names:
            cells[name] = fit_cell(config, name)
            advance()
    rows, walls = [], {}
    for name in names:
        walls[name], values = cells[name]
        row = [name, f"{walls[name]:.0f}"]
        for f in free:
            error = np.abs(np.asarray(values[f.key]) - np.asarray(capture.truth[f.key]))
            relative = error / np.maximum(np.abs(np.asarray(capture.truth[f.key])), 1e-12)
            row.append(f"{error.max():.4f} ({100 * relative.max():.1f} %)")
        rows.append(row)
    reference = walls.get("default", next(iter(walls.values())))
    for row, name in zip(rows, names, strict=True):
        row.insert(2, f"{walls[name] / reference:.2f}")
    where = (
        "each schedule a Ray task holding a whole node's CPUs (the machine below: the driver's)"
        if ray
        else "schedules run one after another in one process"
    )
    return Table(
        title=f"Fit schedules on {config.name}: wall time and max error vs the known values",
        columns=["schedule", "wall s", "time / default", *(f"{f.key} |err|" for f in free)],
        rows=rows,
        notes=[
            "wall time after an untimed one-step-per-phase warm-up of the schedule (kernels "
            "compiled); it includes the final uncertainty (64 spp Jacobian)",
            f"{where}, from the config's start and seed",
            machine(),
        ],
    )
