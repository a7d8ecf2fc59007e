"""Run a fit config end to end: capture in, fitted values, uncertainty, summary and plot out."""

from __future__ import annotations

import dataclasses
import json
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from captures import CaptureError
from captures.images import write_image

from .figures import pyplot, save_figure
from .fitconfig import FitConfig
from .free import Free, resolve, texture_data
from .inspect import open_capture
from .report import comparison_sheet
from .solve import Problem, Result, run_schedule


def start_values(material: dict, free: list[Free]) -> dict:
    """Each free parameter's starting value from the material dict (its declared default when the
    material does not set it)."""
    out = {}
    for f in free:
        if f.emitter:
            out[f.key] = f.spec.default  # as configured
            continue
        if f.shape:  # a mask's texture: its texels as painted
            texture = material[f.key.split(".")[0] + "_mask"]["texture"]
            out[f.key] = texture_data(texture).ravel().tolist()
            continue
        parts = f.key.split(".")
        if material["type"] == "layered":
            if parts == ["bump"]:
                table, name = material, "bump"
            elif len(parts) == 3 and parts[1] == "mask":
                table, name = material[f"{parts[0]}_mask"], parts[2]
            else:
                table, name = material[parts[0]], parts[1]
        else:
            table, name = material, parts[1]
        value = table.get(name, f.spec.default) if isinstance(table, dict) else f.spec.default
        if isinstance(value, dict):
            if value.get("type") != "rgb":
                raise ValueError(f"{f.key}: a texture cannot be a free parameter here yet")
            value = value["value"]
        out[f.key] = value
    return out


def run_fit(
    cfg: FitConfig, out: Path, progress: Callable[[int, int, float], None] | None = None
) -> dict:
    """Fit, then write `summary.json`, `loss.png` and `fit.png` (photos, fitted renders and their
    differences) into `out`; returns the summary.
    `progress(phase, step, loss)` as in `run_schedule`."""
    capture = open_capture(cfg.capture, cfg.downscale)
    free = resolve(cfg.material, cfg.free)
    problem = Problem(capture, cfg.material, free, cfg.gains, cfg.loss, cfg.loss_scale)
    start = start_values(cfg.material, free)
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
    partial = out / ".summary.json.partial"
    partial.write_text(json.dumps(summary, indent=2))
    partial.replace(out / "summary.json")
    _plot(result, cfg.phases, out / "loss.png")
    comparison_sheet(problem, result.u, out / "fit.png", seed=cfg.seed + 7)
    for f in free:
        if f.shape:  # fitted textures as images next to the summary
            texels = np.asarray(result.values[f.key], np.float32).reshape(f.shape)
            write_image(out / f"{f.key}.exr", texels)
    return summary


def _summary(cfg: FitConfig, truth: dict, start: dict, result: Result, wall: float) -> dict:
    errors = {}
    for key, value in result.values.items():
        if key in truth:
            errors[key] = (np.asarray(value) - np.asarray(truth[key])).tolist()
    return {
        "config": str(cfg.path),
        "capture": str(cfg.capture),
        "phases": [dataclasses.asdict(p) for p in cfg.phases],
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


def _plot(result: Result, phases, path: Path) -> None:
    """The loss per step, one colour per phase (phases at another resolution or loss scale are
    not comparable in level; LM and BFGS phases show their final loss as one point)."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6, 3.2))
    begin = 0
    for k, (phase, end) in enumerate(zip(phases, result.phase_ends, strict=True)):
        steps = np.arange(begin, end)
        label = f"{k + 1}: {phase.solver}, {phase.spp} spp, 1/{phase.downscale} res"
        ax.semilogy(steps, result.history[begin:end], "o" if end - begin == 1 else "-", label=label)
        begin = end
    ax.set_xlabel("step")
    ax.set_ylabel("loss (weighted)")
    ax.set_title("per phase at its own resolution and spp", fontsize=8)
    ax.legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, path, dpi=100)
