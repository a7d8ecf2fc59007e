"""Everything a fit reads and checks before any work: the capture, the held-out views, the
free parameters, the problem and its start (`prepare`), the run folder (`check_output`) and a
checkpoint to resume (`check_resume`). Every problem is a one-line `InputError` here."""

from __future__ import annotations

import dataclasses
import difflib
import json
import logging
import math
from pathlib import Path

import numpy as np

from captures import CaptureError, InputError, open_capture
from captures.capture import MIN_SIDE, Capture
from captures.errors import listing
from captures.scene import EnvMap
from materials.params import LAYER_PLUGINS, ChoiceOption

from ..config import FitConfig
from ..material import (
    Free,
    check_uvs,
    parse_key,
    resolve,
    start_values,
)
from ..output import write_text
from ..solvers import Checkpoint, Problem
from ..solvers.gn import AUTO_SPLIT
from ..solvers.schedule import Phase, check_saved
from ..solvers.uncertainty import forward_mode_refusal
from .run_folder import LOCK

log = logging.getLogger(__name__)


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
    elif out.exists() and any(p.name != LOCK for p in out.iterdir()):  # a lock: its own
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
            _warn(
                capture,
                f"{path}: the truth was made with {key} = {choice!r}, the material has "
                f"{have!r} ({scored}); set {option} = {choice!r} on the {layer or 'material'} "
                "layer to fit the same model",
            )
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
            _warn(
                capture,
                f"{path}: the peer's truth.{f.key} = {value} is outside the parameter's bounds "
                f"[{f.spec.lower:g}, {f.spec.upper:g}] ({f.spec.doc}): the fit cannot reach it "
                "and ends near the bound; not scored",
            )
            del capture.truth[f.key]


def _warn(capture: Capture, message: str) -> None:
    """A warning: logged now, and kept with the capture for the summary and the report."""
    log.warning(message)
    capture.warnings.append(message)


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
        "phases": [f"{p.describe()} x {p.steps} {p.options!r}" for p in prepared.phases],
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
    check_saved(saved, u, len(prepared.phases), checkpoint.path)
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
    phases: list[Phase]  # the schedule at the fit's quality for these views (`fit_phases`)


def fit_phases(cfg: FitConfig, problem: Problem) -> list[Phase]:
    """`cfg`'s schedule at its quality preset for `problem`'s fitted views (a draft halves the
    resolution of views that keep `DRAFT_MIN_SIDE` pixels a side)."""
    return cfg.phases_for(min(min(v.image.shape[:2]) for v in problem.capture.views))


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
    phases = fit_phases(cfg, problem)
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
    for k, phase in enumerate(phases):  # a gains option where no gain is fitted
        if not cfg.gains and "profile_gains" in phase.options.model_fields_set and trace:
            messages.append(
                f"{cfg.path}: fit.phases[{k}].profile_gains: no gains are fitted (fit.gains is "
                "false), so it does nothing; remove it, or set fit.gains"
            )
    for message in messages:
        _warn(capture, message)
    # with textures free, forward-mode solvers move the scalars, the textures held
    scalars = [f for f in free if not f.shape]
    if problem.textures and not scalars:
        refusal = f"every free parameter is a texture ({', '.join(problem.textures)})"
    elif problem.textures:
        refusal = forward_mode_refusal(dataclasses.replace(problem, free=scalars, _cache={}))
    else:
        refusal = forward_mode_refusal(problem)
    # the default schedule's phases are named as such, with how to give others
    notes = [] if "phases" in cfg.settings.model_fields_set else ["the default schedule"]
    notes += [f"at fit.quality = {cfg.quality!r}"] if cfg.quality != "default" else []
    given = f" ({', '.join(notes)})" if notes else ""
    largest, sizes = 0, set()
    for k, phase in enumerate(phases):  # fail before any work, naming the phase
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
            if not given:
                fix = "give a smaller factor"
            else:
                fix = (
                    'give [[fit.phases]] of your own with downscale = 1 (README, "Fitting"), '
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
        _warn(
            capture,
            f"{cfg.path}: the fit renders {largest:,} pixels a step (views of "
            f"{listing(sorted(sizes))}): "
            f"each step will take long and much memory; {_smaller(cfg, largest)}",
        )
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
    return Prepared(capture, held, free, problem, start_values(free), phases)


#: Pixels a step (all fitted views, a phase's resolution) above which a fit is warned: the
#: shipped jobs render 18,000-58,000; three 6000x4000 photos (72 M) took 15 GB and no step in
#: 6 minutes.
LARGE_PIXELS = 2_000_000


def _smaller(cfg: FitConfig, pixels: int) -> str:
    """How to render about a million pixels a step: a larger `fit.downscale`."""
    factor = cfg.downscale * math.ceil(math.sqrt(pixels / 1e6))
    return f"set fit.downscale = {factor} (now {cfg.downscale}: about 1 M pixels a step)"
