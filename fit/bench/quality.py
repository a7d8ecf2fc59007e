"""The whole `layerfit fit` command at each quality preset against the loop a Mitsuba user writes
today (`fit.bench.tutorial`): the time a user waits for (a fresh process: start-up, imports, the
kernel cache, the fit, its uncertainty and report), the errors against the truth, and where the
default's time goes, part by part, with empty kernel caches and warm ones."""

from __future__ import annotations

import functools
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from ..limits import QUALITIES
from .common import Table, complete, constants_digest, machine, resumed

#: The objects of the table: a name and its fit config (read from the working directory).
QUALITY_CASES = (
    ("sphere", Path("configs/peer-sphere.toml")),
    ("torus", Path("configs/peer-torus.toml")),
    ("cup", Path("configs/cup-fit.toml")),
)
#: The case the tutorial loop runs on (the loop fits a single material: not the cup's layers).
LOOP_CASE = "sphere"


def command_run(config: Path, quality: str, seed: int, cold: Path | None = None) -> dict:
    """`layerfit fit CONFIG --quality Q --seed S` as a user runs it, in a fresh process (`cold`:
    an empty folder for its Dr.Jit and JAX caches, as on a fresh clone): its wall time, the
    summary's errors, their ratios to the reported sd and its parts' timings. A failed command
    is a `RuntimeError` with its last line."""
    env = dict(os.environ)
    if cold is not None:
        env["DRJIT_CACHE_DIR"] = str(cold / "drjit")
        env["JAX_COMPILATION_CACHE_DIR"] = str(cold / "jax")
    with tempfile.TemporaryDirectory(prefix="layerfit-bench-") as folder:
        out = Path(folder) / "run"
        command = [sys.executable, "-m", "fit", "fit", str(config), "--out", str(out)]
        command += ["--quality", quality, "--seed", str(seed)]
        began = time.perf_counter()
        done = subprocess.run(
            command,
            check=False,
            env=env,
            capture_output=True,
            text=True,
            stdin=subprocess.DEVNULL,
        )
        seconds = time.perf_counter() - began
        if done.returncode != 0:
            last = (done.stderr.strip() or done.stdout.strip() or "no output").splitlines()[-1]
            raise RuntimeError(f"{' '.join(command)}: exit {done.returncode}: {last}")
        summary = json.loads((out / "summary.json").read_text())
    return {
        "seconds": seconds,
        "fit_seconds": summary["wall_time_s"],
        "errors": summary["error"],
        "truth": {k: v for k, v in summary["truth"].items() if k in summary["error"]},
        "error_over_std": summary.get("error_over_std", {}),
        "timings": summary.get("timings_s", {}),
        "steps": [o["steps"] for o in summary["outcomes"]],
    }


def loop_run(config: Path, seed: int) -> dict:
    """The tutorial loop on `config`'s capture from its start, in process after an untimed
    warm-up (its kernels compiled), timed until its values are read; its errors."""
    from ..commands.prepare import prepare
    from ..config import load_fit_config
    from .tutorial import TUTORIAL_WARM_UP, tutorial_loop

    cfg = load_fit_config(config)
    prepared = prepare(cfg, trace=False)
    tutorial_loop(prepared.problem, prepared.start, TUTORIAL_WARM_UP, seed=99)
    seconds, values, _ = tutorial_loop(prepare(cfg, trace=False).problem, prepared.start, seed=seed)
    truth = prepared.capture.truth
    errors = {
        k: (np.asarray(v, float) - np.asarray(truth[k], float)).tolist()
        for k, v in values.items()
        if k in truth
    }
    return {"seconds": seconds, "errors": errors, "truth": {k: truth[k] for k in errors}}


def measures(entry: dict) -> dict[str, float]:
    """A run's errors as the table shows them: the worst colour channel (absolute), alpha
    (relative), ior (absolute), each the worst over the layers that have one."""
    out: dict[str, float] = {}
    for key, value in entry["errors"].items():
        error = np.abs(np.asarray(value, float))
        if key.endswith(".roughness"):
            name = "alpha"
            error = error / np.abs(np.asarray(entry["truth"][key], float))
        elif key.endswith(".ior"):
            name = "ior"
        elif error.size == 3 and not key.startswith("gain."):
            name = "colour"
        else:
            continue
        out[name] = max(out.get(name, 0.0), float(np.max(error)))
    return out


def quality_table(
    seeds: int,
    results: Path,
    progress=None,
    cases=QUALITY_CASES,
    replace: bool = False,
    plot: Path | None = None,
) -> tuple[Table, Table]:
    """Each case at each quality preset (whole commands, seeds 0 .. `seeds` - 1) and the
    tutorial loop on `LOOP_CASE` (same seeds), plus one default command with an empty kernel
    cache; runs are saved to `results` as they finish (a rerun resumes). Returns the presets'
    table (median time, its ratio to the loop's, median errors) and the default's time part
    by part (cold and warm, on `LOOP_CASE`); `plot`: the trade drawn there (PNG)."""
    setting = {
        "cases": [[name, str(path)] for name, path in cases],
        "constants": constants_digest(),
    }
    done = resumed(results, setting, "runs", "runs of another setting", replace)
    jobs = {}
    loop_config = dict(cases)[LOOP_CASE]
    # the cold run first: every later one finds the cache its first command filled
    with tempfile.TemporaryDirectory(prefix="layerfit-cold-") as cold:
        jobs["cold default"] = functools.partial(command_run, loop_config, "default", 0, Path(cold))
        for k in range(seeds):
            jobs[f"loop {k}"] = functools.partial(loop_run, loop_config, k)
            for name, path in cases:
                for quality in QUALITIES:
                    jobs[f"{name} {quality} {k}"] = functools.partial(command_run, path, quality, k)
        complete(results, setting, "runs", done, jobs, progress, "bench: quality presets")
    loop = [done[f"loop {k}"] for k in range(seeds)]
    loop_seconds = float(np.median([r["seconds"] for r in loop]))
    columns = ["object", "quality", "whole command s", "loop s / this", "colour", "alpha", "ior"]
    columns.append("errors within 3 sd")
    rows = []

    def median(runs, name):
        values = [measures(r).get(name) for r in runs]
        values = [v for v in values if v is not None]
        return float(np.median(values)) if values else None

    def errors(runs):
        colour, alpha, ior = (median(runs, n) for n in ("colour", "alpha", "ior"))
        return [
            "-" if colour is None else f"{colour:.4f}",
            "-" if alpha is None else f"{100 * alpha:.1f} %",
            "-" if ior is None else f"{ior:.4f}",
        ]

    for name, _ in cases:
        for quality in QUALITIES:
            runs = [done[f"{name} {quality} {k}"] for k in range(seeds)]
            seconds = float(np.median([r["seconds"] for r in runs]))
            ratios = [
                np.abs(np.asarray(z, float)) for r in runs for z in r["error_over_std"].values()
            ]
            flat = np.concatenate([np.ravel(z) for z in ratios]) if ratios else np.zeros(0)
            within = f"{int(np.sum(flat <= 3))} of {flat.size}" if flat.size else "-"
            ratio = f"{loop_seconds / seconds:.1f}x" if name == LOOP_CASE else "-"
            rows.append([name, quality, f"{seconds:.1f}", ratio, *errors(runs), within])
        if name == LOOP_CASE:
            rows.append(
                [name, "the tutorial loop", f"{loop_seconds:.1f}", "1.0x", *errors(loop), "-"]
            )
    presets = Table(
        title="Quality presets: the whole command against the loop users write",
        columns=columns,
        rows=rows,
        notes=[
            f"medians over seeds 0-{seeds - 1}; each command a fresh process (`layerfit fit "
            "CONFIG --quality Q --seed S`), warm kernel cache; the loop in process, after an "
            "untimed warm-up, until its values are read (`fit.bench.tutorial`: Mitsuba's Adam, "
            "200 x 16 spp then 100 x 64 spp)",
            "colour: worst channel, absolute; alpha: relative; ior: absolute; each the worst "
            "over the material's layers",
            machine(),
        ],
    )
    if plot is not None:
        _plot_trade(done, seeds, cases, plot)
    warm = done[f"{LOOP_CASE} default 0"]
    cold = done["cold default"]
    parts = list(dict.fromkeys([*cold["timings"], *warm["timings"]]))
    breakdown = [
        [
            "interpreter, imports, exit (the rest)",
            *(f"{r['seconds'] - sum(r['timings'].values()):.2f}" for r in (cold, warm)),
        ]
    ]
    breakdown += [
        [part, *(f"{r['timings'].get(part, 0.0):.2f}" for r in (cold, warm))] for part in parts
    ]
    breakdown.append(["whole command", *(f"{r['seconds']:.2f}" for r in (cold, warm))])
    where = Table(
        title=f"Where the default's time goes: `layerfit fit {loop_config}`",
        columns=["part", "empty caches s", "warm s"],
        rows=breakdown,
        notes=[
            "the summary's `timings_s` (seed 0); a phase's first step records and compiles "
            f"its renders (steps per phase, warm: {warm['steps']}); the rest: the whole "
            "command's wall time less its timed parts",
            machine(),
        ],
    )
    return presets, where


def _plot_trade(done: dict, seeds: int, cases, out: Path) -> None:
    """Each object's presets as time against alpha's error (medians over the seeds, joined in
    order of time), and the tutorial loop's point."""
    from matplotlib.ticker import FixedLocator, NullFormatter, ScalarFormatter

    from ..output.figures import pyplot, save_figure

    plt = pyplot()
    fig, ax = plt.subplots(figsize=(7, 4.5))

    def point(runs):
        alpha = [measures(r).get("alpha") for r in runs]
        alpha = [a for a in alpha if a is not None]
        seconds = float(np.median([r["seconds"] for r in runs]))
        return seconds, 100 * float(np.median(alpha)) if alpha else float("nan")

    for (name, _), colour in zip(cases, ("tab:blue", "tab:orange", "tab:green"), strict=False):
        points = [point([done[f"{name} {q} {k}"] for k in range(seeds)]) for q in QUALITIES]
        ax.plot(*zip(*points, strict=True), "o-", color=colour, label=name)
        for (t, e), quality in zip(points, QUALITIES, strict=True):
            ax.annotate(quality, (t, e), textcoords="offset points", xytext=(4, 4), fontsize=8)
    t, e = point([done[f"loop {k}"] for k in range(seeds)])
    ax.scatter([t], [e], marker="X", s=90, color="tab:purple", label=f"tutorial loop ({LOOP_CASE})")
    ax.set(
        xscale="log",
        yscale="log",
        xlabel="whole command, s (the loop: in process)",
        ylabel="alpha's error, % (median over seeds)",
        title="Quality presets: time against accuracy",
    )
    # plain numbers on the log axes (not 2 x 10^1), a few of them
    ax.xaxis.set_major_locator(FixedLocator([5, 10, 20, 50, 100, 200, 500]))
    ax.yaxis.set_major_locator(FixedLocator([0.1, 0.2, 0.5, 1, 2, 5, 10, 20, 50, 100]))
    for axis in (ax.xaxis, ax.yaxis):
        axis.set_major_formatter(ScalarFormatter())
        axis.set_minor_formatter(NullFormatter())
    ax.legend()
    fig.tight_layout()
    save_figure(fig, out)
