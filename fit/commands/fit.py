"""`layerfit fit`: a fit config end to end: capture in; fitted values, uncertainty, the native
preset, summary and pictures out."""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from captures import CaptureError, open_capture
from captures.images import write_image

from ..config import FitConfig
from ..material import provenance, resolve, save_preset, start_values
from ..output import comparison_sheet, loss_plot, write_text
from ..solvers import Problem, Result, run_schedule


def run_fit(
    cfg: FitConfig, out: Path, progress: Callable[[int, int, float], None] | None = None
) -> dict:
    """Fit, then write `preset.toml` (the fitted material), `summary.json`, `loss.png` and
    `fit.png` (photos, fitted renders and their differences) into `out`; returns the summary.
    `progress(phase, step, loss)` as in `run_schedule`."""
    capture = open_capture(cfg.capture, cfg.downscale)
    free = resolve(cfg.material, cfg.free)
    problem = Problem(capture, cfg.material, free, cfg.gains, cfg.loss, cfg.loss_scale)
    start = start_values(free)
    for k, phase in enumerate(cfg.phases):  # fail before any work, naming the phase
        try:
            problem.at(phase.downscale)
        except CaptureError as err:
            raise CaptureError(f"{cfg.path}: fit.phases[{k}].downscale: {err}") from None
    began = time.perf_counter()
    result = run_schedule(problem, start, cfg.phases, cfg.seed, progress, cfg.uncertainty_spp)
    wall = time.perf_counter() - began
    summary = _summary(cfg, capture.truth, start, result, wall)
    out.mkdir(parents=True, exist_ok=True)
    textures = {  # fitted textures as images next to the summary and in the preset
        f.key: np.asarray(result.values[f.key], np.float32).reshape(f.shape)
        for f in free
        if f.shape
    }
    for key, texels in textures.items():
        write_image(out / f"{key}.exr", texels)
    std = {k: v for k, v in (result.std or {}).items() if k in cfg.material.params}
    save_preset(
        cfg.material.with_values(result.values),
        out / "preset.toml",
        provenance(cfg.capture, cfg.path, result.loss, std or None),
        textures,
    )
    write_text(out / "summary.json", json.dumps(summary, indent=2))
    loss_plot(result, cfg.phases, out / "loss.png")
    comparison_sheet(problem, result.u, out / "fit.png", seed=cfg.seed + 7)
    return summary


def _summary(cfg: FitConfig, truth: dict, start: dict, result: Result, wall: float) -> dict:
    errors = {}
    for key, value in result.values.items():
        if key in truth:
            errors[key] = (np.asarray(value) - np.asarray(truth[key])).tolist()
    return {
        "config": str(cfg.path),
        "capture": str(cfg.capture),
        "phases": [
            {**p.model_dump(exclude=set(p.model_extra or ())), **p.options.model_dump()}
            for p in cfg.phases
        ],
        "outcomes": [r.as_dict() for r in result.reports],
        "seed": cfg.seed,
        "start": start,
        "values": result.values,
        "std": result.std,
        "correlation": None if result.correlation is None else result.correlation.tolist(),
        "poorly_determined": result.poorly_determined,
        "truth": {k: truth[k] for k in result.values if k in truth},
        "error": errors,
        "loss": result.loss,
        "history": result.history,
        "wall_time_s": wall,
    }
