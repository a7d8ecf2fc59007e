"""The default schedule against the tutorial loop on a clean target, several seeds each: wall
time, error, and when each one's running answer reached the other's median error."""

from __future__ import annotations

import functools
import json
import math
import time
from pathlib import Path

import numpy as np

from .common import Table, complete, legend_once, machine, resumed, schedule_key, short
from .problems import recovery_problem, relative_errors
from .tutorial import TUTORIAL_GRAD_SEED, TUTORIAL_SEED_STRIDE, TUTORIAL_WARM_UP, tutorial_loop

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
    from ..solvers import DEFAULT_SCHEDULE, run_schedule

    truth = recovery.Case("sphere").truth()

    def problem():
        return recovery_problem(versus_capture())

    def max_error(values):
        return max(relative_errors(values, truth).values())

    trajectory = []
    if method == "tutorial":
        tutorial_loop(problem(), recovery.START, TUTORIAL_WARM_UP, seed=99)
        seconds, values, _ = tutorial_loop(
            problem(),
            recovery.START,
            seed=seed,
            record=lambda it, t, v: trajectory.append([it, t, max_error(v)]),
        )
    else:
        run_schedule(problem(), recovery.START, short(DEFAULT_SCHEDULE), 99, uncertainty_spp=4)
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
        if "n_averaged" in state:  # `gn` offers all its iterates, and how many it would average
            tail = tail[len(tail) - state["n_averaged"] :] if state["n_averaged"] else []
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
    from .. import recovery
    from ..solvers import DEFAULT_SCHEDULE

    setting = {"target_spp": VERSUS_TARGET_SPP, "width": VERSUS_WIDTH}
    done = resumed(
        results,
        setting,
        "runs",
        "runs of another setting",
        replace,
        ("seconds", "max_relative_error", "trajectory"),
    )
    schedule = schedule_key(DEFAULT_SCHEDULE)

    def run(method: str, k: int) -> dict:
        return versus_run(method, k) | ({"schedule": schedule} if method == "default" else {})

    def stale(name: str, entry: dict) -> bool:  # a default run of another default schedule
        return name.startswith("default") and entry.get("schedule") != schedule

    jobs = {
        f"{m} {k}": functools.partial(run, m, k)
        for k in range(seeds)
        for m in ("default", "tutorial")
    }
    label = "bench: default vs tutorial"
    complete(results, setting, "runs", done, jobs, progress, label, stale)
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
    legend_once(ax)
    ax.set(
        yscale="log",
        xlabel="wall time, s",
        ylabel="max relative error",
        title="Default vs tutorial loop, grid sphere (X, star: final values)",
    )
    fig.tight_layout()
    save_figure(fig, out)
