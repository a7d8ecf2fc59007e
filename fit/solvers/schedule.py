"""Fit schedules: phases of a solver at a sample count and resolution, the default one, and
running them in turn (then the uncertainty at the result)."""

from __future__ import annotations

import fnmatch
import time
from collections.abc import Callable
from typing import Annotated

import numpy as np
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    PositiveInt,
    PrivateAttr,
    ValidationError,
    model_validator,
)

from captures.errors import InputError
from captures.model import FieldError

from .. import timing
from ..limits import MAX_SPP, QUALITIES
from .base import Options, PhaseReport, Result
from .checkpoint import Checkpoint
from .problem import Problem
from .registry import SOLVERS
from .textures import (
    PROBE_SEED_OFFSET,
    Smoothed,
    curvature,
    residual_variance,
    smooth_textures,
    texel_sd,
    texel_trade,
)
from .uncertainty import forward_mode_refusal, uncertainty


class Phase(BaseModel):
    """One phase of a schedule (a `[[fit.phases]]` table): a solver, its steps, samples per pixel
    and resolution; the solver's own options (Adam's `lr`, LM's `jacobian_spp`, ...) beside them,
    checked against the solver's `Options`."""

    model_config = ConfigDict(
        extra="allow", frozen=True, strict=True, use_attribute_docstrings=True
    )

    solver: str
    """The solver: adam | gn | lm | bfgs (`fit/solvers/registry.py`)."""
    steps: PositiveInt
    """Steps (Adam) or the most steps (LM, BFGS)."""
    spp: Annotated[PositiveInt, Field(le=MAX_SPP)]
    """Samples per pixel of each render (at most 2^20: `fit.limits.MAX_SPP`)."""
    downscale: PositiveInt = 1
    """This phase's resolution: the photos area-averaged by this factor, the cameras follow."""
    _options: Options = PrivateAttr()

    @model_validator(mode="after")
    def _solver_options(self):
        if self.solver not in SOLVERS:
            choices = ", ".join(SOLVERS)
            raise FieldError("solver", f"got {self.solver!r}; choose one of {choices}")
        extra = dict(self.model_extra or {})
        allowed = SOLVERS[self.solver].Options.model_fields
        for key in extra:
            if key not in allowed:
                known = ", ".join(allowed) or "none"
                raise FieldError(
                    key,
                    f"does not apply to solver = {self.solver!r}; remove it, or use one of its "
                    f"options: {known}",
                )
        try:
            self._options = SOLVERS[self.solver].Options(**extra)
        except ValidationError as err:
            first = err.errors(include_url=False)[0]
            # the field and its items' indices; not pydantic's union members ("constrained-int")
            loc = first["loc"]
            key = ".".join(str(x) for x in (loc[0], *(i for i in loc[1:] if isinstance(i, int))))
            said = (
                first["msg"].replace("Input should", "should").replace("a valid tuple", "an array")
            )
            raise FieldError(key, f"got {first['input']!r}; {said}") from None
        limit = getattr(self._options, "max_steps", None)
        if limit is not None and not self._options.precision:
            raise FieldError(
                "max_steps", "limits a phase that averages until precise; set precision"
            )
        if limit is not None and limit < self.steps:
            raise FieldError("max_steps", f"= {limit} is below steps = {self.steps}; raise it")
        if getattr(self._options, "shared_paths", False):
            if self._options.gradient != "control":
                raise FieldError(
                    "shared_paths", 'shares the control gradient\'s paths; set gradient = "control"'
                )
            primal = self._options.primal_spp
            if primal not in (None, "auto", self.spp):  # "auto": shared where it keeps one
                raise FieldError(
                    "shared_paths",
                    f"needs the image at the reverse pass's spp = {self.spp}; remove primal_spp "
                    f"= {primal!r}",
                )
        fewest = getattr(self._options, "relaxed_min_determined", None)
        if fewest is not None and fewest > self._options.relaxed_min:
            raise FieldError(
                "relaxed_min_determined",
                f"= {fewest} is above relaxed_min = {self._options.relaxed_min}; lower it",
            )
        most = getattr(self._options, "spp_limit", None)
        if most is not None and most <= self.spp:
            raise FieldError(
                "spp_limit", f"= {most} does not raise spp = {self.spp}; make it larger"
            )
        return self

    @property
    def options(self) -> Options:
        """The solver's validated options."""
        return self._options

    def __getattr__(self, name):  # phase.lr, phase.jacobian_spp: the solver's options
        options = self.__pydantic_private__.get("_options") if self.__pydantic_private__ else None
        if options is not None and name in type(options).model_fields:
            return getattr(options, name)
        return super().__getattr__(name)

    def describe(self, base: int = 1) -> str:
        """One line: solver, spp, resolution (of the full photos, `base` the fit's own
        area-averaging: fit.downscale), held keys."""
        held = getattr(self.options, "hold", ())
        return f"{self.solver}, {self.spp} spp, 1/{base * self.downscale} res" + (
            f", holding {', '.join(held)}" if held else ""
        )


#: The default schedule: Adam with fresh seeds at half resolution and 8 spp is cheap and robust from
#: far away (its scale-free steps also move a parameter started next to a bound, where the sigmoid
#: is flat); then the stochastic Gauss-Newton `gn` at full resolution, in two phases. Up to 56 steps
#: of 16 spp relax, and the mean of their last half is handed on (a single iterate wanders
#: 0.012-0.028 around alpha 0.02 at 16 spp), with 4x the samples from a curvature refresh on where a
#: value's steps are noisier than 10 % of it (`GNOptions.spp_limit`: a glossy lobe's steps at 16 spp
#: jumped alpha 0.01 next to its bound). It ends once relaxed (`GNOptions.relaxed`: quiet steps
#: whose last half has no trend, from 30 steps at its last count, or from 20 where its curvature
#: is signal and none of its steps has a trend; the Cycles sphere at 20 steps, where Adam left it
#: within its noise); ended once settled over a window (`GNOptions.window`), the
#: slow relaxation toward alpha 0.01-0.02 from a start at 0.2 stopped early (the torus at alpha 0.01
#: ended +49 to +69 % against +10 % with all 56 steps). Then steps of 64 spp are averaged, their
#: curvature refreshed every 4 so that the uncertainty takes its Jacobians: 8 steps, and more (up to
#: 32) until the average's Monte Carlo sd is within 1.5 % of every value (`precision`), its first
#: steps left out while it still relaxes (`gn.burn_in`): a glossy lobe's noise decides (the Cycles
#: torus at alpha 0.04 took 24-32 steps and ended within 3.3 %, where 8 steps ended +5.3, -5.3 and
#: +5.8 % on seeds 0-2). A gradient's variance falls faster than 1 / spp (8x for 4x the samples at
#: alpha 0.02), so the average is taken over steps of many samples; relaxing takes steps.
#: Measurements: BENCHMARKS, "Fitting: the measurements behind the default" and "Low alpha".
DEFAULT_SCHEDULE = (
    Phase(solver="adam", steps=100, spp=8, downscale=2, lr=0.1),
    Phase(
        solver="gn",
        steps=56,
        spp=16,
        jacobian_spp=16,
        refresh=10,
        average=0.5,
        spp_limit=64,
        relaxed=True,
    ),
    Phase(
        solver="gn",
        steps=8,
        spp=64,
        jacobian_spp=32,
        refresh=4,
        average=1.0,
        precision=0.015,
        max_steps=32,
    ),
)


#: Coarser grids of each free texture that the default's Adam phases move with its texels when
#: a mask's texture is free (`AdamOptions.levels`, `fit.solvers.pyramid`): a mask texel's
#: gradient goes through the layer choice's Russian roulette, far noisier than a colour's. The
#: cup's masks from ones: `mask_iou` lime 0.03 -> 0.44-0.48, glaze 0.78 both, ior 1.432 ->
#: 1.493-1.494 (truth 1.5); the DiLiGenT pot's colour per pixel relit 0.061 without, 0.063 with
#: (BENCHMARKS, "The main job", "DiLiGenT pot").
TEXTURE_LEVELS = 4
#: The free keys that are masks' textures.
MASK_TEXTURES = "*.mask.texture"
#: The full-resolution Adam phase's steps with a mask's texture free (`TEXTURE_SCHEDULE`'s 60
#: for colours): a mask texel's gradient is far noisier than a colour's. The stained sphere and
#: torus (fit seeds 0-2, BENCHMARKS "Stained objects"): IoU 0.97 and 0.95-0.96 against
#: 0.90-0.95 and 0.89-0.91, every error within 2.7 sd against 4.8, in 1.5-2x the time.
MASK_TEXTURE_STEPS = 240

#: The full-resolution Adam phase's learning rate with textures free. Adam divides each texel's
#: step by its gradient's noise, and a texel the photographs see at a grazing angle or under a
#: fraction of a pixel moves at a small share of it. Against 0.03 (Xeon-21, 2026-12-07; BENCHMARKS
#: "Stained objects", "The main job", "DiLiGenT pot"): the stained torus's stain colour within
#: 0.0103 against 0.0204 and its IoU 0.96-0.97 against 0.95-0.96 (fit seeds 0-2); the cup's masks
#: glaze 0.97, lime 0.92-0.93, stain 0.77-0.81 against 0.95-0.97, 0.91-0.92, 0.75-0.77; the
#: DiLiGenT pot relit 0.059 against 0.061, the ball 0.019 against 0.020; in the same time (0.1 on
#: the cup's seed 0: stain 0.77, its threshold 3.5 sd off).
TEXTURE_LR = 0.06

#: The default schedule with textures free (`[fit.textures]`): Adam moves everything, at half
#: resolution then at full resolution with its last half averaged (a texel's gradient is one
#: texel's pixels' noise), masks' textures coarse to fine (`TEXTURE_LEVELS`); then `gn` polishes
#: the scalars with the textures held
#: (`Problem.holding_textures`: no forward-mode render goes through a bitmap's texels), and the
#: uncertainty is the scalars' with the textures held.
TEXTURE_SCHEDULE = (
    Phase(solver="adam", steps=100, spp=8, downscale=2, lr=0.1),
    Phase(solver="adam", steps=60, spp=16, lr=TEXTURE_LR, average=0.5),
    Phase(solver="gn", steps=12, spp=64, jacobian_spp=32, refresh=6, average=1.0),
)


#: Quality presets (`fit.quality`, `layerfit fit --quality`), each a change of the schedule (the
#: default one or a config's own phases): `draft` halves every phase's steps, its step limits
#: (`max_steps`) and a relaxing phase's fewest steps (`relaxed_min`, `relaxed_min_determined`),
#: renders the full-resolution phases at half resolution where the views keep
#: `DRAFT_MIN_SIDE` pixels a side, halves the samples of every phase but the last for a material
#: of one layer (`DRAFT_SAMPLES`) and averages until `DRAFT_PRECISION`; `best` doubles every
#: phase's steps and limits (`QUALITIES`). Their time and error: BENCHMARKS, "Quality presets".

#: A draft's precise phase averages until the Monte Carlo sd is within this share of every
#: value (`GNOptions.precision`, where the phase asks less), two sd inside the draft's 10 % on
#: alpha.
DRAFT_PRECISION = 0.05
#: The fewest pixels a side a draft leaves a view when it halves the resolution: below, it keeps
#: the phase's own. The cup's draft at 32x28 (fit seeds 0-2) ended alpha +12, -22 and +5 %, at
#: 64x56 -8, +5 and +4 %; the Cycles sphere's at 80x60 within 1.1 % (BENCHMARKS, "Quality
#: presets").
DRAFT_MIN_SIDE = 48
#: The sample counts a draft halves in every phase but the last: a phase that hands on to
#: another needs only to come close. The last keeps its own: the averaged phase's gradient noise
#: grows faster than its samples fall at low alpha (at 32 spp, half the default's, the Cycles
#: torus's draft ended alpha +13 and +19 % on fit seeds 1-2). A layered material keeps them
#: too: its layers share a pixel's samples by Russian roulette, and with them halved the cup's
#: draft ended its clay's colour 0.039 off at 3.4 sd (BENCHMARKS, "Quality presets").
DRAFT_SAMPLES = ("spp", "jacobian_spp", "primal_spp", "spp_limit")


def at_quality(
    phases, quality: str = "default", side: int | None = None, layered: bool = False
) -> tuple[Phase, ...]:
    """`phases` at a quality preset (`QUALITIES`); `side`: the fitted views' smallest side at
    full resolution (unknown: a draft halves every full-resolution phase); `layered`: the
    material stacks layers (a draft keeps its samples: `DRAFT_SAMPLES`)."""
    if quality not in QUALITIES:
        raise ValueError(f"unknown quality {quality!r}; choose one of {', '.join(QUALITIES)}")
    if quality == "default":
        return tuple(phases)
    halve = side is None or side // 2 >= DRAFT_MIN_SIDE
    out = []
    for i, phase in enumerate(phases):
        fields = phase.model_dump()  # its options too (extra fields), validated again below
        limit = fields.get("max_steps")
        if quality == "draft":
            fields["steps"] = max(1, -(-phase.steps // 2))
            if i < len(phases) - 1 and not layered:
                for key in DRAFT_SAMPLES:  # `primal_spp` may be "auto": left as it is
                    if isinstance(fields.get(key), int):
                        fields[key] = max(1, fields[key] // 2)
            if halve and phase.downscale == 1:
                fields["downscale"] = 2
            if limit:
                fields["max_steps"] = max(1, -(-limit // 2))
            if fields.get("precision"):
                fields["precision"] = max(fields["precision"], DRAFT_PRECISION)
            if getattr(phase.options, "relaxed", False):
                for key in ("relaxed_min", "relaxed_min_determined"):
                    fields[key] = -(-getattr(phase.options, key) // 2)
        else:
            fields["steps"] = 2 * phase.steps
            if limit:
                fields["max_steps"] = 2 * limit
        out.append(Phase(**fields))
    return tuple(out)


#: Samples per pixel of the renders that smooth the textures after Adam
#: (`fit.solvers.textures`).
TEXTURE_SPP = 16


#: What the default schedule holds through its first Adam steps when any of it is free.
MASK_THRESHOLDS = "*.mask.threshold"


def default_schedule(
    free: list[str], textures: bool = False, scalars: bool = True
) -> tuple[Phase, ...]:
    """`DEFAULT_SCHEDULE` for these free keys (`TEXTURE_SCHEDULE` with `textures` free, its Adam
    phases alone without `scalars` free: nothing for `gn` to move). With a mask threshold free,
    its Adam phase is split, the first 30 steps holding the thresholds (colours first;
    `AdamOptions.hold`: on the cup, one seed's glaze threshold otherwise walked out of the
    noise's range in Adam's first 20 steps, where no gradient brings it back; BENCHMARKS, "The
    main job"). With a mask's texture free, its Adam phases move textures coarse to fine
    (`TEXTURE_LEVELS`), the full-resolution one for `MASK_TEXTURE_STEPS`."""
    schedule = TEXTURE_SCHEDULE if textures else DEFAULT_SCHEDULE
    if textures and not scalars:
        schedule = tuple(p for p in schedule if p.solver == "adam")
    if textures and any(fnmatch.fnmatchcase(k, MASK_TEXTURES) for k in free):
        schedule = tuple(_for_masks(p) if p.solver == "adam" else p for p in schedule)
    if not any(fnmatch.fnmatchcase(k, MASK_THRESHOLDS) for k in free):
        return schedule
    adam, *rest = schedule
    fields = adam.model_dump()  # its options too (extra fields), validated again below
    return (
        Phase(**{**fields, "steps": 30, "hold": (MASK_THRESHOLDS,)}),
        Phase(**{**fields, "steps": adam.steps - 30}),
        *rest,
    )


def _for_masks(adam: Phase) -> Phase:
    """An Adam phase of `TEXTURE_SCHEDULE` with a mask's texture free: coarse to fine, and the
    full-resolution one for `MASK_TEXTURE_STEPS`."""
    fields = {**adam.model_dump(), "levels": TEXTURE_LEVELS}
    if adam.downscale == 1:
        fields["steps"] = MASK_TEXTURE_STEPS
    return Phase(**fields)


class _Trade:
    """`trade(J1, J2)` for the uncertainty of the scalars with `problem`'s textures held at `u`
    (`fit.solvers.textures.texel_trade`, at `TEXTURE_SPP` and the last phase's resolution; with
    the colour smoother's prior weights and, at full resolution, its curvature; `stop` as the
    uncertainty's). It keeps the curvature's diagonal it used (`h`, None before a call), which
    gives the masks' texels their sd."""

    def __init__(self, problem: Problem, u, phases, seed: int, smoothed: Smoothed | None, stop):
        self.problem, self.u, self.stop = problem, u, stop
        self.downscale = phases[-1].downscale
        self.weights = smoothed.weight if smoothed is not None else None
        full = smoothed is not None and self.downscale == 1
        self.h = smoothed.curvature if full else None
        self.seed = seed + len(phases)  # the uncertainty's (the trade's renders offset their own)

    def __call__(self, jac1, jac2):
        if self.h is None:
            self.h = curvature(
                self.problem, self.u, TEXTURE_SPP, self.seed, self.downscale, self.stop
            )
        return texel_trade(
            self.problem,
            self.u,
            (jac1, jac2),
            TEXTURE_SPP,
            self.seed,
            self.downscale,
            self.weights,
            self.h,
            self.stop,
        )


def _masks_sd(problem: Problem, u, result: Result, phases, seed: int, h, stop=None):
    """Each texel's sd of the free textures no smoothing gave one (a mask's; `texel_sd`), at the
    last phase's resolution: from the curvature's diagonal `h` where the trade or the smoother
    has it there (else rendered: `stop` as the uncertainty's), and the residual's variance of one
    render, into `result`'s `texture_std` and `texture_seen`."""
    keys = {f.key for f in problem.free if f.shape} - set(result.texture_std or {})
    if not keys:
        return
    downscale, seed = phases[-1].downscale, seed + len(phases)
    if h is None:
        h = curvature(problem, u, TEXTURE_SPP, seed, downscale, stop)
    sigma2 = residual_variance(problem, u, TEXTURE_SPP, seed + PROBE_SEED_OFFSET - 1, downscale)
    std, seen = texel_sd(problem, u, h, sigma2, keys)
    result.texture_std = {**(result.texture_std or {}), **std}
    result.texture_seen = {**(result.texture_seen or {}), **seen}


def _same(u):
    return u


def _second(_, u):
    return u


def _phase_result(result: Result) -> dict:
    """What the uncertainty takes of a phase's result, for its end's checkpoint: its loss, its
    averaged tail's variance and gradients, and its Jacobians (a run stopped after the last
    phase, in its uncertainty or its files, resumed with the loss NaN and the sd without the
    tail's noise)."""
    out: dict = {"last_loss": float(result.loss)}
    if result.tail_variance is not None:
        out["last_tail_variance"] = np.asarray(result.tail_variance, np.float64)
    if result.tail_gradients is not None:
        out["last_tail_u"], out["last_tail_grad"] = (
            np.asarray(x, np.float64) for x in result.tail_gradients
        )
    if result.linearisation is not None:  # the uncertainty takes its Jacobians
        *arrays, spp = result.linearisation
        out |= {f"last_linear_{i}": np.asarray(a, np.float32) for i, a in enumerate(arrays)}
        out["last_linear_spp"] = int(spp)
    return out


def _restore_phase_result(result: Result, saved: dict, history: list) -> None:
    """The last phase's loss and tail from its end's checkpoint (`_phase_result`); from a
    checkpoint without them (an older layerfit), the loss from the history."""
    loss = saved.get("last_loss")
    result.loss = float(loss) if loss is not None else float(history[-1] if history else "nan")
    if "last_tail_variance" in saved:
        result.tail_variance = np.asarray(saved["last_tail_variance"], np.float64)
    if "last_tail_u" in saved and "last_tail_grad" in saved:
        result.tail_gradients = (
            np.asarray(saved["last_tail_u"], np.float64),
            np.asarray(saved["last_tail_grad"], np.float64),
        )
    if "last_linear_spp" in saved:
        arrays = [np.asarray(saved[f"last_linear_{i}"], np.float32) for i in range(5)]
        result.linearisation = (*arrays, int(saved["last_linear_spp"]))


def solve(
    solver: str,
    problem: Problem,
    u0,
    *,
    steps: int,
    spp: int,
    seed: int = 0,
    downscale: int = 1,
    progress: Callable[[int, float], None] | None = None,
    **options,
) -> Result:
    """One phase: `solver` (a registry name) with its `options`, from the unconstrained `u0`."""
    phase = Phase(solver=solver, steps=steps, spp=spp, downscale=downscale, **options)
    return SOLVERS[solver]().run(
        problem,
        np.asarray(u0, np.float32),
        steps=phase.steps,
        spp=phase.spp,
        seed=seed,
        downscale=phase.downscale,
        options=phase.options,
        progress=progress,
    )


def check_saved(saved: dict, u, n_phases: int, path) -> None:
    """Refuse a checkpoint saved by another fit (its vector's size or its phase)."""
    if np.shape(saved.get("u_phase")) != np.shape(u) or int(saved.get("phase", 0)) > n_phases:
        raise InputError(
            f"{path}: was saved by a different fit (other free parameters, views or "
            "phases); run without --resume (and --force) to start again"
        )


def run_schedule(
    problem: Problem,
    start: dict,
    phases: tuple[Phase, ...] | list[Phase] = DEFAULT_SCHEDULE,
    seed: int = 0,
    progress: Callable[[int, int, float], None] | None = None,
    uncertainty_spp: int = 64,
    checkpoint: Checkpoint | None = None,
    resume: bool = False,
) -> Result:
    """Run `phases` in turn from `start` (phase k uses seed + k), then the uncertainty at the
    result, at the last phase's resolution (where `forward_mode_refusal` allows it: no
    texture, at most `MAX_UNCERTAINTY_PARAMS` components; from the last `gn` phase's own
    Jacobians where they hold its samples). `progress(phase, step, loss)` after every step a
    solver reports and at the end of each phase. Each phase's report (outcome, steps, rejected
    steps, wall time) is in the result's `reports`.

    With a `checkpoint` the state is saved every interval of work and at each phase's end; with
    `resume` the run continues from the saved state (seeds follow from the phase and step, so
    the run ends where an uninterrupted one would, to float rounding)."""
    u = problem.unconstrained(start)
    history, steps, ends, reports = [], 0, [], []
    saved = checkpoint.load() if checkpoint is not None and resume else None
    first = 0
    if saved is not None:
        check_saved(saved, u, len(phases), checkpoint.path)
        checkpoint.elapsed_before = float(saved.get("elapsed_s", 0.0))
        first, u = int(saved["phase"]), np.asarray(saved["u_phase"], np.float32)
        history, ends = list(saved["history_before"]), list(saved["ends"])
        reports = [PhaseReport.from_dict(r) for r in saved["reports"]]
        steps = sum(r.steps for r in reports)
        # stopped before the first new step, the partial summary is the saved state's (it was
        # the start's values)
        checkpoint.latest = saved
        if progress:  # the phases finished before the stop show as finished
            for k, report in enumerate(reports[:first]):
                progress(k, max(phases[k].steps, report.steps), report.loss)
    result = Result(problem.values(u), u, float("nan"), 0)
    if saved is not None and first == len(phases):  # stopped after the last phase's end
        _restore_phase_result(result, saved, history)
    # colour textures are smoothed once, after the last Adam phase (before `gn` polishes the
    # scalars); a fit resumed past that point reports their texels' own sd, as a mask's
    # (`_masks_sd`)
    adams = [k for k, p in enumerate(phases) if p.solver == "adam"]
    colours = any(f.shape and f.spec.kind == "rgb" for f in problem.free)
    smooth_before = adams[-1] + 1 if colours and adams else -1
    smoothed = None
    for k in range(first, len(phases)):
        phase = phases[k]
        in_phase = saved if saved is not None and k == first and "step" in saved else None
        if k == smooth_before and in_phase is None:  # resumed inside it: u_phase is smoothed
            with timing.timed("texture smoothing"):
                smoothed = smooth_textures(problem, u, TEXTURE_SPP, seed + smooth_before)
            u = smoothed.u
        stamps: list[float] = []  # the first step's end: the renders recorded, compiled

        def report(i, value, k=k, stamps=stamps):
            if not stamps:
                stamps.append(time.perf_counter())
            if progress:
                progress(k, i, value)

        done = {
            "phase": k,
            "u_phase": np.asarray(u, np.float32),
            "history_before": list(history),
            "ends": list(ends),
            "reports": [r.as_dict() for r in reports],
        }
        # forward-mode solvers move the scalars with the textures held (Adam fits textures)
        solved, take, put = (
            problem.holding_textures(u)
            if problem.textures and phase.solver != "adam"
            else (problem, _same, _second)
        )

        def offer(state, done=done, u=u, put=put):
            # a held phase's state is of its own coordinates; `u_full` is the whole vector (a
            # stop's partial summary reads it)
            full = {"u_full": put(u, state["u"])} if "u" in state and put is not _second else {}
            checkpoint.offer({**done, **state, **full})

        began = time.perf_counter()
        result = SOLVERS[phase.solver]().run(
            solved,
            take(u),
            steps=phase.steps,
            spp=phase.spp,
            seed=seed + k,
            downscale=phase.downscale,
            options=phase.options,
            progress=report,
            resume=in_phase,
            offer=offer if checkpoint is not None else None,
        )
        result.reports[-1].seconds = seconds = time.perf_counter() - began
        first_step = stamps[0] - began if stamps else seconds
        timing.add(f"phase {k + 1} ({phase.solver}): first step", first_step)
        timing.add(f"phase {k + 1} ({phase.solver}): other steps", seconds - first_step)
        if solved is not problem:
            result.u = put(u, result.u)
            result.values = problem.values(result.u)
        if progress:  # a phase that averaged past its steps (`precision`) ends at those
            progress(k, max(phase.steps, result.steps), result.loss)
        history += result.history
        reports += result.reports
        u, steps = result.u, steps + result.steps
        ends.append(len(history))
        if checkpoint is not None:  # a phase's end is always saved
            checkpoint.latest = {
                "phase": k + 1,
                "u_phase": np.asarray(u, np.float32),
                "history_before": list(history),
                "ends": list(ends),
                "reports": [r.as_dict() for r in reports],
                **_phase_result(result),
            }
            checkpoint.flush()
            if checkpoint.stop:
                raise KeyboardInterrupt
    if smooth_before == len(phases):  # the last phase is Adam's: smoothed at the end
        with timing.timed("texture smoothing"):
            smoothed = smooth_textures(problem, u, TEXTURE_SPP, seed + smooth_before)
        u = smoothed.u
        result.u, result.values = u, problem.values(u)
    if smoothed is not None:
        result.texture_std, result.texture_weight = smoothed.std, smoothed.weight
        result.texture_seen = smoothed.seen
    result.steps, result.history, result.phase_ends, result.reports = steps, history, ends, reports
    # with textures free, the scalars' sd with the textures held (their curvature alone)
    last, take = (
        problem.holding_textures(u)[:2]
        if problem.textures and any(not f.shape for f in problem.free)
        else (problem, _same)
    )
    if problem.textures and phases[-1].solver == "adam":
        result.tail_variance = result.tail_gradients = None  # of all coordinates, not the held
    stop = None if checkpoint is None else (lambda: checkpoint.stop)
    trade = None if last is problem else _Trade(problem, u, phases, seed, smoothed, stop)
    if forward_mode_refusal(last) is None:  # else no sd: std stays None
        with timing.timed("uncertainty"):
            result.std, result.correlation, result.poorly_determined = uncertainty(
                last,
                take(u),
                uncertainty_spp,
                seed + len(phases),
                # at the last phase's resolution: the answer is that loss's minimum, and the
                # tail's gradients (of that loss) match the curvature rendered there; a draft
                # fit at half resolution spent 3.7 s of its 14.6 on full-resolution renders here
                downscale=phases[-1].downscale,
                extra_variance=result.tail_variance,
                tail_gradients=result.tail_gradients,
                # the last phase's Jacobians, where it solved this problem (not textures held)
                linearisation=result.linearisation if last is problem else None,
                # with textures held, what refitting their texels would take from the scalars
                trade=trade,
                # a Ctrl-C stops it between two renders (its checkpoint: the last phase's end);
                # once it is done, the fit is whole and is written
                stop=stop,
            )
    if any(f.shape and f.key not in (result.texture_std or {}) for f in problem.free):
        with timing.timed("texture sd"):
            h = trade.h if trade is not None else None
            if h is None and smoothed is not None and phases[-1].downscale == 1:
                h = smoothed.curvature
            _masks_sd(problem, u, result, phases, seed, h, stop)
    result.linearisation = None  # the uncertainty's only: not carried on (a start's Ray result)
    return result
