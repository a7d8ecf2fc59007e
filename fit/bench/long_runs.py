"""Long runs: time and memory per Adam step over many steps (re-tracing and leaked AD graphs
make them grow), a table of the first steps against the last and a plot."""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .common import DEFAULT_SCENE, Table, machine, ticker
from .problems import sphere_problem


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
    advance = ticker(progress, "bench: long run", steps)
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
        advance()
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
