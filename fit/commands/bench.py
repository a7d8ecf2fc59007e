"""Benchmarks: tables of measured speed (never asserted in tests). Ratios come from one run."""

from __future__ import annotations

import dataclasses
import functools
import math
import os
import platform
import statistics
import time
from dataclasses import dataclass
from pathlib import Path

import mitsuba as mi
import numpy as np

from captures.errors import InputError

from ..config import load_render_config
from ..render import load_scene, scene_dict

#: The scene the speed tables render (relative to the working directory: the repository's root).
DEFAULT_SCENE = Path("configs/glazed-sphere.toml")
CUP_SCENE = Path("configs/cup.toml")


@dataclass
class Table:
    title: str
    columns: list[str]
    rows: list[list[str]]
    notes: list[str]

    def markdown(self) -> str:
        lines = [f"### {self.title}", "", "| " + " | ".join(self.columns) + " |"]
        lines.append("|" + "---|" * len(self.columns))
        lines += ["| " + " | ".join(row) + " |" for row in self.rows]
        return "\n".join(lines + [""] + [f"- {n}" for n in self.notes]) + "\n"

    def rich(self):
        from rich.table import Table as RichTable

        table = RichTable(title=self.title, caption="\n".join(self.notes))
        for column in self.columns:
            table.add_column(column)
        for row in self.rows:
            table.add_row(*row)
        return table


def machine(cpuinfo: str | None = None) -> str:
    """The machine a table was measured on: the CPU's model name, and where /proc/cpuinfo
    says, its family, model and widest vector unit (two VMs both named "AMD EPYC" ran this
    bench's fits 4x apart: CPU family 26 with AVX-512 and an older one), the core count, the
    Mitsuba variant and version."""
    import os

    cpu, details = platform.processor() or platform.machine(), {}
    if cpuinfo is None:
        try:
            cpuinfo = Path("/proc/cpuinfo").read_text()
        except OSError:
            cpuinfo = ""
    for line in cpuinfo.splitlines():  # the first processor's lines
        key, _, value = (part.strip() for part in line.partition(":"))
        if not key:  # a blank line ends a processor's block
            if details:
                break
            continue
        details.setdefault(key, value)
    cpu = details.get("model name", cpu)
    flags = set(details.get("flags", "").split())
    extra = [f"{name} {details[key]}" for key, name in CPU_FIELDS if key in details]
    extra += [name for flag, name in SIMD if flag in flags][:1]
    cpu = f"{cpu} ({', '.join(extra)})" if extra else cpu
    return f"{cpu}, {os.cpu_count()} cores, {mi.variant()}, mitsuba {mi.__version__}"


#: The /proc/cpuinfo fields a machine line names, and how.
CPU_FIELDS = (("cpu family", "family"), ("model", "model"))
#: The vector units Dr.Jit's LLVM backend can use, widest first (/proc/cpuinfo flag, name).
SIMD = (("avx512f", "AVX-512"), ("avx2", "AVX2"), ("avx", "AVX"), ("sse4_2", "SSE4.2"))


def _timed(scene: mi.Scene, spp: int, seed: int) -> float:
    start = time.perf_counter()
    np.asarray(mi.render(scene, spp=spp, seed=seed))  # forces the lazy result
    return time.perf_counter() - start


def bsdf_speed_table(spp: int = 64, repeats: int = 7, progress=None) -> Table:
    """Render time of our BSDFs vs Mitsuba's built-ins with matching parameters, same scene.

    `glaze` is compared with `principled` (the built-in with a Fresnel-weighted specular lobe over
    a diffuse base), `oren_nayar` with `diffuse`.
    """
    cfg = load_render_config(DEFAULT_SCENE)
    glaze = cfg.material.bsdf
    pigment = glaze["pigment"]
    principled = {
        "type": "principled",
        "base_color": pigment,
        "roughness": float(np.sqrt(glaze["roughness"])),  # principled's roughness r: alpha = r^2
        "eta": glaze["ior"],
    }
    # name: (BSDF, reference name)
    bsdfs = {
        "principled": (principled, "principled"),
        "glaze paper/schlick": (glaze, "principled"),
        "glaze paper/exact": ({**glaze, "fresnel": "exact"}, "principled"),
        "glaze reciprocal/schlick": ({**glaze, "coupling": "reciprocal"}, "principled"),
        "diffuse": ({"type": "diffuse", "reflectance": pigment}, "diffuse"),
        "oren_nayar sigma 0.5": (
            {"type": "oren_nayar", "reflectance": pigment, "sigma": 0.5},
            "diffuse",
        ),
    }
    scenes = {name: load_scene(scene_dict(cfg.scene, b, 0, spp)) for name, (b, _) in bsdfs.items()}
    times = _interleaved(scenes, spp, repeats, progress, "bench: BSDF speed")
    median = {name: statistics.median(t) for name, t in times.items()}
    cam = cfg.scene.cameras[0]
    rows = [
        [
            name,
            f"{median[name] * 1e3:.1f}",
            f"{min(times[name]) * 1e3:.1f}",
            ref,
            f"{median[name] / median[ref]:.3f}",
        ]
        for name, (_, ref) in bsdfs.items()
    ]
    return Table(
        title=f"BSDF render time: glazed-sphere scene, {cam.width}x{cam.height}, {spp} spp, prb",
        columns=["BSDF", "median ms", "min ms", "reference", "time / reference"],
        rows=rows,
        notes=[
            f"median of {repeats} interleaved renders after one untimed warm-up each",
            machine(),
        ],
    )


def _interleaved(scenes: dict, spp: int, repeats: int, progress, label: str) -> dict[str, list]:
    """Times of `repeats` renders of each scene, interleaved (so that drift hits all alike), after
    an untimed warm-up each (first renders compile kernels)."""
    task = progress.add_task(label, total=repeats * len(scenes)) if progress else None
    times: dict[str, list[float]] = {name: [] for name in scenes}
    for scene in scenes.values():
        _timed(scene, spp, 0)
    for i in range(repeats):
        for name, scene in scenes.items():
            times[name].append(_timed(scene, spp, i + 1))
            if progress:
                progress.advance(task)
    return times


def cup_speed_table(spp: int = 64, repeats: int = 5, size: int = 256, progress=None) -> Table:
    """Render time of the paper's cup (configs/cup.toml) at `size`^2, and of each of its layers
    alone as the whole material: the stack's cost relative to its most expensive layer."""
    cfg = load_render_config(CUP_SCENE)
    camera = dataclasses.replace(cfg.scene.cameras[0], width=size, height=size)
    scene = dataclasses.replace(cfg.scene, cameras=(camera,))
    stack = cfg.material.bsdf
    materials = {"cup: 4-layer stack": stack}
    materials |= {f"{name} alone": stack[name] for name in stack["layers"].split(",")}
    scenes = {name: load_scene(scene_dict(scene, m, 0, spp)) for name, m in materials.items()}
    times = _interleaved(scenes, spp, repeats, progress, "bench: cup layers")
    median = {name: statistics.median(t) for name, t in times.items()}
    slowest = max((n for n in median if n.endswith("alone")), key=median.get)
    rows = [
        [
            name,
            f"{median[name] * 1e3:.0f}",
            f"{min(times[name]) * 1e3:.0f}",
            f"{median[name] / median[slowest]:.2f}",
        ]
        for name in materials
    ]
    return Table(
        title=f"Cup render time: {size}x{size}, {spp} spp, prb, max depth {scene.max_depth}",
        columns=["material", "median ms", "min ms", f"time / {slowest}"],
        rows=rows,
        notes=[
            f"median of {repeats} interleaved renders after one untimed warm-up each",
            "a layer alone: its BSDF as the whole material (no masks, no bump)",
            machine(),
        ],
    )


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
    short = tuple(p.model_copy(update={"steps": 1}) for p in schedule)
    problem = Problem(capture, cfg.material, free, cfg.gains, cfg.loss, cfg.loss_scale)
    run_schedule(problem, start, short, cfg.seed, None, cfg.uncertainty_spp)
    problem = Problem(capture, cfg.material, free, cfg.gains, cfg.loss, cfg.loss_scale)
    began = time.perf_counter()
    result = run_schedule(problem, start, schedule, cfg.seed, None, cfg.uncertainty_spp)
    return time.perf_counter() - began, result.values


def _fit_cell_task(config: Path, name: str, variant: str | None, cpus: int):
    """In a Ray worker: `fit_cell` with the driver's variant and the task's CPUs as threads."""
    from ..batch.cluster import DEFAULT_KERNEL_CACHE, prepare_worker

    prepare_worker(cpus, variant, DEFAULT_KERNEL_CACHE)
    return fit_cell(config, name)


def _ray_cells(config: Path, names: list[str], address: str | None, advance) -> dict:
    """`fit_cell` of each schedule as a Ray task holding a whole node's CPUs (cells never share
    a node, so their wall times are not distorted; a cluster's nodes run several at once)."""
    from ..batch.cluster import connect, driver_variant

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
    task = progress.add_task("bench: fit schedules", total=len(names)) if progress else None

    def advance():
        if progress:
            progress.advance(task)

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


# Long runs: time and memory per iteration ---------------------------------------------------------

LONG_KEYS = ("glaze.pigment", "glaze.roughness", "glaze.ior")


def rss_bytes() -> int:
    """The process's resident set size now: psutil if installed, else /proc/self/statm, else the
    peak from `resource` (the only portable figure; it cannot shrink)."""
    try:
        import psutil

        return int(psutil.Process().memory_info().rss)
    except ImportError:
        pass
    try:
        pages = int(Path("/proc/self/statm").read_text().split()[1])
        return pages * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError):
        import resource

        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024  # Linux: KiB


_UNITS = {"B": 1, "KiB": 1 << 10, "MiB": 1 << 20, "GiB": 1 << 30, "TiB": 1 << 40}


def jit_stats() -> tuple[float, float, float]:
    """(bytes Dr.Jit's allocator holds in use, live JIT variables, kernels built so far: launches
    that missed the in-memory cache, compiled or loaded from disk) as `dr.whos` reports them; NaN
    where its text has no such line."""
    import re

    import drjit as dr

    text = dr.whos(True)
    used = re.search(r"(LLVM|CUDA)\s*:\s*([\d.]+) (\w+)/", text)
    live = re.search(r"Variables created\s*:\s*\d+ \(peak: \d+", text)
    rows = len(re.findall(r"^\s+\d+\s+(LLVM|CUDA)\s", text, re.MULTILINE))
    misses = re.search(r"(\d+) soft, (\d+) hard misses", text)
    return (
        float(used.group(2)) * _UNITS.get(used.group(3), float("nan")) if used else float("nan"),
        float(rows) if live else float("nan"),
        float(int(misses.group(1)) + int(misses.group(2))) if misses else float("nan"),
    )


@dataclass
class LongRun:
    """Per-step measurements of one long Adam run."""

    size: int
    spp: int
    seconds: np.ndarray
    """Wall time of each step (from one progress call to the next; step 1 includes compiling)."""
    rss: np.ndarray
    """Process RSS (bytes) after each step."""
    traces: np.ndarray
    """JAX traces so far (jaxpr traces: each re-trace of a jitted function) after each step."""
    jit_steps: np.ndarray
    """The steps at which `jit` was sampled."""
    jit: np.ndarray
    """(Dr.Jit bytes in use, live JIT variables, kernels compiled so far) at `jit_steps`."""
    values: dict


def sphere_problem(size: int, config: Path = DEFAULT_SCENE, target_spp: int = 64):
    """A one-view `size`^2 fit of `config`'s material (pigment, roughness, ior free) against its
    own render at `target_spp`."""
    from captures.capture import Capture, View

    from ..material import resolve
    from ..render import render
    from ..solvers import Problem

    cfg = load_render_config(config)
    camera = dataclasses.replace(cfg.scene.cameras[0], width=size, height=size)
    scene = dataclasses.replace(cfg.scene, cameras=(camera,))
    target = render(load_scene(scene_dict(scene, cfg.material, 0, target_spp)), target_spp, 99)
    capture = Capture(scene, [View("v", target, np.ones((size, size), np.float32), camera)])
    return Problem(capture, cfg.material, resolve(cfg.material, list(LONG_KEYS)))


def long_run(
    steps: int = 1000,
    size: int = 32,
    spp: int = 4,
    lr: float = 0.02,
    config: Path = DEFAULT_SCENE,
    sample_every: int = 10,
    progress=None,
) -> LongRun:
    """Run Adam for `steps` on `sphere_problem(size)` at `spp`, recording each step's wall time
    and RSS, and every `sample_every` steps Dr.Jit's memory, live variables and compiled
    kernels (re-tracing and leaked AD graphs make these grow)."""
    from ..material import start_values
    from ..solvers import solve

    problem = sphere_problem(size, config)
    u0 = problem.unconstrained(start_values(problem.free))
    task = progress.add_task("bench: long run", total=steps) if progress else None
    seconds, rss, traces, jit_steps, jit = [], [], [], [], []
    last, traced = [time.perf_counter()], [0]

    def count(name: str, _seconds: float, **_) -> None:
        if name == "/jax/core/compile/jaxpr_trace_duration":
            traced[0] += 1

    def record(step: int, _loss: float) -> None:
        now = time.perf_counter()
        seconds.append(now - last[0])
        rss.append(rss_bytes())
        traces.append(traced[0])
        if step % sample_every == 0 or step == 1:
            jit_steps.append(step)
            jit.append(jit_stats())
        if progress:
            progress.advance(task)
        last[0] = time.perf_counter()  # the sampling above is not the next step's time

    import jax.monitoring

    jax.monitoring.register_event_duration_secs_listener(count)
    try:
        result = solve("adam", problem, u0, steps=steps, spp=spp, seed=0, lr=lr, progress=record)
    finally:
        jax.monitoring.unregister_event_duration_listener(count)
    return LongRun(
        size,
        spp,
        np.asarray(seconds),
        np.asarray(rss, dtype=np.float64),
        np.asarray(traces),
        np.asarray(jit_steps),
        np.asarray(jit, dtype=np.float64).reshape(-1, 3),
        result.values,
    )


def long_run_table(run: LongRun, window: int = 100) -> Table:
    """First vs last `window` steps: mean time, RSS, Dr.Jit memory and kernels compiled."""
    n = len(run.seconds)
    window = max(1, min(window, n // 2))
    first, last = run.seconds[1 : window + 1], run.seconds[n - window :]  # step 1 compiles
    mib = 1 << 20
    early = min(window, n) - 1  # after the first window (compiling and caches settled)
    j0 = int(np.searchsorted(run.jit_steps, early + 1))
    j0 = min(j0, len(run.jit_steps) - 1)
    rows = [
        [
            "mean ms per step",
            f"{1e3 * first.mean():.1f}",
            f"{1e3 * last.mean():.1f}",
            f"{last.mean() / first.mean():.3f} x",
        ],
        [
            "median ms per step",
            f"{1e3 * np.median(first):.1f}",
            f"{1e3 * np.median(last):.1f}",
            f"{np.median(last) / np.median(first):.3f} x",
        ],
        [
            "process RSS MiB",
            f"{run.rss[early] / mib:.1f}",
            f"{run.rss[-1] / mib:.1f}",
            f"{(run.rss[-1] - run.rss[early]) / mib:+.1f} MiB",
        ],
        [
            "Dr.Jit memory in use MiB",
            f"{run.jit[j0, 0] / mib:.2f}",
            f"{run.jit[-1, 0] / mib:.2f}",
            f"{(run.jit[-1, 0] - run.jit[j0, 0]) / mib:+.2f} MiB",
        ],
        [
            "live JIT variables",
            f"{run.jit[j0, 1]:.0f}",
            f"{run.jit[-1, 1]:.0f}",
            f"{run.jit[-1, 1] - run.jit[j0, 1]:+.0f}",
        ],
        [
            "JAX traces (total)",
            f"{run.traces[early]}",
            f"{run.traces[-1]}",
            f"{run.traces[-1] - run.traces[early]:+d}",
        ],
        [
            "kernels built (total)",
            f"{run.jit[j0, 2]:.0f}",
            f"{run.jit[-1, 2]:.0f}",
            f"{run.jit[-1, 2] - run.jit[j0, 2]:+.0f}",
        ],
    ]
    return Table(
        title=f"Long Adam run: {n} steps, {run.size}x{run.size} sphere, one view, {run.spp} spp",
        columns=[
            "measure",
            f"steps 2-{window + 1} / at step {early + 1}",
            f"last {window} / at step {n}",
            "change",
        ],
        rows=rows,
        notes=[
            "time: from one step's end to the next (step 1, which compiles, left out); RSS from "
            "psutil or /proc/self/statm; Dr.Jit figures from dr.whos, sampled every few steps",
            machine(),
        ],
    )


def plot_long_run(run: LongRun, out: Path) -> Path:
    """A PNG of ms per step and memory (RSS, Dr.Jit) against the step."""
    from ..output.figures import pyplot, save_figure

    plt = pyplot()
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(7, 6), sharex=True)
    steps = np.arange(1, len(run.seconds) + 1)
    top.plot(steps[1:], 1e3 * run.seconds[1:], lw=0.5, color="0.6", label="per step")
    k = min(25, max(1, len(steps) // 10))
    if len(steps) > k + 1:
        smooth = np.convolve(run.seconds[1:], np.ones(k) / k, mode="valid")
        top.plot(steps[k:], 1e3 * smooth, color="C0", label=f"mean of {k}")
    top.set_ylabel("ms per step")
    top.legend(loc="upper right")
    bottom.plot(steps, run.rss / (1 << 20), color="C1", label="process RSS")
    bottom.set_ylabel("RSS MiB")
    twin = bottom.twinx()
    twin.plot(run.jit_steps, run.jit[:, 0] / (1 << 20), color="C2", label="Dr.Jit in use")
    twin.set_ylabel("Dr.Jit MiB")
    # flat should look flat: at least 16 MiB (RSS) and 1 MiB (Dr.Jit) of axis
    for axis, values, span in ((bottom, run.rss, 16), (twin, run.jit[:, 0], 1)):
        low, high = np.nanmin(values) / (1 << 20), np.nanmax(values) / (1 << 20)
        if high - low < span:
            axis.set_ylim(max(0.0, (low + high - span) / 2), (low + high + span) / 2)
    bottom.set_xlabel("Adam step")
    bottom.legend(loc="upper left")
    twin.legend(loc="lower right")
    fig.suptitle(f"Long Adam run: {run.size}x{run.size} sphere, {run.spp} spp")
    fig.tight_layout()
    return save_figure(fig, out)


# Recovery over the parameter range (issue 14) -----------------------------------------------------


#: The modules whose constants decide a default fit's answer besides its schedule (`gn`'s
#: curvature caution, the uncertainty's thresholds, the BSDFs' sampling and bounds).
FIT_MODULES = (
    "fit.solvers.adam",
    "fit.solvers.gn",
    "fit.solvers.problem",
    "fit.solvers.schedule",
    "fit.solvers.uncertainty",
    "materials.glaze",
    "materials.layered",
    "materials.microfacet",
    "materials.oren_nayar",
    "materials.params",
)


def _canonical(value):
    """`value` as JSON-able data that does not depend on the process (sets sorted: their order
    follows the string hash's per-process seed); objects without such a form as their repr,
    None where that holds an address."""
    import dataclasses

    from pydantic import BaseModel

    if isinstance(value, BaseModel):
        value = value.model_dump()
    elif dataclasses.is_dataclass(value) and not isinstance(value, type):
        value = {f.name: getattr(value, f.name) for f in dataclasses.fields(value)}
    if isinstance(value, dict):
        return {str(k): _canonical(v) for k, v in value.items()}
    if isinstance(value, set | frozenset):
        return sorted((_canonical(v) for v in value), key=repr)
    if isinstance(value, list | tuple):
        return [_canonical(v) for v in value]
    if value is None or isinstance(value, bool | int | float | str):
        return value
    text = repr(value)
    return None if " at 0x" in text else text


def constants_digest(modules=FIT_MODULES) -> str:
    """A short hash of the upper-case module constants of `modules`: a changed constant
    (`gn.CAUTION`) changes it, and it is the same in every process."""
    import hashlib
    import importlib
    import inspect
    import json

    table = {}
    for name in modules:
        module = importlib.import_module(name)
        for key, value in vars(module).items():
            if key.lstrip("_").isupper() and not (inspect.ismodule(value) or callable(value)):
                table[f"{name}.{key}"] = _canonical(value)
    text = json.dumps(table, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:12]


def schedule_key(schedule) -> list[str]:
    """A schedule as a resumable results file's setting records it: each phase's solver, spp,
    resolution, steps and options, and the digest of the fitting code's constants
    (`constants_digest`): a changed option or constant makes earlier results another setting
    (until 2026-12-01 a changed `gn.CAUTION` silently kept the old default runs)."""
    return [f"{p.describe()} x {p.steps} {p.options!r}" for p in schedule] + [
        f"constants {constants_digest()}"
    ]


def _resumed(
    results: Path,
    setting: dict,
    entries: str,
    other: str,
    replace: bool,
    required: tuple[str, ...] = ("seconds",),
) -> dict:
    """The finished entries of a resumable results file (JSON: its `setting` and `entries`,
    each entry a table with the `required` keys); none when it does not exist or with
    `replace`. A file that is not such JSON, or holds `other` (another setting), is refused:
    nothing a user has is overwritten."""
    import json

    if not results.exists() or replace:
        return {}
    try:
        saved = json.loads(results.read_text())
        same = saved.get("setting") == json.loads(json.dumps(setting))
    except (OSError, ValueError, AttributeError):
        raise InputError(f"{results}: not a bench results file; give another --results") from None
    if not same:
        raise InputError(
            f"{results}: holds {other}; give another --results, or delete it to start again"
        )
    done = saved.get(entries, {})
    if not isinstance(done, dict):
        raise InputError(
            f"{results}: {entries}: not a table of finished entries; delete the file or give "
            "another --results"
        )
    for name, entry in done.items():
        missing = [k for k in required if not isinstance(entry, dict) or k not in entry]
        if missing:
            raise InputError(
                f"{results}: {entries}[{name!r}]: no {missing[0]}; delete the file or give "
                "another --results"
            )
    return done


def recovery_table(
    cases: list,
    width: int,
    height: int,
    results: Path,
    progress=None,
    replace: bool = False,
) -> Table:
    """Fit each synthetic case back from the common start with the default schedule (see
    `fit.recovery`); each outcome is saved to `results` (JSON, rewritten atomically after
    every case) and a case already there (same size, schedule and start) is not fitted again,
    so a stopped sweep resumes (`replace`: start again). The calibration table: each
    parameter's error and error/sigma."""
    import json

    from captures.files import write_text

    from .. import recovery
    from ..solvers import DEFAULT_SCHEDULE

    schedule = " + ".join(
        f"{p.solver} {p.steps} x {p.spp} spp 1/{p.downscale}" for p in DEFAULT_SCHEDULE
    )
    setting = {
        "size": [width, height],
        "schedule": schedule,
        "phases": schedule_key(DEFAULT_SCHEDULE),
        "start": recovery.START,
    }
    done = _resumed(
        results,
        setting,
        "cases",
        "a sweep of another size, schedule, start or fitting code (its constants)",
        replace,
        ("values", "std", "seconds"),
    )
    task = progress.add_task("bench: recovery", total=len(cases)) if progress else None
    outcomes = []
    for case in cases:
        if case.name in done:
            outcome = recovery.Outcome.from_dict(case, done[case.name])
        else:
            outcome = recovery.recover(case, None, width, height)
            done[case.name] = outcome.as_dict()
            write_text(results, json.dumps({"setting": setting, "cases": done}, indent=1))
        outcomes.append(outcome)
        if progress:
            progress.advance(task)
    # each miss: what its target allows at all (two Jacobian renders at the truth; saved, so a
    # resumed sweep does not render them again)
    limits = []
    for outcome in outcomes:
        if outcome.passed():
            continue
        entry = done[outcome.case.name]
        if "limit" not in entry:
            limit = recovery.data_limit(outcome.case, width, height)
            entry["limit"] = {k: recovery.strict(v) for k, v in limit.items()}
            write_text(results, json.dumps({"setting": setting, "cases": done}, indent=1))
        sd = entry["limit"]["glaze.roughness"]
        alpha = "undetermined" if sd is None else f"{100 * sd / outcome.case.roughness:.1f} %"
        limits.append(f"{outcome.case.name}: {alpha}")
    passed = sum(o.passed() for o in outcomes)
    errors = [s for o in outcomes for k in recovery.KEYS for s in np.ravel(o.sigmas[k])]
    covered = sum(s <= recovery.MAX_SIGMAS for s in errors)
    return Table(
        title=f"Recovery over the range: {len(cases)} synthetic cases, 3 views of {width}x{height}",
        columns=[
            "case",
            "alpha error (error / sd)",
            "ior error",
            "pigment, worst channel",
            "wall s",
            "within targets and 3 sd",
        ],
        rows=recovery.calibration_rows(outcomes),
        notes=[
            f"{passed} of {len(outcomes)} cases within every target (alpha 5 % relative, ior "
            "0.03, pigment 0.02) and 3 sd; "
            f"{covered} of {len(errors)} parameter errors within 3 reported sd",
            f"each case: the truth rendered at {recovery.TARGET_SPP} spp, fitted from "
            f"{recovery.START} with the default schedule ({schedule}); ✗ marks a miss",
            *(
                [
                    "what the target's own noise allows alpha in each miss (its sd at the truth "
                    f"from two {recovery.LIMIT_SPP}-spp Jacobians, no fit): " + "; ".join(limits)
                ]
                if limits
                else []
            ),
            machine(),
        ],
    )


# The loop a Mitsuba user writes today (issue 14) --------------------------------------------------

#: The tutorial loop, pinned: Mitsuba's own Adam on raw values, 200 iterations at 16 spp and lr
#: 0.05, then 100 at 64 spp and lr 0.01; iteration i renders with seed i, its gradient with seed
#: i + TUTORIAL_GRAD_SEED; values clipped to the parameters' bounds after each step.
TUTORIAL = ((200, 16, 0.05), (100, 64, 0.01))
TUTORIAL_GRAD_SEED = 1_000_003
TUTORIAL_SEED_STRIDE = 100_000


def tutorial_loop(
    problem, start: dict, stages=TUTORIAL, seed: int = 0, record=None, every: int = 10
) -> tuple[float, dict, int]:
    """The loop of a Mitsuba tutorial, natively (no JAX, no transforms, no freezing): one scene
    per view, `mi.ad.Adam` on the raw parameter values, `dr.backward` of the weighted squared
    error through `mi.render` with a decorrelated `seed_grad`, clipped to bounds. Returns its
    wall time until the final values are read (Dr.Jit evaluates lazily: a loop's iterations
    return before their work is done), the values, and the renders (primal and adjoint each
    count one per view). With `seed` k iteration i renders with seed k x TUTORIAL_SEED_STRIDE + i
    (k = 0: the pinned seeds); `record(iteration, seconds, values)` is called every `every`
    iterations (reading the values waits for that iteration's kernels)."""
    import drjit as dr

    from ..render import MATERIAL_PREFIX

    capture = problem.capture
    _, sqrt_w = problem.target()
    scenes, params, targets, weights, offset = [], [], [], [], 0
    for i, view in enumerate(capture.views):
        scenes.append(load_scene(scene_dict(capture.scene_of(i), problem.material, 0, 16)))
        params.append(mi.traverse(scenes[-1]))
        targets.append(mi.TensorXf(view.image))
        size = view.image.size
        weights.append(mi.TensorXf(sqrt_w[offset : offset + size].reshape(view.image.shape)))
        offset += size
    keys = [MATERIAL_PREFIX + f.traverse for f in problem.free]

    def values():
        out = {}
        for f, key in zip(problem.free, keys, strict=True):
            value = np.ravel(np.asarray(opt[key], np.float64))
            out[f.key] = value.tolist() if f.size > 1 else float(value[0])
        return out

    began = time.perf_counter()
    opt = mi.ad.Adam(lr=stages[0][2])
    for f, key in zip(problem.free, keys, strict=True):
        opt[key] = type(params[0][key])(*np.ravel(start[f.key]).tolist())
    it, renders = 0, 0
    for iterations, spp, lr in stages:
        opt.set_learning_rate(lr)
        for _ in range(iterations):
            loss = mi.Float(0.0)
            for scene, p, target, weight in zip(scenes, params, targets, weights, strict=True):
                p.update(opt)
                base = seed * TUTORIAL_SEED_STRIDE + it
                image = mi.render(scene, p, spp=spp, seed=base, seed_grad=base + TUTORIAL_GRAD_SEED)
                loss += dr.sum(dr.square((image - target) * weight), axis=None)
                renders += 2
            dr.backward(loss)
            opt.step()
            for f, key in zip(problem.free, keys, strict=True):
                opt[key] = dr.clip(opt[key], f.spec.lower, f.spec.upper)
            it += 1
            if record is not None and it % every == 0:
                record(it, time.perf_counter() - began, values())
    final = values()
    return time.perf_counter() - began, final, renders


# The default against the tutorial loop on a clean target, several seeds (issue 14, item 3) -------

#: The comparison's target samples per pixel. Against the grid's 256-spp targets the least-squares
#: optimum itself lies off the truth by about the methods' own errors (measured at 128x96, the
#: mean of 64 Newton steps from the truth: alpha -1.1 +- 0.5 %, pigment red +0.24 +- 0.09 %;
#: against a 2048-spp target -0.2 +- 0.5 % and +0.04 %), so one run's error there is partly
#: the target's draw.
VERSUS_TARGET_SPP = 2048
VERSUS_WIDTH = 128


@functools.cache
def versus_capture():
    """The grid sphere's three views at `VERSUS_WIDTH`, rendered at `VERSUS_TARGET_SPP` (once)."""
    from .. import recovery

    size = (VERSUS_WIDTH, VERSUS_WIDTH * 3 // 4)
    return recovery.capture(recovery.Case("sphere"), *size, spp=VERSUS_TARGET_SPP)


def versus_run(method: str, seed: int) -> dict:
    """One run of `method` ("default" or "tutorial") with `seed` on `versus_capture()`, after an
    untimed warm-up that compiles its kernels: wall time, errors against the truth, and (the
    tutorial) its running max error every 10 iterations."""
    from .. import recovery
    from ..material import resolve
    from ..solvers import DEFAULT_SCHEDULE, Problem, run_schedule

    material = recovery.glaze(recovery.START)
    free = resolve(material, list(recovery.KEYS))
    truth = recovery.Case("sphere").truth()

    def problem():
        p = Problem(versus_capture(), material, free)
        for downscale in (1, 2):
            p.renderer(downscale)
        return p

    def max_error(values):
        return max(
            float(np.max(np.abs(np.subtract(values[k], truth[k])) / np.abs(truth[k])))
            for k in recovery.KEYS
        )

    trajectory = []
    if method == "tutorial":
        tutorial_loop(problem(), recovery.START, ((1, 16, 0.05), (1, 64, 0.01)), seed=99)
        seconds, values, _ = tutorial_loop(
            problem(),
            recovery.START,
            seed=seed,
            record=lambda it, t, v: trajectory.append([it, t, max_error(v)]),
        )
    else:
        short = tuple(p.model_copy(update={"steps": 1}) for p in DEFAULT_SCHEDULE)
        run_schedule(problem(), recovery.START, short, 99, uncertainty_spp=4)
        fitted = problem()
        recorder = _Running(lambda u: max_error(fitted.values(u)), trajectory)
        values = run_schedule(fitted, recovery.START, DEFAULT_SCHEDULE, seed, checkpoint=recorder)
        seconds = time.perf_counter() - recorder.began
        values = values.values
    return {
        "seconds": seconds,
        "max_relative_error": max_error(values),
        "values": values,
        "trajectory": trajectory,
    }


class _Running:
    """A stand-in checkpoint that records a schedule's running answer every `every` steps:
    [step, seconds, error(answer)], the answer being the iterate, or in an averaging phase the
    mean of its averaged iterates so far (what the phase would return if it stopped there)."""

    def __init__(self, error, trajectory: list, every: int = 4):
        self.error, self.trajectory, self.every = error, trajectory, every
        self.latest, self.stop, self.steps = None, False, 0
        self.began = time.perf_counter()

    def offer(self, state: dict) -> None:
        self.steps += 1
        if self.steps % self.every:
            return
        tail = state.get("tail", [])[: state.get("n_tail", 0)]
        answer = np.mean(tail, axis=0) if len(tail) else state["u"]
        seconds = time.perf_counter() - self.began
        self.trajectory.append([self.steps, seconds, self.error(np.asarray(answer, np.float32))])

    def flush(self) -> None:  # a phase's end: nothing to write
        pass


def versus_table(
    seeds: int, results: Path, progress=None, replace: bool = False, plot: Path | None = None
) -> Table:
    """The default schedule and the tutorial loop, each run with seeds 0 .. `seeds` - 1 on the grid
    sphere (three views of 128x96) against a 2048-spp target; runs are saved to `results` as
    they finish (a rerun resumes; a default run of another default schedule runs again). The
    table: each run's wall time, max relative error and time to the other method's median
    error; the plot: error against time (both running answers, the final values)."""
    import json

    from captures.files import write_text

    from .. import recovery
    from ..solvers import DEFAULT_SCHEDULE

    setting = {"target_spp": VERSUS_TARGET_SPP, "width": VERSUS_WIDTH}
    done = _resumed(
        results,
        setting,
        "runs",
        "runs of another setting",
        replace,
        ("seconds", "max_relative_error", "trajectory"),
    )
    schedule = schedule_key(DEFAULT_SCHEDULE)
    runs = [(m, k) for k in range(seeds) for m in ("default", "tutorial")]
    task = progress.add_task("bench: default vs tutorial", total=len(runs)) if progress else None
    for method, k in runs:
        name = f"{method} {k}"
        stale = method == "default" and done.get(name, {}).get("schedule") != schedule
        if name not in done or stale:  # a default run of another default schedule: again
            done[name] = versus_run(method, k) | (
                {"schedule": schedule} if method == "default" else {}
            )
            write_text(results, json.dumps({"setting": setting, "runs": done}, indent=1))
        if progress:
            progress.advance(task)
    medians = {}
    for method in ("default", "tutorial"):
        mine = [done[f"{method} {k}"] for k in range(seeds)]
        medians[method] = (
            float(np.median([d["seconds"] for d in mine])),
            float(np.median([d["max_relative_error"] for d in mine])),
        )
    rows, reach = [], {}
    for method, other in (("default", "tutorial"), ("tutorial", "default")):
        reach[method] = []
        for k in range(seeds):
            d = done[f"{method} {k}"]
            t = time_to_error(d, medians[other][1])
            reach[method].append(math.inf if t is None else t)
            rows.append(
                [
                    method,
                    str(k),
                    f"{d['seconds']:.1f}",
                    f"{100 * d['max_relative_error']:.2f} %",
                    "not reached" if t is None else f"{t:.1f}",
                ]
            )
        t = float(np.median(reach[method]))
        rows.append(
            [
                f"**{method}, median**",
                "",
                f"{medians[method][0]:.1f}",
                f"{100 * medians[method][1]:.2f} %",
                "not reached" if math.isinf(t) else f"{t:.1f}",
            ]
        )
    ratio = medians["tutorial"][0] / medians["default"][0]
    equal = medians["tutorial"][0] / float(np.median(reach["default"]))
    if plot is not None:
        _plot_versus(done, seeds, plot)
    return Table(
        title=f"The default against the tutorial loop: grid sphere, 3 views of "
        f"{VERSUS_WIDTH}x{VERSUS_WIDTH * 3 // 4}, {VERSUS_TARGET_SPP}-spp target",
        columns=["method", "seed", "wall s", "max rel. error", "s to the other's median error"],
        rows=rows,
        notes=[
            f"median wall time: the tutorial loop's is {ratio:.1f}x the default's; median max "
            f"error: default {100 * medians['default'][1]:.2f} %, tutorial "
            f"{100 * medians['tutorial'][1]:.2f} %; the default's running answer reached the "
            f"loop's median error, to stay, {equal:.1f}x sooner than the loop ended (medians)",
            "s to the other's median error: the first time after which the run's running answer "
            "(every 10 iterations of the loop; every 4 steps of the default, an averaging "
            "phase's mean so far; then the final values) stays within the other method's median "
            "max error",
            "default: the default schedule (uncertainty included), seed k; tutorial: Mitsuba's "
            "Adam on raw values, 200 x 16 spp lr 0.05 + 100 x 64 spp lr 0.01, iteration i "
            f"seeded k x {TUTORIAL_SEED_STRIDE} + i (gradient: + {TUTORIAL_GRAD_SEED}); each run "
            "after an untimed warm-up that compiles its kernels",
            "max rel. error: over the pigment's channels, alpha and ior, against the truth "
            f"(alpha 0.1, ior 1.5, blue); start {json.dumps(recovery.START)}",
            machine(),
        ],
    )


def time_to_error(run: dict, error: float) -> float | None:
    """The first time after which a run's running answer (its trajectory, then its final
    values) stays within `error`; None if its final values do not."""
    reached = None
    points = [*run["trajectory"], [None, run["seconds"], run["max_relative_error"]]]
    for _, seconds, e in points:
        if e <= error:
            reached = seconds if reached is None else reached
        else:
            reached = None
    return reached


def _plot_versus(done: dict, seeds: int, out: Path) -> None:
    from ..output.figures import pyplot, save_figure

    plt = pyplot()
    fig, ax = plt.subplots(figsize=(7, 4.5))
    for k in range(seeds):
        run = done[f"tutorial {k}"]
        if run["trajectory"]:
            _, t, e = zip(*run["trajectory"], strict=True)
            ax.plot(t, e, color="tab:purple", alpha=0.6, label="tutorial loop (running)")
        if done[f"default {k}"]["trajectory"]:
            _, t, e = zip(*done[f"default {k}"]["trajectory"], strict=True)
            ax.plot(t, e, color="tab:red", alpha=0.6, label="default (running)")
        ax.scatter(run["seconds"], run["max_relative_error"], marker="X", color="tab:purple", s=80)
        d = done[f"default {k}"]
        ax.scatter(
            d["seconds"],
            d["max_relative_error"],
            marker="*",
            color="tab:red",
            s=160,
            label="default",
        )
    handles, labels = ax.get_legend_handles_labels()
    unique = dict(zip(labels, handles, strict=True))
    ax.legend(unique.values(), unique.keys())
    ax.set(
        yscale="log",
        xlabel="wall time, s",
        ylabel="max relative error",
        title="Default vs tutorial loop, grid sphere (X, star: final values)",
    )
    fig.tight_layout()
    save_figure(fig, out)


# The bench grid: resolution x spp x solver, and the tutorial loop (issue 14) ----------------------

GRID_WIDTHS = (64, 128, 256)
GRID_SPPS = (4, 16, 64)
GRID_SOLVERS = ("adam", "lm", "bfgs", "default")
#: The diagonal subset of other shapes (the cup's, in the issue): (width, spp) pairs, each with
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
        return tuple(
            p.model_copy(update={"spp": max(1, round(p.spp * scale))}) for p in DEFAULT_SCHEDULE
        )
    raise ValueError(f"solver {solver!r}")


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
    from ..material import resolve
    from ..solvers import Problem, run_schedule

    height = width * 3 // 4
    case = recovery.Case(shape)
    capture = recovery.capture(case, width, height)
    material = recovery.glaze(recovery.START)
    free = resolve(material, list(recovery.KEYS))

    def problem():
        p = Problem(capture, material, free)
        for downscale in (1, 2):
            p.renderer(downscale)
        return p

    if solver == "tutorial":
        warm = problem()
        tutorial_loop(warm, recovery.START, ((1, 16, 0.05), (1, 64, 0.01)))
        seconds, values, renders = tutorial_loop(problem(), recovery.START)
    else:
        schedule = grid_schedule(solver, spp)
        short = tuple(p.model_copy(update={"steps": 1}) for p in schedule)
        run_schedule(problem(), recovery.START, short, 0, uncertainty_spp=4)
        p = problem()
        counts = [_counting(p.renderer(d)) for d in (1, 2)]
        began = time.perf_counter()
        values = run_schedule(p, recovery.START, schedule, 0).values
        seconds = time.perf_counter() - began
        renders = sum(c[0] for c in counts)
    truth = case.truth()
    errors = {
        k: float(np.max(np.abs(np.subtract(values[k], truth[k])) / np.abs(truth[k])))
        for k in recovery.KEYS
    }
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
    import json

    from captures.files import write_text

    from ..solvers import DEFAULT_SCHEDULE

    setting = {"default": schedule_key(DEFAULT_SCHEDULE)}
    required = ("seconds", "renders", "max_relative_error", "held_out_rmse")
    done = _resumed(
        results,
        setting,
        "cells",
        "a grid of another default schedule or fitting code (its constants)",
        replace,
        required,
    )
    task = progress.add_task("bench: grid", total=len(cells)) if progress else None
    for cell in cells:
        name = _cell_name(*cell)
        if name not in done:
            done[name] = grid_cell(*cell)
            write_text(results, json.dumps({"setting": setting, "cells": done}, indent=1))
        if progress:
            progress.advance(task)
    names = [_cell_name(*c) for c in cells]
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
            f"start {json.dumps(_start_values())}; truth: the default job's blue glaze, "
            "alpha 0.1, ior 1.5",
            machine(),
        ],
    )


def _start_values() -> dict:
    from .. import recovery

    return recovery.START


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
        handles, labels = ax.get_legend_handles_labels()
        unique = dict(zip(labels, handles, strict=True))
        ax.legend(unique.values(), unique.keys())
    fig.tight_layout()
    save_figure(fig, out)


# Where a fit's time goes (issue 14, item 3) -------------------------------------------------------


def profile_table(width: int = 160, shape: str = "sphere") -> Table:
    """The default schedule on a recovery case (three views of `width` x 3/4 width), after an
    untimed warm-up that compiles every kernel, profiled: Dr.Jit's kernel history (kernel
    execution, IR generation, compilation) and the wall time inside each kind of renderer call
    (primal, reverse, Jacobian); what is left is JAX, the solvers and Python around them."""
    import drjit as dr

    from .. import recovery
    from ..material import resolve
    from ..solvers import DEFAULT_SCHEDULE, Problem, run_schedule

    height = width * 3 // 4
    case = recovery.Case(shape)
    capture = recovery.capture(case, width, height)
    material = recovery.glaze(recovery.START)
    free = resolve(material, list(recovery.KEYS))
    # The warm-up runs on the timed fit's own scenes, two steps a phase: every frozen function
    # records at its first call and again at its second. Kernels of scenes loaded after others
    # in one process are compiled anew (Dr.Jit's kernel history: no memory or disk cache hit),
    # so a warm-up on other scenes left 3.9-5.7 s of LLVM inside the timed fit at 160x120.
    short = tuple(p.model_copy(update={"steps": 2}) for p in DEFAULT_SCHEDULE)
    problem = Problem(capture, material, free)
    run_schedule(problem, recovery.START, short, 0)
    inside = {"primal": [0, 0.0], "reverse": [0, 0.0], "jacobian": [0, 0.0]}
    for downscale in (1, 2):
        renderer = problem.renderer(downscale)
        for kind, name in (("primal", "render"), ("reverse", "vjp"), ("jacobian", "jacobian")):
            setattr(renderer, name, _timed_call(getattr(renderer, name), inside[kind]))
    dr.kernel_history_clear()
    with dr.scoped_set_flag(dr.JitFlag.KernelHistory):
        began = time.perf_counter()
        run_schedule(problem, recovery.START, DEFAULT_SCHEDULE, 0)
        wall = time.perf_counter() - began
        history = dr.kernel_history()
    execution = sum(k.get("execution_time", 0.0) for k in history) / 1000
    codegen = sum(k.get("codegen_time", 0.0) for k in history) / 1000
    backend = sum(k.get("backend_time", 0.0) for k in history) / 1000
    renderer_wall = sum(t for _, t in inside.values())
    kernels = sum(1 for k in history if k.get("type") == dr.KernelType.JIT)
    rows = [["whole fit (default schedule, uncertainty included)", f"{wall:.2f}", "100 %", ""]]

    def row(label, seconds, note=""):
        rows.append([label, f"{seconds:.2f}", f"{100 * seconds / wall:.1f} %", note])

    for kind, (calls, seconds) in inside.items():
        row(f"inside renderer calls: {kind}", seconds, f"{calls} calls")
    row("  of which Dr.Jit kernels executing", execution, f"{kernels} kernel launches")
    row("  of which kernel IR generation (tracing)", codegen)
    row("  of which compilation (LLVM)", backend, "0 when every kernel is cached")
    row(
        "  the rest inside (Python plugins traced, replays, host copies)",
        renderer_wall - execution - codegen - backend,
    )
    row("outside renderer calls (JAX, solvers, Python)", wall - renderer_wall)
    row("outside Mitsuba's kernels (all but execution)", wall - execution)
    return Table(
        title=f"Where a fit's time goes: default schedule, {shape}, 3 views of {width}x{height}",
        columns=["part", "seconds", "share", "note"],
        rows=rows,
        notes=[
            "Dr.Jit's kernel history (execution, IR generation and compile times) and wall "
            "time around each renderer call, after an untimed two-step-per-phase warm-up on "
            "the same scenes (every frozen function recorded)",
            machine(),
        ],
    )


def _timed_call(call, total: list):
    """`call`, adding its count and wall time to `total` ([calls, seconds])."""

    def timed(*args, **kwargs):
        began = time.perf_counter()
        try:
            return call(*args, **kwargs)
        finally:
            total[0] += 1
            total[1] += time.perf_counter() - began

    return timed
