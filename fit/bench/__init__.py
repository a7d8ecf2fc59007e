"""Benchmarks: tables of measured speed and accuracy (never asserted in tests), one module each.

- `bsdfs`: render time of our BSDFs against Mitsuba's built-ins, and of the cup's stack.
- `schedules`: fit schedules' wall time against error on one fit config (locally or on Ray).
- `long_runs`: time and memory per step over a long Adam run.
- `recovery`: the recovery sweep's calibration table (resumable).
- `tutorial`: the loop a Mitsuba user writes (Mitsuba's Adam on raw values), the baseline.
- `grid`: resolution x spp x solver, a held-out view, the Pareto front (resumable).
- `versus`: the default schedule against the tutorial loop over seeds (resumable).
- `profile`: where a fit's time goes (Dr.Jit's kernel history, renderer calls).
- `common`: the table, the machine line, results files; `problems`: the fits they time.
- `command`: `run`, the `layerfit bench` command without its command line.

Importing this package imports neither Mitsuba nor any benchmark: `run` checks its options before
the variant is chosen. The names below are loaded from their modules when first used; the
benchmarks' modules need the variant chosen (`fit.variant.select_variant`).
"""

from __future__ import annotations

import importlib

from .command import MAX_SPP, SCENES, TABLES, Report, run

#: Each public name of the benchmarks' modules, and its module.
_LAZY = {
    "Table": "common",
    "machine": "common",
    "resumed": "common",
    "constants_digest": "common",
    "schedule_key": "common",
    "sphere_problem": "problems",
    "bsdf_speed_table": "bsdfs",
    "cup_speed_table": "bsdfs",
    "fit_schedules": "schedules",
    "fit_trade_table": "schedules",
    "LongRun": "long_runs",
    "long_run": "long_runs",
    "long_run_table": "long_runs",
    "plot_long_run": "long_runs",
    "recovery_table": "recovery",
    "tutorial_loop": "tutorial",
    "grid_cells": "grid",
    "grid_table": "grid",
    "pareto_front": "grid",
    "versus_table": "versus",
    "profile_table": "profile",
}

__all__ = ["MAX_SPP", "SCENES", "TABLES", "Report", "run", *_LAZY]


def __getattr__(name: str):
    if name not in _LAZY:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(f"{__name__}.{_LAZY[name]}"), name)


def __dir__() -> list[str]:
    return sorted({*globals(), *_LAZY})
