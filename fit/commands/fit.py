"""`layerfit fit`: a fit config end to end, into a run folder:

```
out/<config name>/
  preset.toml           the fitted material (native preset; fitted textures beside it)
  summary.json          values, std, truth and errors, per-view residuals, phase outcomes and
                        times, software versions
  report.html report/   photo | fit | difference per view (held-out views marked), loss per
                        phase, the parameter table, the correlation heat map, fitted masks
  checkpoint.npz        while running (removed at the end): `--resume` continues from it
```
Every file is written atomically; an existing run folder is never overwritten without `force`.
Stopped (Ctrl-C, SIGTERM), a fit leaves its checkpoint, a summary and report marked interrupted,
and no preset; stopped while the folder is written, it finishes writing first.
With `fit.starts` > 1 (`--starts`) the schedule runs from several starts on Ray workers and the
best one's folder is written (`fit/batch/starts.py`); the summary's `starts` lists every start.
"""

from __future__ import annotations

import contextlib
import dataclasses
import difflib
import errno
import html
import json
import logging
import math
import re
import signal
import threading
import time
import tomllib
from collections.abc import Callable
from pathlib import Path

import numpy as np

from captures import CaptureError, InputError, open_capture
from captures.capture import MIN_SIDE, Capture
from captures.errors import listing
from captures.images import TEXTURE_SUFFIXES, write_image
from captures.scene import EnvMap
from materials.params import LAYER_PLUGINS, ChoiceOption

from ..config import FitConfig, config_identity
from ..errors import OutputError
from ..material import (
    Free,
    at_bounds,
    check_uvs,
    parse_key,
    provenance,
    resolve,
    save_preset,
    start_values,
    to_physical,
)
from ..material.preset import software_versions
from ..output import ViewPanel, write_report, write_text
from ..solvers import Checkpoint, Problem, Result, run_schedule
from ..solvers.base import PhaseReport
from ..solvers.gn import AUTO_SPLIT
from ..solvers.schedule import check_saved
from ..solvers.uncertainty import forward_mode_refusal

log = logging.getLogger(__name__)

#: Samples per pixel of the renders in the report (and the per-view residuals).
REPORT_SPP = 64


class Interrupted(Exception):
    """A fit stopped by Ctrl-C after saving its checkpoint and a partial report. `saved`: whether
    the stop's own state reached the checkpoint (False: a full disk kept an earlier one, or
    none); `unwritten`: why the partial report could not be written, if it could not."""

    def __init__(self, out: Path, saved: bool = True, unwritten: str | None = None):
        super().__init__(f"interrupted; the checkpoint and a partial report are in {out}")
        self.out, self.saved, self.unwritten = out, saved, unwritten


def held_out(n_views: int, n: int) -> list[int]:
    """`n` view indices spread over `n_views`, never the first."""
    if n == 0:
        return []
    if not 0 < n < n_views:
        raise InputError(
            f"holdout = {n}: "
            f"{'negative' if n < 0 else f'leaves none of the {n_views} view(s) in the fit'}; "
            "keep at least one view in the fit (and hold out fewer)"
        )
    picks = sorted({min(n_views - 1, max(1, round((j + 1) * n_views / (n + 1)))) for j in range(n)})
    rest = [i for i in range(n_views - 1, 0, -1) if i not in picks]
    return sorted(picks + rest[: n - len(picks)])


def check_output(out: Path, cfg: FitConfig, resume: bool, force: bool) -> None:
    """Refuse, before any work, an output that would lose something or cannot be written."""
    if out.exists() and not out.is_dir():
        raise InputError(f"--out {out}: is a file; give a folder")
    inputs = [cfg.path, Path(cfg.capture), *cfg.material.texture_files().values()]
    from ..material.preset import read_toml

    preset = read_toml(Path(cfg.path)).get("material")
    if isinstance(preset, str):  # a starting preset (a run's preset.toml): --force replaced it
        inputs.append(Path(cfg.path).parent / preset)
    inputs = [Path(p).resolve() for p in inputs]
    if any(p == out.resolve() or p.is_relative_to(out.resolve()) for p in inputs):
        raise InputError(f"--out {out}: holds the fit's inputs; choose another folder")
    if resume:
        if cfg.starts > 1:
            raise InputError(
                f"{cfg.path}: fit.starts = {cfg.starts}: a multi-start fit has no checkpoint to "
                "--resume; run it again with --force"
            )
        if not (out / "checkpoint.npz").exists():
            raise InputError(f"--resume: no checkpoint in {out}; run without --resume")
        Checkpoint(out / "checkpoint.npz").load()  # unreadable: refused before any work
    elif out.exists() and any(out.iterdir()):
        if not force:
            raise InputError(
                f"--out {out}: exists and is not empty; choose another folder, --resume a "
                "killed run, or --force to replace its results"
            )
        if not any((out / name).is_file() for name in ("summary.json", "checkpoint.npz")):
            raise InputError(
                f"--out {out}: is not empty and holds no layerfit run (no summary.json or "
                "checkpoint.npz): --force replaces only a run's results; choose another folder"
            )
    # what the run writes, in place of entries of the other kind (found after the whole fit)
    for name, folder in RUN_ENTRIES.items():
        entry = out / name
        if entry.exists() and entry.is_dir() != folder:
            kind = "a file" if folder else "a folder"
            raise InputError(
                f"--out {out}: {name} is {kind}, where the run writes its {name}; move it away "
                "or choose another folder"
            )
    try:
        out.mkdir(parents=True, exist_ok=True)
        write_text(out / ".write-test", "")
        (out / ".write-test").unlink()
    except OSError as err:
        raise InputError(
            f"--out {out}: cannot write there ({err.strerror}); choose another folder"
        ) from None


#: The run folder's entries by name, and whether each is a folder.
RUN_ENTRIES = {
    "report": True,
    "report.html": False,
    "summary.json": False,
    "preset.toml": False,
    "checkpoint.npz": False,
}


#: Every layer plugin's choice options and their choices, by option name (`diffuse`, ...).
CHOICES = {
    o.key: o.choices
    for decl in LAYER_PLUGINS.values()
    for o in decl.options.values()
    if isinstance(o, ChoiceOption)
}


def check_truth(
    capture: Capture, free: list[Free], path, material=None, gained: dict[str, int] | None = None
) -> None:
    """A `[truth]` value of the wrong size fails before any work (not after the fit); a key
    that names no parameter of the fitted `material` is a warning (it is not scored), with the
    closest key where one is near (a typo). Where the truth is a model's other than the
    material's (`Capture.truth_options`: a peer's EON diffuse lobe), a warning names the option
    to set and the values it depends on are not scored. A view's gain (`gain.<view>`) is scored
    where `gained` (view name -> gain channels) fits it, else warned and not scored."""
    _check_gain_truth(capture, path, gained or {})
    if material is not None:
        for key, choice in capture.truth_options.items():
            layer, _, option = key.rpartition(".")
            known = CHOICES.get(option, ())
            if not known:
                raise CaptureError(
                    f"{path}: truth_options.{key}: {option!r} is no layer option; name one of "
                    f"{', '.join(CHOICES)} (as <layer>.<option>), or remove the key"
                )
            if choice not in known:
                raise CaptureError(
                    f"{path}: truth_options.{key} = {choice!r}; give one of {', '.join(known)}"
                )
            have = material.options.get(key, choice)
            if have == choice:
                continue
            # the diffuse lobe gives sigma its meaning (radians, or EON's roughness)
            dropped = [k for k in capture.truth if option == "diffuse" and k == f"{layer}.sigma"]
            for name in dropped:
                del capture.truth[name]
            scored = f"{', '.join(dropped)} not scored" if dropped else "scores compare two models"
            message = (
                f"{path}: the truth was made with {key} = {choice!r}, the material has "
                f"{have!r} ({scored}); set {option} = {choice!r} on the {layer or 'material'} "
                "layer to fit the same model"
            )
            log.warning(message)
            capture.warnings.append(message)  # in the summary and the report too
        known = sorted(material.params)
        unknown = [
            k
            for k in capture.truth
            if k not in known and not k.startswith("gain.") and not _emitter_key(path, k)
        ]
        others = []
        for name in unknown:
            near = difflib.get_close_matches(name, known, n=1, cutoff=0.8)
            if near:
                log.warning(f"{path}: truth.{name}: not scored (did you mean {near[0]}?)")
            else:
                others.append(name)
        if others:
            log.warning(
                f"{path}: truth: {', '.join(others)}: not scored (the fitted material has no "
                "such parameter)"
            )
    for f in free:
        value = capture.truth.get(f.key)
        if value is None:
            continue
        if np.size(value) != f.size:
            raise CaptureError(
                f"{path}: truth.{f.key}: has {np.size(value)} value(s) but the parameter has "
                f"{f.size}; give {'one number' if f.size == 1 else f'{f.size} numbers'}"
            )
        try:  # a truth no fit can reach would be scored as the fit's error
            f.spec.check(value, f"{path}: truth.{f.key}")
        except ValueError as err:
            if Path(str(path)).name != "scene.json":
                raise CaptureError(str(err)) from None
            # another renderer's target (a Cycles glaze of roughness 0.08: alpha 0.0064) is
            # fitted all the same, toward the nearest value the material has; not scored
            message = (
                f"{path}: the peer's truth.{f.key} = {value} is outside the parameter's bounds "
                f"[{f.spec.lower:g}, {f.spec.upper:g}] ({f.spec.doc}): the fit cannot reach it "
                "and ends near the bound; not scored"
            )
            log.warning(message)
            capture.warnings.append(message)  # in the summary and the report too
            del capture.truth[f.key]


def _check_emitters(capture: Capture, fitted: Capture, free: list[Free], path) -> None:
    """A free emitter scale needs its emitters in every fitted view's scene (it was an internal
    error at the first render: "not in the scene of view ... (nothing to fit)")."""
    keys = {f.emitter: f.key for f in free if f.emitter}
    env = capture.scene.environment
    if "environment" in keys and not (isinstance(env, EnvMap) or any(env)):
        raise InputError(
            f"{path}: fit.free: {keys['environment']}: the capture's scene has no environment "
            "(black): nothing to scale; drop the key, or give the scene an environment"
        )
    if "lights" in keys:
        dark = [
            v.name
            for v in fitted.views
            if not (v.lights if v.lights is not None else capture.scene.lights)
        ]
        if dark:
            raise InputError(
                f"{path}: fit.free: {keys['lights']}: {listing(dark)} of the capture "
                f"{'has' if len(dark) == 1 else 'have'} no light: nothing to scale; drop the key"
            )


def _check_gain_truth(capture: Capture, path, gained: dict[str, int]) -> None:
    """`gain.<view>` truths: of the size its fitted gain has (1 or 3 values), else an error
    before any work (after the fit, an internal error); of a view with no fitted gain (gains
    off, a held-out view, no such view), warned and left out of the scores."""
    for key in [k for k in capture.truth if k.startswith("gain.")]:
        view, size = key.removeprefix("gain."), gained.get(key.removeprefix("gain."))
        if size is None:
            why = "gains are not fitted (fit.gains)" if not gained else f"no fitted view {view}"
            log.warning(f"{path}: truth.{key}: not scored ({why})")
            del capture.truth[key]
        elif np.size(capture.truth[key]) != size:
            raise CaptureError(
                f"{path}: truth.{key}: has {np.size(capture.truth[key])} value(s) but the fitted "
                f"gain has {size}; give {'one number' if size == 1 else f'{size} numbers'}"
            )


def _emitter_key(path, key: str) -> bool:
    """Whether a truth key names an emitter's value; a key no parameter can have is named (a
    `glaze.base color` was an internal error)."""
    try:
        return parse_key(key).emitter
    except KeyError:
        raise CaptureError(
            f"{path}: truth.{key}: not a parameter key (layer.parameter, e.g. glaze.roughness); "
            "fix or remove it"
        ) from None


def fit_identity(prepared: Prepared, cfg: FitConfig) -> dict:
    """What makes a checkpoint this fit's (JSON values): the free parameters, the fitted views,
    each phase as written, the seed, the capture, the starting material and the loss settings
    (loss, loss_scale, gains, downscale, holdout)."""
    identity = {
        "free": [f.key for f in prepared.free],
        "views": [v.name for v in prepared.problem.capture.views],
        # a capture made again at another size (same path and names): its vector is the same
        # size, its gains' and textures' pixels are not (an internal error mid-resume)
        "view sizes": [list(v.image.shape[:2]) for v in prepared.problem.capture.views],
        "phases": [f"{p.describe()} x {p.steps} {p.options!r}" for p in cfg.phases],
        "seed": cfg.seed,
        # a checkpoint of another capture with the same view names, another starting material
        # or loss was resumed without a word (its history then mixed two losses)
        "capture": str(Path(cfg.capture).resolve()),
        "starting material": cfg.material.table(),
        "loss": [cfg.loss, cfg.loss_scale, cfg.gains, cfg.downscale, cfg.holdout],
    }
    return json.loads(json.dumps(identity, default=str))


#: Keys of `fit_identity` that earlier layerfits did not save (their checkpoints still resume).
LATER_IDENTITY = frozenset({"view sizes"})


def check_resume(prepared: Prepared, cfg: FitConfig, out: Path) -> None:
    """Refuse, before any work, a checkpoint in `out` that another fit saved (`fit_identity`:
    other free parameters, views, phases, seed, capture, starting material or loss; a vector of
    the same size would otherwise be read as this fit's)."""
    checkpoint = Checkpoint(out / "checkpoint.npz")
    saved = checkpoint.load()
    if saved is None:
        return
    u = prepared.problem.unconstrained(prepared.start)
    check_saved(saved, u, len(cfg.phases), checkpoint.path)
    theirs, ours = saved.get("identity"), fit_identity(prepared, cfg)
    if theirs is None:
        return
    if not isinstance(theirs, dict):
        raise InputError(
            f"{checkpoint.path}: its fit's identity is not a table (not a checkpoint layerfit "
            "saves); run without --resume (and with --force) to start again"
        )
    unknown = sorted(set(theirs) - set(ours))
    if unknown:  # a later layerfit's checkpoint: what it compared this one cannot
        raise InputError(
            f"{checkpoint.path}: was saved by another version of layerfit (its fit's "
            f"{', '.join(unknown)} this one does not know); run without --resume (and with "
            "--force) to start again"
        )
    # a key an earlier layerfit did not save (`LATER_IDENTITY`) is not compared: its
    # checkpoints still resume; any other key missing is a difference
    what = next(
        (k for k in ours if theirs.get(k) != ours[k] and (k in theirs or k not in LATER_IDENTITY)),
        None,
    )
    if what is not None:
        shown = f"the checkpoint's {theirs.get(what)}, this fit's {ours[what]}"
        if what == "loss":
            what = "loss, loss_scale, gains, downscale or holdout"
        raise InputError(
            f"{checkpoint.path}: was saved by a fit with other {what} "
            f"({shown if len(shown) < 160 else 'they differ'}); run without --resume (and with "
            "--force) to start again"
        )


@dataclasses.dataclass(frozen=True)
class Prepared:
    """What a fit reads before any work: the capture, the held-out views, the free parameters
    the problem and the starting values (every input error is raised while preparing)."""

    capture: Capture
    held: list[int]
    free: list[Free]
    problem: Problem
    start: dict


#: The fewest pixels a side of a view at any phase's resolution.
MIN_PIXELS = MIN_SIDE
#: A phase's options that set a render's samples per pixel, besides its `spp`.
SPP_OPTIONS = ("primal_spp", "jacobian_spp")


def _samples(phase, option: str) -> int:
    """The most samples per pixel a phase's option can render (`"auto"`: `gn`'s larger split)."""
    value = getattr(phase.options, option, None) or 0
    return AUTO_SPLIT * phase.spp if value == "auto" else value


def prepare(cfg: FitConfig, holdout: int | None = None, trace: bool = True) -> Prepared:
    """Open the capture and check everything the fit needs against it (holdout, free keys,
    `[truth]` sizes, each phase's downscale): any problem is a one-line `InputError` before
    any render. With `trace`, views without the object or seeing its faces from behind are
    warned (`view_warnings`; a multi-start's workers leave it to the command, which warned
    once)."""
    capture = open_capture(cfg.capture, cfg.downscale, f"{cfg.path}: fit.downscale")
    try:
        held = held_out(len(capture.views), cfg.holdout if holdout is None else holdout)
    except InputError as err:
        raise InputError(
            f"{'--holdout' if holdout is not None else f'{cfg.path}: fit.holdout'}: {err}"
        ) from None
    fitted = dataclasses.replace(
        capture, views=[v for i, v in enumerate(capture.views) if i not in held]
    )
    try:
        free = resolve(cfg.material, cfg.free)
    except KeyError as err:  # a free key: name the config it came from
        raise InputError(f"{cfg.path}: fit.free: {err.args[0]}") from None
    _check_emitters(capture, fitted, free, cfg.path)
    problem = Problem(fitted, cfg.material, free, cfg.gains, cfg.loss, cfg.loss_scale)
    gained = {fitted.views[i].name: problem.gain_channels for i in problem.gain_views}
    check_truth(capture, free, capture.path or cfg.capture, cfg.material, gained)
    check_uvs(capture.scene, cfg.material)
    from ..render.scene import view_warnings  # Mitsuba's: its variant is set by now

    views = [(v.name, v.camera) for v in capture.views]
    where = capture.path or cfg.capture
    masks = [None if v.mask is None else (v.mask, v.mask_coverage) for v in capture.views]
    messages = view_warnings(capture.scene, views, where, masks) if trace else []
    if cfg.gains and len(fitted.views) < 2 and trace:  # it had no effect, silently
        messages.append(
            f"{cfg.path}: fit.gains: with one fitted view its gain is pinned at 1 (the gains' "
            "geometric mean is 1), so its exposure is taken as declared; fit two or more views, "
            "or set gains = false"
        )
    unused = sorted({"start_spread", "starts_spp"} & cfg.settings.model_fields_set)
    if cfg.starts == 1 and unused and trace:  # multi-start settings for a single start
        messages.append(
            f"{cfg.path}: fit.{' and fit.'.join(unused)}: for a multi-start fit, and this one "
            "has one start; remove it, or set fit.starts (or --starts) above 1"
        )
    for k, phase in enumerate(cfg.phases):  # a gains option where no gain is fitted
        if not cfg.gains and "profile_gains" in phase.options.model_fields_set and trace:
            messages.append(
                f"{cfg.path}: fit.phases[{k}].profile_gains: no gains are fitted (fit.gains is "
                "false), so it does nothing; remove it, or set fit.gains"
            )
    for message in messages:
        log.warning(message)
        capture.warnings.append(message)  # in the summary and the report too
    refusal = forward_mode_refusal(problem)
    # the default schedule's phases are named as such, with how to give others
    given = "" if "phases" in cfg.settings.model_fields_set else " (the default schedule)"
    largest, sizes = 0, set()
    for k, phase in enumerate(cfg.phases):  # fail before any work, naming the phase
        if refusal and phase.solver in ("gn", "lm"):
            raise InputError(
                f"{cfg.path}: fit.phases[{k}].solver = {phase.solver!r}{given}: {refusal}, and "
                "it renders a forward-mode Jacobian; give [[fit.phases]] of adam only (e.g. "
                'solver = "adam", steps = 200, spp = 16)'
            )
        try:
            views = problem.at(phase.downscale).views
        except CaptureError as err:
            raise CaptureError(f"{cfg.path}: fit.phases[{k}].downscale{given}: {err}") from None
        h, w = min(v.image.shape[0] for v in views), min(v.image.shape[1] for v in views)
        if min(h, w) < MIN_PIXELS:
            fix = (
                "give a smaller factor"
                if not given
                else 'give [[fit.phases]] of your own with downscale = 1 (README, "Fitting"), '
                "or larger views"
            )
            raise InputError(
                f"{cfg.path}: fit.phases[{k}].downscale = {phase.downscale}{given} (with "
                f"fit.downscale = {cfg.downscale}) leaves a {w}x{h} view: at least {MIN_PIXELS} "
                f"pixels a side; {fix}"
            )
        if hold := getattr(phase.options, "hold", ()):
            try:
                problem.held(hold)
            except InputError as err:
                raise InputError(f"{cfg.path}: fit.phases[{k}].{err}") from None
        pixels = sum(v.image.shape[0] * v.image.shape[1] for v in views)
        spp = max(phase.spp, *(_samples(phase, name) for name in SPP_OPTIONS))
        if pixels * spp >= 2**32:
            raise InputError(
                f"{cfg.path}: fit.phases[{k}]{given}: {spp} spp over {pixels} pixels is more "
                "than Mitsuba's 2^32 samples a render; "
                + (f"{_smaller(cfg, pixels)}, or " if pixels > 1e6 else "")
                + "lower the phase's spp"
            )
        if pixels > largest:
            largest, sizes = pixels, {f"{v.image.shape[1]}x{v.image.shape[0]}" for v in views}
    if largest > LARGE_PIXELS:  # accepted without a word: 15 GB and no step in 6 minutes
        message = (
            f"{cfg.path}: the fit renders {largest:,} pixels a step (views of "
            f"{listing(sorted(sizes))}): "
            f"each step will take long and much memory; {_smaller(cfg, largest)}"
        )
        log.warning(message)
        capture.warnings.append(message)
    pixels = sum(v.image.shape[0] * v.image.shape[1] for v in fitted.views)
    full = {"uncertainty_spp": cfg.uncertainty_spp}  # renders at full resolution
    if cfg.starts > 1:
        full["starts_spp"] = cfg.starts_spp
    for name, spp in full.items():
        if pixels * spp >= 2**32:
            raise InputError(
                f"{cfg.path}: fit.{name} = {spp} over {pixels} pixels is more than Mitsuba's "
                "2^32 samples a render; lower it"
            )
    return Prepared(capture, held, free, problem, start_values(free))


#: Pixels a step (all fitted views, a phase's resolution) above which a fit is warned: the
#: shipped jobs render 18,000-58,000; three 6000x4000 photos (72 M) took 15 GB and no step in
#: 6 minutes (helper-35's audit).
LARGE_PIXELS = 2_000_000


def _smaller(cfg: FitConfig, pixels: int) -> str:
    """How to render about a million pixels a step: a larger `fit.downscale`."""
    factor = cfg.downscale * math.ceil(math.sqrt(pixels / 1e6))
    return f"set fit.downscale = {factor} (now {cfg.downscale}: about 1 M pixels a step)"


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
    (`fit.batch.starts`; `on_start(k, outcome)` as each ends, no checkpoint) and the best by a
    common high-spp loss is kept; the summary's `starts` lists them all."""
    prepared = prepared or prepare(cfg, holdout)
    capture, held, problem = prepared.capture, prepared.held, prepared.problem
    start = prepared.start
    began = time.perf_counter()
    if cfg.starts > 1:
        from ..batch.starts import run_starts

        result, spread, start = run_starts(cfg, prepared, holdout, on_start)
        wall = time.perf_counter() - began
        with _finish_first(), _writing(out, None):
            summary = _write(cfg, out, capture, held, problem, start, result, wall, starts=spread)
            Checkpoint(out / "checkpoint.npz").remove()  # an earlier single-start run's, if any
        return summary
    checkpoint = Checkpoint(out / "checkpoint.npz")
    checkpoint.identity = fit_identity(prepared, cfg)
    try:
        with _stop_on_ctrl_c(checkpoint):
            result = run_schedule(
                problem,
                start,
                cfg.phases,
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
    wall = time.perf_counter() - began + checkpoint.elapsed_before  # earlier sessions too
    with _finish_first(), _writing(out, checkpoint):
        summary = _write(cfg, out, capture, held, problem, start, result, wall)
        checkpoint.remove()
    return summary


#: What a write into a run folder fails with that its user can fix (space, quota, permissions).
WRITE_ERRORS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EACCES, errno.EROFS, errno.EPERM})


@contextlib.contextmanager
def _writing(out: Path, checkpoint: Checkpoint | None):
    """A run folder that cannot be written (a full disk) is one line saying what was kept."""
    try:
        yield
    except OSError as err:
        inside = isinstance(err.filename, str) and Path(err.filename).resolve().is_relative_to(
            Path(out).resolve()
        )
        if err.errno not in WRITE_ERRORS and not inside:  # not the folder's: not this
            raise
        kept = (
            f"its checkpoint {checkpoint.path} is kept: free space (or fix permissions) and run "
            "the same command with --resume"
            if checkpoint is not None and checkpoint.path.exists()
            else "no checkpoint was saved: free space (or fix permissions) and run it again"
        )
        raise OutputError(
            f"{out}: could not write the run folder ({err.strerror or err}"
            f"{f': {err.filename}' if err.filename else ''}); {kept}"
        ) from None


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
    u = np.asarray(state.get("u", state.get("u_phase", problem.unconstrained(start))))
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
        with _finish_first(), _writing(out, checkpoint):
            _write(cfg, out, capture, held, problem, start, partial, wall, interrupted=True)
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
    from .. import entry

    if entry.asked():  # a Ctrl-C since the command started that a library's callback swallowed
        first(signal.SIGINT, None)
    try:
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)


def _write(
    cfg, out, capture, held, problem, start, result, wall, interrupted=False, starts=None
) -> dict:
    """The run folder's files from a (possibly partial) result (`starts`: a multi-start's).
    Images an earlier run wrote into this folder (`--force`) and this one did not (a view or a
    fitted texture it no longer has) are removed once the new files are in place; other files
    are left alone."""
    before = _outputs(out)
    free = problem.free
    textures = {  # fitted textures as images next to the summary and in the preset
        f.key: np.asarray(result.values[f.key], np.float32).reshape(f.shape)
        for f in free
        if f.shape
    }
    panels = _panels(cfg, capture, held, problem, result)
    summary = _summary(cfg, capture, held, start, result, wall, panels, interrupted, free)
    if starts is not None:
        summary["starts"] = starts
    for key, texels in textures.items():
        write_image(out / f"{key}.exr", texels)
    # the fitted textures' files: the report's masks are baked from them (it showed the start's)
    fitted_material = cfg.material.with_values(result.values).with_textures(
        {key: out / f"{key}.exr" for key in textures}
    )
    if interrupted:  # no preset of a fit that did not end (nor an earlier run's beside it)
        (out / "preset.toml").unlink(missing_ok=True)
    else:
        std = {k: v for k, v in (result.std or {}).items() if k in cfg.material.params}
        save_preset(
            fitted_material,
            out / "preset.toml",
            provenance(cfg.capture, cfg.path, result.loss, std or None),
            textures,
        )
    masks = _masks(fitted_material) | {k: t[..., 0] for k, t in textures.items()}
    title = f"{cfg.path.name}{' (interrupted)' if interrupted else ''}"
    write_report(out, summary, panels, masks, title)
    # the summary last: beside no checkpoint, it marks a finished run folder (batches skip those)
    write_text(out / "summary.json", json.dumps(_finite(summary), indent=2, allow_nan=False))
    for path, inode in before.items():  # every file is written anew (atomic: a new inode)
        if path.exists() and path.stat().st_ino == inode:
            path.unlink()
    return summary


def _outputs(out: Path) -> dict[Path, int]:
    """The images an earlier fit wrote into this run folder that are there now, with their
    inodes: the PNGs its `report.html` shows, the texture files its `preset.toml` names as the
    preset writes them (`preset.<key>.<ext>`), and fitted textures named by a parameter of its
    `summary.json` (`<key>.exr`). Nothing else a user keeps there (a PNG of their own in
    `report/`, a texture a hand-edited preset names: both were deleted by `--force`)."""
    try:
        keys = set(json.loads((out / "summary.json").read_text())["values"])
    except (OSError, ValueError, KeyError, TypeError):
        keys = set()
    try:
        preset = tomllib.loads((out / "preset.toml").read_text())
    except (OSError, ValueError):
        preset = {}
    try:
        page = (out / "report.html").read_text(errors="replace")
    except OSError:
        page = ""
    shown = {html.unescape(name) for name in re.findall(r"src='report/([^'/]+\.png)'", page)}
    paths = [out / "report" / name for name in sorted(shown)]
    paths += [out / name for name in _images_named(preset) if name.startswith("preset.")]
    paths += [p for p in out.glob("*.exr") if p.stem in keys]
    return {p: p.stat().st_ino for p in paths if p.is_file()}


def _images_named(value) -> list[str]:
    """Every string in a TOML document that is the bare name (no folder) of an image file."""
    if isinstance(value, dict):
        return [s for v in value.values() for s in _images_named(v)]
    if isinstance(value, list):
        return [s for v in value for s in _images_named(v)]
    if isinstance(value, str) and value and Path(value).name == value:
        return [value] if Path(value).suffix.lower() in TEXTURE_SUFFIXES else []
    return []


def _panels(cfg, capture, held, problem, result) -> list[ViewPanel]:
    """Every view (held-out ones too) rendered at the fitted values, with its relative RMSE."""
    from ..render import Renderer

    n = problem.n_material
    x = np.asarray(to_physical(problem.free, np.asarray(result.u)[:n]), np.float32)
    flat = Renderer(capture, cfg.material, problem.free).render(x, cfg.seed + 7, REPORT_SPP)
    panels, offset = [], 0
    for i, view in enumerate(capture.views):
        size = view.image.size
        render = flat[offset : offset + size].reshape(view.image.shape)
        offset += size
        gain = result.values.get(f"gain.{view.name}", [1.0, 1.0, 1.0])
        render = render * np.asarray(gain, np.float32)
        w = view.weight[..., None]
        rmse = math.sqrt(
            float(np.sum(w * (render - view.image) ** 2))
            / max(float(np.sum(w * view.image**2)), 1e-30)
        )
        panels.append(ViewPanel(view.name, view.image, render, view.weight, i in held, rmse))
    return panels


def _masks(material) -> dict[str, np.ndarray]:
    """Each layer's mask (texture x fbm at the fitted values) baked in UV space."""
    from ..render import bake_texture

    bsdf = material.bsdf
    if bsdf.get("type") != "layered":
        return {}
    return {
        f"{name}.mask": bake_texture(bsdf[f"{name}_mask"], 256, 256)
        for name in bsdf["layers"].split(",")
        if f"{name}_mask" in bsdf
    }


def _labels(values: dict) -> list[str]:
    """One label per component of the solver's vector (`glaze.pigment[0]`, `glaze.ior`)."""
    out = []
    for key, value in values.items():
        size = np.size(value)
        out += [key] if size == 1 else [f"{key}[{i}]" for i in range(size)]
    return out


def _summary(cfg, capture, held, start, result, wall, panels, interrupted, free) -> dict:
    truth = capture.truth
    errors, z = {}, {}
    for key, value in result.values.items():
        if key in truth:
            error = np.asarray(value, float) - np.asarray(truth[key], float)
            errors[key] = error.tolist()
            std = (result.std or {}).get(key)
            if std is not None:  # an undetermined (infinite) or zero sd gives no ratio
                sd = np.asarray(std, float)
                ratio = np.where(np.isfinite(sd) & (sd > 0), error / np.maximum(sd, 1e-30), np.nan)
                z[key] = ratio.tolist()
    return {
        "config": str(Path(cfg.path).resolve()),
        "capture": str(cfg.capture),
        "capture_warnings": list(capture.warnings),
        "interrupted": interrupted,
        "phases": [
            {**p.model_dump(exclude=set(p.model_extra or ())), **p.options.model_dump()}
            for p in cfg.phases
        ],
        "outcomes": [r.as_dict() for r in result.reports],
        "seed": cfg.seed,
        "downscale": cfg.downscale,  # the photos' area-averaging before any phase's own
        "config_identity": config_identity(cfg),
        # the material's structural choices (lobes, coupling, Fresnel, noise scales)
        "options": dict(cfg.material.options),
        "holdout": [capture.views[i].name for i in held],
        "start": start,
        "values": result.values,
        "std": result.std,
        "correlation": None if result.correlation is None else result.correlation.tolist(),
        "correlation_labels": _labels(result.values),
        "poorly_determined": result.poorly_determined,
        # values that ended at a bound: the truth there, past it, or a local minimum
        "at_bounds": at_bounds(free, result.values),
        "truth": {k: truth[k] for k in result.values if k in truth},
        "error": errors,
        "error_over_std": z,
        "views": [{"name": p.name, "rmse": p.rmse, "held_out": p.held_out} for p in panels],
        "loss": result.loss,
        "history": result.history,
        "phase_ends": result.phase_ends,
        "wall_time_s": wall,
        "software": software_versions(),
    }


def _finite(value):
    """JSON-safe: non-finite floats become None (JSON has no NaN or Infinity)."""
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_finite(v) for v in value]
    if isinstance(value, float | np.floating) and not math.isfinite(value):
        return None
    if isinstance(value, np.generic):
        return value.item()
    return value
