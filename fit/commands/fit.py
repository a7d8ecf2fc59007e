"""`layerfit fit`: a fit config end to end, into a run folder:

```
out/<config name>/
  preset.toml           the fitted material (native preset; fitted textures beside it)
  summary.json          values, std, truth and errors, per-view residuals, phase outcomes and
                        times, software versions
  report.html report/   photo | fit | difference per view (held-out views marked), loss per
                        phase, the parameter table, the correlation table, fitted masks
  checkpoint.npz        while running (removed at the end): `--resume` continues from it
```
Every file is written atomically; an existing run folder is never overwritten without `force`.
Stopped (Ctrl-C, SIGTERM), a fit leaves its checkpoint, a summary and report marked interrupted,
and no preset; stopped while the folder is written, it finishes writing first.
With `fit.starts` > 1 (`--starts`) the schedule runs from several starts on Ray workers and the
best one's folder is written (`fit/commands/starts.py`); the summary's `starts` lists every start.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import shlex
import signal
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from captures.errors import InputError

from .. import interrupts, timing
from ..config import FitConfig
from ..errors import OutputError, Stopped
from ..limits import QUALITIES
from ..solvers import Checkpoint, Result, run_schedule
from ..solvers.base import PhaseReport
from .prepare import Prepared, fit_identity, prepare
from .run_folder import check_free, owned, write_run, writing


class Interrupted(Exception):
    """A fit stopped by Ctrl-C after saving its checkpoint and a partial report. `saved`: whether
    the stop's own state reached the checkpoint (False: a full disk kept an earlier one, or
    none); `unwritten`: why the partial report could not be written, if it could not."""

    def __init__(self, out: Path, saved: bool = True, unwritten: str | None = None):
        super().__init__(f"interrupted; the checkpoint and a partial report are in {out}")
        self.out, self.saved, self.unwritten = out, saved, unwritten


def run_fit(
    cfg: FitConfig,
    out: Path,
    progress: Callable[[int, int, float], None] | None = None,
    resume: bool = False,
    holdout: int | None = None,
    prepared: Prepared | None = None,
    on_start: Callable[[int, dict], None] | None = None,
) -> dict:
    """Fit `cfg` into the run folder `out` (see the module's docstring); returns the summary.
    `progress(phase, step, loss)` as in `run_schedule`. On Ctrl-C the checkpoint and a partial
    summary and report are written, then `Interrupted` is raised. `prepared` (from `prepare`)
    saves opening the capture again.

    With `fit.starts` > 1 the schedule runs from that many starts on Ray workers
    (`fit.commands.starts`; `on_start(k, outcome)` as each ends, no checkpoint) and the best by a
    common high-spp loss is kept; the summary's `starts` lists them all."""
    prepared = prepared or prepare(cfg, holdout)
    capture, held, problem = prepared.capture, prepared.held, prepared.problem
    start = prepared.start
    began = time.perf_counter()
    if cfg.starts > 1:
        from .starts import run_starts

        result, spread, start = run_starts(cfg, prepared, holdout, on_start)
        wall = time.perf_counter() - began
        with _finish_first(), writing(out, None):
            summary = write_run(
                cfg, out, capture, held, problem, start, result, wall, starts=spread
            )
            Checkpoint(out / "checkpoint.npz").remove()  # an earlier single-start run's, if any
        return summary
    checkpoint = Checkpoint(out / "checkpoint.npz")
    checkpoint.identity = fit_identity(prepared, cfg)
    try:
        with _stop_on_ctrl_c(checkpoint):
            result = run_schedule(
                problem,
                start,
                prepared.phases,
                cfg.seed,
                progress,
                cfg.uncertainty_spp,
                checkpoint,
                resume,
            )
    except Exception as err:
        # a second Ctrl-C inside a render reaches here wrapped by JAX's callback (an
        # XlaRuntimeError naming it); any other error is not the stop
        if not (checkpoint.stop and _wraps_interrupt(err)):
            raise
        raise _partial(cfg, out, prepared, checkpoint, began) from err
    except KeyboardInterrupt:
        raise _partial(cfg, out, prepared, checkpoint, began) from None
    wall = time.perf_counter() - began + checkpoint.elapsed_before  # earlier runs of it too
    with _finish_first(), writing(out, checkpoint):
        summary = write_run(cfg, out, capture, held, problem, start, result, wall)
        checkpoint.remove()
    return summary


def _wraps_interrupt(err: BaseException) -> bool:
    """Whether `err` is a `KeyboardInterrupt` wrapped by a library (JAX's callback error names
    it in its message; others chain it)."""
    seen = set()
    while err is not None and id(err) not in seen:
        if isinstance(err, KeyboardInterrupt) or "KeyboardInterrupt" in str(err):
            return True
        seen.add(id(err))
        err = err.__cause__ or err.__context__
    return False


def _partial(cfg, out, prepared: Prepared, checkpoint: Checkpoint, began: float) -> Interrupted:
    """After a stop: the checkpoint and a partial summary and report from its latest state
    written; the `Interrupted` to raise."""
    capture, held, problem, start = (
        prepared.capture,
        prepared.held,
        prepared.problem,
        prepared.start,
    )
    checkpoint.flush()
    state = checkpoint.latest or {}
    # a phase holding the textures offers its own coordinates as `u`, the whole vector as
    # `u_full`
    u = state.get("u_full", state.get("u", state.get("u_phase")))
    u = np.asarray(problem.unconstrained(start) if u is None else u)
    steps = state.get("history", [])  # the phase's live list: what was saved of it
    steps = steps[: state.get("n_history", len(steps))]
    history = list(state.get("history_before", [])) + list(steps)
    partial = Result(problem.values(u), u, history[-1] if history else math.nan, 0, history)
    ends = list(state.get("ends", []))
    if len(history) > (ends[-1] if ends else 0):  # stopped inside a phase: its steps so far
        ends.append(len(history))
    partial.phase_ends = ends
    partial.reports = [PhaseReport.from_dict(r) for r in state.get("reports", [])]
    wall = time.perf_counter() - began + checkpoint.elapsed_before
    try:
        with _finish_first(), writing(out, checkpoint):
            write_run(cfg, out, capture, held, problem, start, partial, wall, interrupted=True)
    except OutputError as err:  # still a stop (exit 130), with what could not be written
        return Interrupted(out, not checkpoint.unsaved, str(err))
    return Interrupted(out, not checkpoint.unsaved)


def _finish_first():
    """Ctrl-C (or SIGTERM) while the run folder is written waits until it is whole (a second one
    stops at once): stopped between two files, a finished fit had left its new preset beside
    the summary and report of the run it replaced."""
    return _on_first_stop(lambda: None)


def _stop_on_ctrl_c(checkpoint: Checkpoint):
    """Ctrl-C (or SIGTERM) asks the schedule to stop at its next step (never inside a render,
    where JAX would wrap the interrupt); a second one stops at once."""
    return _on_first_stop(lambda: setattr(checkpoint, "stop", True))


@contextlib.contextmanager
def _on_first_stop(note: Callable[[], None]):
    """Inside, the first Ctrl-C or SIGTERM only calls `note()`; a second one interrupts
    (KeyboardInterrupt). Only the main thread receives signals: elsewhere nothing changes."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    signals = (signal.SIGINT, signal.SIGTERM)
    previous = {s: signal.getsignal(s) for s in signals}

    def first(signum, frame):
        note()
        for s in signals:
            signal.signal(s, signal.default_int_handler)

    for s in signals:
        signal.signal(s, first)

    if interrupts.asked():  # a Ctrl-C since the command started that a library's callback swallowed
        first(signal.SIGINT, None)
    try:
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)


def fit(
    config: Path,
    out: Path | None = None,
    resume: bool = False,
    force: bool = False,
    holdout: int | None = None,
    starts: int | None = None,
    variant: str | None = None,
    progress=None,
    quality: str | None = None,
    seed: int | None = None,
) -> tuple[dict, Path]:
    """`layerfit fit`: fit `config`'s free parameters to its capture into the run folder `out`
    (default `out/<config name>`); returns the summary and the run folder.

    `resume` continues a killed run from its checkpoint; `force` replaces an earlier run's
    results; `holdout` views are kept out and scored; `starts` > 1 fits from that many starts
    on Ray workers; `quality` and `seed` replace the config's `fit.quality` and `fit.seed`
    (the resume command a stop prints repeats them). `progress`: a `rich.progress.Progress`
    (default: none shown). Bad input is an `InputError` before any work (no run folder left
    behind); a stop (Ctrl-C, SIGTERM) is `Stopped`, saying what was kept and how to resume."""
    from ..config import load_fit_config
    from .common import Quiet
    from .prepare import check_output

    progress = progress or Quiet()
    out = out or Path("out") / config.stem
    first_new = out  # the outermost folder this command would create
    while not first_new.parent.exists() and first_new.parent != first_new:
        first_new = first_new.parent
    created = not out.exists()

    def forget_out() -> None:  # a failed start leaves no empty run folder (nor its parents)
        folder = out
        while created and folder.is_dir() and not any(folder.iterdir()):
            folder.rmdir()
            if folder == first_new:
                break
            folder = folder.parent

    cfg = load_fit_config(config, seed=seed)
    if quality is not None:
        if quality not in QUALITIES:
            raise InputError(f"--quality {quality!r}: choose one of {', '.join(QUALITIES)}")
        settings = cfg.settings.model_copy(update={"quality": quality})
        cfg = dataclasses.replace(cfg, settings=settings)
    if starts is not None:
        if starts > 1 and resume:
            raise InputError(f"--starts {starts}: a multi-start fit has no checkpoint to --resume")
        settings = cfg.settings.model_copy(update={"starts": starts})
        cfg = dataclasses.replace(cfg, settings=settings)
    check_free(out)
    check_output(out, cfg, resume, force)
    try:
        with owned(out):
            summary = _fit_owned(
                cfg, config, out, resume, holdout, starts, variant, progress, (quality, seed)
            )
    except BaseException:  # nothing written: no empty run folder left (a checkpoint is kept)
        progress.stop()
        forget_out()
        raise
    return summary, out


def _fit_owned(cfg, config, out, resume, holdout, starts, variant, progress, given) -> dict:
    """`fit`'s work once it owns the run folder, its parts timed into the summary's
    `timings_s`; a stop is `Stopped`, saying what was kept."""
    with timing.recording():
        return _fit_timed(cfg, config, out, resume, holdout, starts, variant, progress, given)


def _fit_timed(cfg, config, out, resume, holdout, starts, variant, progress, given) -> dict:
    from ..cluster import Cancelled
    from .common import start
    from .prepare import check_resume

    try:
        with timing.timed("start Mitsuba, Dr.Jit and the plugins"):
            start(variant)
        with timing.timed("read the capture, build the problem"):
            prepared = prepare(cfg, holdout)  # reads the photos: a Ctrl-C stops it at once
        if interrupts.asked():  # one that JAX's gc callback swallowed meanwhile
            raise KeyboardInterrupt
        if resume:  # before any progress bar: a checkpoint of another fit is one line
            check_resume(prepared, cfg, out)
    except KeyboardInterrupt:
        raise Stopped("interrupted before the fit began: nothing written") from None
    phases = prepared.phases if cfg.starts == 1 else ()
    tasks = [
        progress.add_task(f"fit {k + 1}/{len(phases)}: {p.describe(cfg.downscale)}", total=p.steps)
        for k, p in enumerate(phases)
    ]
    if cfg.starts > 1:
        tasks.append(progress.add_task(f"{cfg.starts} starts on Ray workers", total=cfg.starts))
    try:
        return run_fit(
            cfg,
            out,
            # a phase may average past its steps (`precision`): its bar grows with it
            lambda k, n, loss: progress.update(
                tasks[k], completed=n, total=max(n, phases[k].steps)
            ),
            resume,
            holdout,
            prepared,
            lambda k, row: progress.advance(tasks[-1]),
        )
    except (Interrupted, KeyboardInterrupt) as err:
        progress.stop()
        what = stopped(err, config, out, holdout, variant, starts, *given)
        raise Stopped(what, getattr(err, "unwritten", None)) from None
    except Cancelled as err:  # --starts: the Ray tasks were cancelled
        raise Stopped(f"{err}; nothing written") from None


def stopped(err, config, out, holdout, variant, starts, quality=None, seed=None) -> str:
    """What a stopped fit left: its checkpoint (the stop's own state, or an earlier one when a
    full disk kept that from being written) and how to resume it."""
    if not (out / "checkpoint.npz").exists():
        return "nothing to resume (stopped before the first checkpoint)"
    what = (
        "checkpoint saved"
        if getattr(err, "saved", True)
        else "the stop's state could not be saved (an earlier checkpoint is kept)"
    )
    command = resume_command(config, out, holdout, variant, starts, quality, seed)
    return f"{what}; resume with: {command}"


def resume_command(
    config: Path,
    out: Path,
    holdout: int | None,
    variant: str | None,
    starts: int | None = None,
    quality: str | None = None,
    seed: int | None = None,
) -> str:
    """The command that resumes this fit: its config, run folder and the options that change
    what is fitted (a resume without `--holdout` is refused as another fit), each quoted for a
    shell."""
    words = ["layerfit", "fit", str(config), "--out", str(out), "--resume"]
    words += ["--holdout", str(holdout)] if holdout is not None else []
    words += ["--variant", variant] if variant else []
    words += ["--starts", str(starts)] if starts is not None else []  # 1 over a config's many
    words += ["--quality", quality] if quality is not None else []  # over the config's own
    words += ["--seed", str(seed)] if seed is not None else []
    return shlex.join(words)
