"""Stochastic Gauss-Newton: fresh-seed gradients preconditioned by a Gauss-Newton curvature, the
iterates of the phase's tail averaged."""

from __future__ import annotations

from typing import Annotated, Literal

import jax
import jax.numpy as jnp
import numpy as np
from pydantic import Field, PositiveFloat, PositiveInt
from scipy.special import ndtri, stdtrit

from ..limits import MAX_SPP
from ..material import as_dict, at_bounds, to_physical
from .adam import averaged_result
from .base import AbstractSolver, Options, Outcome, Result
from .problem import image_residual, jax_seed, noise_ratio, residuals
from .uncertainty import (
    CROSS_SEED_OFFSET,
    averaging_covariance,
    cross_product,
    inverse_determined,
    linear_model,
    refuse_forward_mode,
    transform_jacobian,
    transform_slope,
)

#: With `relaxed`: the fewest steps a phase tests for drift (since its start or its last raise of
#: samples).
RELAXED_MIN = 30
#: With `relaxed`: the fewest steps where the curvature the steps were taken with is mostly
#: signal (`determined`) and no value has a trend over all of them (Adam handed on within the
#: noise: the phase had nothing to relax).
RELAXED_MIN_DETERMINED = 20


class GNOptions(Options):
    eta: float = Field(0.5, gt=0.0, le=1.0)
    """Fraction of the Gauss-Newton step taken (1: the full step to the linearised optimum)."""
    jacobian_spp: Annotated[PositiveInt, Field(le=MAX_SPP)] = 16
    """Samples per pixel of the curvature's Jacobian renders: two of half as many each, with
    their own seeds (`_curvature` discounts their noise from their product)."""
    primal_spp: Annotated[PositiveInt, Field(le=MAX_SPP)] | Literal["auto"] | None = None
    """Samples per pixel of each step's image (the residual), its reverse pass staying at the
    phase's `spp` (absent: `spp`). `"auto"` decides at the phase's start from two renders of the
    image (`noise_ratio`). Where the render's own noise is at least `AUTO_RATIO` times the rest
    of the residual (a clean target: a render, a good fit to tidy photographs), a gradient's
    noise is mostly that image noise, carried through both the image and the reverse pass's
    product with it: the image gets `AUTO_SPLIT` times `spp`, the reverse pass `spp /
    AUTO_SPLIT`. Elsewhere (the photographs' noise or an unmodelled difference dominate the
    residual, and the reverse pass's noise times it) both keep `spp`. Measured on the grid's
    sphere against a 2048-spp target (128x96, three views, seeds 0-2): the default's averaged
    phase at 256 / 16 ended at a max error of 0.13-0.53 % against 0.36-1.35 % at 64 / 64, in
    1.1x the time; but over the recovery sweep the reported sd then missed 4 of 150 errors
    (BENCHMARKS, "Fitting: the measurements behind the default"), so the default keeps one
    count. On the layered cup's photographs at its truth (ratio infinite) 256 / 16 gave 1.4x
    the variance per second of 64 / 64 (its reverse pass's own noise is larger: one layer picked
    per point)."""
    refresh: PositiveInt = 10
    """Steps between curvature updates (a Jacobian render each)."""
    damping: PositiveFloat = 1e-3
    """Levenberg damping: the curvature is scaled by 1 + damping."""
    floor: PositiveFloat = 1e-6
    """The smallest curvature eigenvalue, as a fraction of the largest."""
    marquardt: float = Field(0.0, ge=0.0)
    """Marquardt damping: this fraction of the curvature's diagonal is added to it. Directions
    that are weak only jointly (colours trading with gains) take shorter steps, where the steps'
    Monte Carlo noise swamps their signal; a direction weak on its own only by 1 + marquardt."""
    max_step: PositiveFloat = 1.0
    """The largest change of any solver coordinate in one step."""
    average: float = Field(0.5, ge=0.0, le=1.0)
    """Fraction of the last iterates averaged into the result (Polyak): of the steps taken,
    when the phase ends before its `steps` (`window`). Over a half, the first iterates while
    the phase still relaxed toward its optimum are left out (`burn_in`)."""
    window: Annotated[int, Field(ge=0)] = 0
    """The phase ends (outcome `converged`, its `steps` a limit) once its iterates have settled:
    over its last `window` steps no coordinate moved more than its noise would (`settled`).
    0: every step runs."""
    relaxed: bool = False
    """The phase ends (outcome `converged`, its `steps` a limit) at a curvature refresh once it
    has relaxed: its last `refresh` steps are quiet (every value's step noise within
    `max_step_noise`, as `spp_limit` asks, and none clipped to `max_step` while it moved a value
    by more: `largest_move`) and, over its steps since its start or its last raise of samples
    (`spp_limit`), at least `relaxed_min` of them, no value has a trend over their last half
    (`trending`; a value at its bound, `pinned`, moves nothing where its coordinate wanders):
    its result, the mean of its last `average` of them, no longer moves. From
    `relaxed_min_determined` steps where the curvature is mostly signal (`determined`) and no
    value has a trend over all of them: Adam handed on within the noise. A glossy lobe's alpha
    can sit still for 20 steps before it relaxes: on the recovery sweep's torus at alpha
    0.005-0.02 (fit seed 1) Adam handed on 0.022-0.023 and alpha fell only from step 20-30 on,
    its first Jacobians mostly noise (alpha's `signal_share` 0.45-0.49 at the first refresh,
    0.14-0.34 at the second: its curvature swollen, `_curvature`, its steps too short until
    later refreshes average that away)."""
    relaxed_min: PositiveInt = RELAXED_MIN
    """With `relaxed`: the fewest steps it tests for a trend over their last half (a draft
    halves it, as it halves the steps)."""
    relaxed_min_determined: PositiveInt = RELAXED_MIN_DETERMINED
    """With `relaxed`: the fewest steps where the curvature is mostly signal (`determined`),
    at most `relaxed_min`."""
    tolerance: PositiveFloat = 1.0
    """With `window`: the net move that counts as settled, in units of what noise alone gives
    (`settled`; smaller: stricter)."""
    precision: float = Field(0.0, ge=0.0, lt=1.0)
    """With `precision` > 0 the phase goes on past `steps`, `refresh` steps at a time up to
    `max_steps`, until its averaged answer's Monte Carlo standard deviation (from its steps'
    fresh-seed gradients, as the uncertainty takes it: `averaging_covariance`) is at most this
    share of every material value (`precision_scale`: of the value where it is bounded away from
    zero, else of the range): a glossy lobe's noise decides how long it averages (`imprecise`).
    0: `steps` steps."""
    max_steps: PositiveInt | None = None
    """With `precision`: the most steps (absent: `steps`)."""
    spp_limit: Annotated[PositiveInt, Field(le=MAX_SPP)] | None = None
    """With it, at each curvature refresh where some parameter's step noise over the last
    `refresh` steps (`step_noise`: what relaxing toward the optimum does not explain) exceeds
    `max_step_noise` of its `precision_scale`, the phase renders with `SPP_RAISE` times the
    samples from then on (the image and the reverse pass alike), its `spp` raised up to this
    many (more than `spp`). A glossy lobe's steps wander so far at 16 spp that they leave the
    region where the linear model holds: on the recovery sweep's sphere at alpha 0.01 (fit seed
    2) alpha's steps had an sd of 41 % of its value over the default's first 10 relaxing steps,
    its iterates jumped to 0.0022 next to its bound and the fit ended 60-68 % low (with it:
    +4.7 %); at alpha 0.02-0.05 the sd was 5-6 % (BENCHMARKS, "Low alpha on fit seeds 0-2").
    Absent: the phase keeps `spp`."""
    max_step_noise: PositiveFloat = 0.1
    """With `spp_limit`: the step noise (`step_noise`), as a share of a parameter's
    `precision_scale`, above which the phase raises its samples."""
    gradient: Literal["control", "reverse"] = "control"
    """Each step's gradient. `reverse`: the residual `r` of a fresh render times its reverse
    pass (another seed), `J_B^T r`. `control`: the residual's mean over the phase's last steps,
    `m` (`CONTROL_WINDOW`), goes through the reverse pass, and what the step's image adds to it
    through the curvature's own Jacobian `J` (the refreshes' mean): `J^T (r - m) + J_B^T m`.
    Its expectation is the plain gradient's where `m` is the expected residual (so the
    fixed point stays the expected loss's optimum: the Jacobian's error multiplies only `r - m`,
    zero on average), but the reverse pass's noise, which multiplies the image's in `J_B^T r`
    (alpha 0.02 on a sphere: a 16-spp gradient's Newton step has a standard deviation of 105 %
    of alpha, the image's noise alone about 20 %), now multiplies `m` only: the target's noise
    and the misfit. The image's noise meets the Jacobian's mean, not the reverse pass's noise.
    With `J` alone (no `J_B^T m`) the fixed point moves by `J`'s error times the target's
    noise: on the recovery sweep's sphere and torus at alpha 0.01-0.02 (256-spp targets) that
    ended alpha +5.5, -36, +25 and -48 % (BENCHMARKS, "Fitting: the measurements behind the
    default")."""
    shared_paths: bool = False
    """With `gradient = "control"`, loss `l2` and one sample count for the image and the reverse
    pass: the step's image is its reverse pass's own primal pass (`_one_pass`), one pass a step
    instead of an image and a pass (a 64-spp step of the Cycles sphere 545 ms against 722). The
    gradient's expectation stays the same, its noise does not: the image's noise and the
    reverse pass's now correlate through `m`. Measured on the recovery sweep (BENCHMARKS,
    "Quality presets"): in the relaxing phase the sphere at alpha 0.9 found ior's steps 15 %
    noisy where they were quiet and raised its samples; in the averaged phase the sphere's
    cases averaged fewer or as many steps, but the torus at alpha 0.01 ended +27 % (2.7 sd)
    against +8 % with paths of their own (and +31 % against +3 % with the relaxing phase's
    reverse pass at 4 spp). The default does not share them."""


#: With `primal_spp = "auto"` where the render's noise is at least `AUTO_RATIO` times the rest of
#: the residual: the image's samples are `AUTO_SPLIT` times the phase's `spp`, the reverse pass's
#: `spp` divided by it. With noise N and the rest R the reverse pass's part of a gradient's
#: variance scales as (R + N / 4) / (R + N) x 4, 2.5x at a ratio of 1, 1.6x at 4, while the
#: image's part falls 4x or more; at a ratio of 3.4 (the grid's sphere against its 256-spp target)
#: the split measured a third of the variance per second.
AUTO_SPLIT, AUTO_RATIO = 4, 2.0


def sample_split(problem, u, spp: int, seed: int, downscale: int) -> tuple[int, int, float]:
    """`primal_spp = "auto"`'s choice at `u`: (image spp, reverse spp, the noise ratio)."""
    ratio = noise_ratio(problem, u, spp, seed, downscale)
    if ratio >= AUTO_RATIO:
        return AUTO_SPLIT * spp, max(1, spp // AUTO_SPLIT), ratio
    return spp, spp, ratio


#: How many times the samples per pixel a `gn` phase with `spp_limit` takes at a raise: a
#: 16-spp gradient's noise is its image's and its reverse pass's, and 4x the samples of both at
#: alpha 0.02 cut the variance 8x (`DEFAULT_SCHEDULE`).
SPP_RAISE = 4


def step_noise(problem, iterates) -> dict[str, float]:
    """Each free key's standard deviation of its steps' noise between `iterates` (rows of
    solver vectors, a rejected step's skipped), in physical values at the last of them as a
    share of its `precision_scale` (the largest of its components'). A step's noise is what its
    coordinate's relaxation does not explain: a `gn` step moves a coordinate by a fraction of
    its distance to the optimum plus noise, so its steps are regressed on the iterates before
    them (`a + b u`) and the residuals' sd (two degrees of freedom less) is the noise; a steady
    relaxation has none. Fewer than four rows: empty."""
    x = np.asarray(iterates, np.float64)
    x = x[np.all(np.isfinite(x), axis=1)] if x.ndim == 2 else x[:0]
    if len(x) < 4:
        return {}
    n = problem.n_material
    u = x[-1, :n]
    slope = np.abs(transform_slope(problem.free, u))
    value = np.asarray(to_physical(problem.free, u.astype(np.float32)), np.float64)
    # each column's least squares `steps = a + b before`, in closed form (a coordinate that
    # never moved: b = 0)
    steps, before = np.diff(x[:, :n], axis=0), x[:-1, :n]
    steps = steps - steps.mean(axis=0)
    before = before - before.mean(axis=0)
    spread = np.sum(before**2, axis=0)
    b = np.divide(np.sum(before * steps, axis=0), spread, out=np.zeros(n), where=spread > 0)
    residual = steps - b * before
    sd = np.sqrt(np.sum(residual**2, axis=0) / max(len(steps) - 2, 1)) * slope
    share = sd / _scales(problem, value)
    out, i = {}, 0
    for f in problem.free:
        out[f.key] = float(np.max(share[i : i + f.size]))
        i += f.size
    return out


def _scales(problem, x: np.ndarray) -> np.ndarray:
    """Every material component's `precision_scale` at the physical values `x` (flat)."""
    out, i = np.empty(len(x)), 0
    for f in problem.free:
        out[i : i + f.size] = precision_scale(f.spec, x[i : i + f.size])
        i += f.size
    return np.maximum(out, 1e-12)


#: The most a coordinate's curvature is lowered below its plain `J^T J` for the Jacobian's noise.
MAX_NOISE_SHARE = 15 / 16
#: How many standard deviations of the two Jacobians' cross product `_curvature` keeps above it.
CAUTION = 1.0
#: The share of a coordinate's `J^T J` that is signal, not its Jacobians' noise, from which it
#: counts as `determined`.
DETERMINED_SHARE = 0.5


def signal_share(j1: np.ndarray, j2: np.ndarray) -> np.ndarray:
    """Each coordinate's share of its Gauss-Newton curvature that is signal: the two independent
    Jacobians' cross product (unbiased for the noise-free `J^T J`) over the mean Jacobian's
    plain one (which the noise swells: `_curvature`)."""
    plain = 0.25 * (np.sum(j1 * j1, axis=0) + 2 * np.sum(j1 * j2, axis=0) + np.sum(j2 * j2, axis=0))
    cross = np.sum(j1 * j2, axis=0)
    return np.divide(cross, plain, out=np.zeros_like(cross), where=plain > 0)


def determined(jac1: np.ndarray | None, jac2: np.ndarray | None) -> bool:
    """Whether every coordinate's curvature from the two Jacobians (solver coordinates) the
    last steps were taken with is mostly signal (`signal_share` at least `DETERMINED_SHARE`);
    without them, no."""
    return jac1 is not None and bool(np.all(signal_share(jac1, jac2) >= DETERMINED_SHARE))


#: With `gradient = "control"`: the steps whose residuals make its running mean `m` (the mean
#: of all so far for the first steps, then an exponential mean of this weight).
CONTROL_WINDOW = 8


def largest_move(problem, before: np.ndarray, after: np.ndarray) -> float:
    """The largest change of a material value between two solver vectors, in physical values
    as a share of its `precision_scale` at `before` (a value at its bound, where the transform
    is flat, barely moves however far its coordinate goes)."""
    n = problem.n_material
    x0, x1 = (
        np.asarray(to_physical(problem.free, u[:n].astype(np.float32)), np.float64)
        for u in (before, after)
    )
    return float(np.max(np.abs(x1 - x0) / _scales(problem, x0), initial=0.0))


def _curvature(j1: np.ndarray, j2: np.ndarray) -> np.ndarray:
    """A Gauss-Newton curvature from two independent Jacobians: the mean's `J^T J`, each
    coordinate scaled down to a cautious estimate of its noise-free value.

    A rendered Jacobian's noise adds its energy to `J^T J` (never negative), so the curvature
    is too large, most where the image barely depends on a coordinate: on a 160x120 sphere at
    alpha 0.012-0.02, alpha's was 15-18x its noise-free value from 16-spp Jacobians and 5-10x
    at 64 spp (pigment 1.1x, ior 1.5x); its steps were as much too short and `gn` did not relax
    within a phase. The cross product `sum(a b)` of the two is unbiased for the noise-free
    diagonal but noisy itself (its standard deviation about `sqrt(sum(a^2 b^2))`), so each
    diagonal entry is lowered only to that product plus `CAUTION` of its standard deviations
    (a step too long by more than 2/eta oscillates), at most `MAX_NOISE_SHARE` of the way, by
    scaling the coordinate's row and column (the curvature stays positive semi-definite).
    With two standard deviations the recovery sweep's averaged phase still relaxed alpha next
    to its bound ~10 % of the way a step (the sphere at 0.01 ended +44 %); with one, +10 %."""
    # the mean's J^T J from the two Jacobians' products (their cross product's diagonal is
    # sum(a b)): matrix products, not N x P sums
    cross = j1.T @ j2
    plain = 0.25 * (j1.T @ j1 + cross + cross.T + j2.T @ j2)
    diagonal = np.diag(plain)
    products = j1 * j2
    products *= products
    cautious = np.diag(cross) + CAUTION * np.sqrt(products.sum(axis=0))
    lowest = (1.0 - MAX_NOISE_SHARE) * diagonal
    ok = diagonal > 0
    scale = np.ones_like(diagonal)
    scale[ok] = np.sqrt(np.clip(cautious[ok], lowest[ok], diagonal[ok]) / diagonal[ok])
    return plain * np.outer(scale, scale)


def relative(spec) -> bool:
    """Whether a parameter's precision is a share of its value (a quantity bounded away from
    zero: alpha, ior, scale factors) rather than of its range (`precision_scale`)."""
    return spec.lower > 0


def precision_scale(spec, x: np.ndarray) -> np.ndarray:
    """What `GNOptions.precision` is a share of: the value itself for a quantity bounded away
    from zero (alpha, ior, scale factors: their errors are relative), else the range (colours,
    sigma, whose zero is a value like any other)."""
    if relative(spec):
        return np.abs(x)
    return np.full_like(x, spec.upper - spec.lower)


def pinned(problem, u: np.ndarray) -> np.ndarray:
    """Which solver coordinates of `u` (the material's, then the gains') hold a value at a bound
    of its range (`at_bounds`; never a gain, a texel or an unbounded value)."""
    n = problem.n_material
    x = np.asarray(to_physical(problem.free, np.asarray(u[:n], np.float32)), np.float64)
    at = {b["parameter"] for b in at_bounds(problem.free, as_dict(problem.free, x))}
    out = np.zeros(len(u), bool)
    i = 0
    for f in problem.free:
        if not f.shape:  # `at_bounds` labels: `key`, or `key[k]` for a colour's components
            labels = [f.key] if f.size == 1 else [f"{f.key}[{k}]" for k in range(f.size)]
            out[i : i + f.size] = [label in at for label in labels]
        i += f.size
    return out


def imprecise(problem, tail, gradients, jac1, jac2, precision: float) -> list[str]:
    """The free keys whose averaged answer's Monte Carlo standard deviation exceeds `precision`
    of their `precision_scale`, from the averaged steps' iterates and fresh-seed gradients
    (`tail`, `gradients`: rows) and the phase's two Jacobians in the solver's space
    (`averaging_covariance` with their cross curvature). Fewer than 3 steps: every key.

    A component whose average sits at a bound of its range (`at_bounds`) is left out: where the
    loss is flat there, as Oren-Nayar's sigma at 0 (it acts quadratically), the sd linearised at
    the average is large whatever the iterates do (the Cycles sphere's sigma at half resolution:
    0.023 for an average that stayed at 0.0002 from 6 to 9 steps), and the summary says where
    the value ended."""
    tail, gradients = np.asarray(tail, np.float64), np.asarray(gradients, np.float64)
    finite = np.all(np.isfinite(tail), axis=1) & np.all(np.isfinite(gradients), axis=1)
    tail, gradients = tail[finite], gradients[finite]
    if len(tail) < 3:
        return [f.key for f in problem.free]
    u = tail.mean(axis=0)
    h = cross_product(jac1, jac2)
    inverse, _ = inverse_determined(h)
    cov = averaging_covariance(tail, gradients, u, h, inverse)
    n = problem.n_material
    x = np.asarray(to_physical(problem.free, u[:n]), np.float64)
    slope = transform_jacobian(problem.free, u[:n])
    sd = np.sqrt(np.clip(np.diag(slope @ cov[:n, :n] @ slope.T), 0.0, None))
    noisy = (sd > precision * _scales(problem, x)) & ~pinned(problem, u)[:n]
    out, i = [], 0
    for f in problem.free:
        if np.any(noisy[i : i + f.size]):
            out.append(f.key)
        i += f.size
    return out


def _averaged(iterates: list, average: float, eta: float) -> int:
    """How many of a phase's last iterates its result averages: its last `average` of them,
    less the first ones while it still relaxed (`burn_in`) where that share is over a half."""
    taken = len(iterates)
    n = round(average * taken)
    if average > 0.5:
        n = min(n, taken - burn_in(iterates, eta))
    return n


#: `burn_in`'s false alarms: the chance that iterates only wandering around the optimum are
#: taken for a phase still relaxing toward it.
BURN_IN_ALARM = 0.01
#: `burn_in` needs this many iterates.
BURN_IN_MIN = 12


def burn_in(iterates: list, eta: float) -> int:
    """How many of a phase's first iterates (rows) were still relaxing toward its optimum: none
    unless some coordinate's mean over the second half differs from its mean over the first by
    more than noise would give (the two-sided `BURN_IN_ALARM` level of the largest of P
    differences, Sidak, of Student's t with the second half's spread), else the truncation of
    those coordinates' series that minimises their marginal standard error (MSER: White, 1997),
    at most half of them.

    At the optimum a `gn` phase's iterates are an AR(1) series, coefficient about 1 - eta, so a
    mean of m of them has the variance of m (1 - rho) / (1 + rho) independent ones (a cautious
    allowance: the torus's averaged phase measured -0.09 at rest). The averaged
    phase from a start 49 % over the torus's alpha 0.01 relaxed for about 16 of its 32 steps:
    its mean over all of them ended +15.5 %, over the last 16 +2.6 % (BENCHMARKS, "Recovery
    over the range")."""
    x = np.asarray(iterates, np.float64)
    moving = drifting(x, eta)
    if moving is None or not moving.size:
        return 0
    return max(_mser(x[:, j], len(x) // 2) for j in moving)


def drifting(iterates, eta: float) -> np.ndarray | None:
    """The coordinates (columns) of a phase's iterates (rows) whose mean over the second half
    differs from their mean over the first by more than noise would (`burn_in`'s test); None
    where there are too few (`BURN_IN_MIN`) or a rejected step's."""
    x = np.asarray(iterates, np.float64)
    taken = len(x)
    if taken < BURN_IN_MIN or x.ndim != 2 or not np.all(np.isfinite(x)):
        return None
    half = taken // 2
    first, second = x[:half], x[half:]
    # the noise from the second half alone: the first one's drift would swell it
    spread = second.std(axis=0, ddof=1)
    se = spread * np.sqrt(_ar1_inflation(eta) * (1.0 / half + 1.0 / (taken - half)))
    level = _level(BURN_IN_ALARM, x.shape[1], taken - half - 1)
    moved = np.abs(second.mean(axis=0) - first.mean(axis=0))
    return np.nonzero(moved > level * np.maximum(se, 1e-30))[0]


#: `trending`'s false alarms: the chance that iterates only wandering around the optimum are
#: taken for a phase still moving. Generous: a false alarm costs `refresh` more steps, a miss
#: hands on a mean short of the optimum.
TREND_ALARM = 0.2


def trending(iterates, eta: float, alarm: float = TREND_ALARM) -> np.ndarray | None:
    """The coordinates (columns) of a phase's iterates (rows) with a trend: the slope of their
    least-squares line over the steps beyond what noise would give (Student's t of the
    residuals' spread, each slope's variance inflated for an AR(1) of coefficient 1 - eta, at
    most 0.9; the two-sided `alarm` level for all coordinates together, Sidak); None where
    there are fewer than four rows or a rejected step's. A relaxation toward the optimum is a
    trend whatever its rate: a slow one's steady steps are its residuals' signal, not noise
    (a comparison of the halves, `drifting`, takes a steady drift's spread for noise)."""
    x = np.asarray(iterates, np.float64)
    n = len(x)
    if n < 4 or x.ndim != 2 or not np.all(np.isfinite(x)):
        return None
    t = np.arange(n, dtype=np.float64) - 0.5 * (n - 1)
    centred = x - x.mean(axis=0)
    slope = t @ centred / (t @ t)
    residual = centred - np.outer(t, slope)
    sigma = np.sqrt(np.sum(residual**2, axis=0) / (n - 2))
    se = sigma * np.sqrt(_ar1_inflation(eta) / (t @ t))
    level = _level(alarm, x.shape[1], n - 2)
    return np.nonzero(np.abs(slope) > level * np.maximum(se, 1e-30))[0]


def _ar1_inflation(eta: float) -> float:
    """How much a mean's (or a slope's) variance over a `gn` phase's iterates exceeds that of
    independent ones: an AR(1) of coefficient 1 - eta (at most 0.9), (1 + rho) / (1 - rho)."""
    rho = min(max(1.0 - eta, 0.0), 0.9)
    return (1.0 + rho) / (1.0 - rho)


def _level(alarm: float, columns: int, dof: int) -> float:
    """Student's t quantile (`dof` degrees of freedom) that the largest of `columns` two-sided
    statistics exceeds with chance `alarm` under noise alone (Sidak)."""
    sidak = 1.0 - 0.5 * (1.0 - (1.0 - alarm) ** (1.0 / columns))
    return float(stdtrit(dof, sidak))


def _mser(series: np.ndarray, most: int) -> int:
    """The truncation d <= `most` of a series that minimises its marginal standard error, the
    squared deviations of the rest from their mean over the square of their count."""
    best, arg = np.inf, 0
    for d in range(most + 1):
        rest = series[d:]
        value = float(np.sum((rest - rest.mean()) ** 2)) / len(rest) ** 2
        if value < best:
            best, arg = value, d
    return arg


def settled(iterates: list, tolerance: float = 1.0) -> bool:
    """Whether a phase's iterates over its last window (rows: the iterate before the window and
    after each of its steps) have settled: every coordinate's net move over the window is at
    most `tolerance` times what noise alone gives the largest of them, in units of their own
    spread. At the optimum the iterates wander around it (`gn`'s steps make them an AR(1)), so
    a coordinate's net move over a window is its noise, about sqrt(2) times its spread; as they
    relax the net move grows with the window while the noise does not (a steady drift's net
    move is sqrt(12) times its window's spread: sqrt(6) in these units). Noise alone gives the
    largest of P coordinates' |net / (sqrt(2) spread)| about `z_P` half the time (the median of
    the largest of P |N(0, 1)|), so a phase at its optimum passes each check about half the
    time whatever P. A rejected step (NaN) in the window, or fewer than three rows: not
    settled."""
    if len(iterates) < 3:
        return False
    x = np.asarray(iterates, np.float64)
    if not np.all(np.isfinite(x)):
        return False
    net = np.abs(x[-1] - x[0])
    spread = x.std(axis=0, ddof=1)
    z_p = float(ndtri(0.5 * (1.0 + 0.5 ** (1.0 / x.shape[1]))))
    return bool(np.all(net <= tolerance * z_p * np.sqrt(2.0) * spread))


def _gradients(
    problem, primal_spp: int, grad_spp: int, downscale: int, control: bool, shared: bool
):
    """A `gn` step's gradients, jitted: `(loss, J_B^T r)` and `(J_B^T m, r)` at `(u, seed)`
    (and `m`) from one render of `primal_spp` and its reverse pass of `grad_spp` (with
    `shared`, the control gradient's from one pass where it can: `_one_pass`)."""
    render = problem.render_fn("reverse", primal_spp, downscale, grad_spp=grad_spp)
    one_pass = shared and control and primal_spp == grad_spp and problem.loss == "l2"
    # the gains' derivative from an independent render: `J_B^T r` has the step's image in both
    # factors (biased low); the control gradient never multiplies the image by itself (`J` and
    # `m` come from other renders), so it saves that render
    residual = residuals(problem, render, downscale, independent_gains=not control)

    def loss(u, seed):
        r = residual(u, seed)
        return 0.5 * jnp.dot(r, r)

    def projected(u, seed, mean):
        r = residual(u, seed)
        return jnp.dot(jax.lax.stop_gradient(mean), r), r

    if one_pass:
        projected = _one_pass(problem, render, downscale)
    return jax.jit(jax.value_and_grad(loss)), jax.jit(jax.grad(projected, has_aux=True))


def _one_pass(problem, render, downscale: int):
    """The control gradient's `projected(u, seed, m)` (value `m . r`, its derivative through the
    image `J_B^T m`; the residual `r` beside) from one reverse pass whose primal pass is the
    step's image (the bridge's `render.paired`: `Renderer.render_vjp`), where a step rendered
    its image and then a reverse pass of its own paths (the image a third of a step's time).
    The two now share their paths, and the step's expected gradient stays the same: `J_B^T m`'s
    expectation is `J^T m` for any `m` that does not depend on this step's paths (`m` is the
    earlier steps' mean residual), and `J^T (r - m)` is linear in the image. (`J_B^T r`, the
    plain gradient, keeps them apart: its expectation with shared paths picks up the gradient
    of the image's variance: `GRAD_SEED_OFFSET`.) The residual is linear in the image (loss
    `l2`), so its cotangent on the image, `m` through the weights and gains, needs no image."""
    residual, n = image_residual(problem, downscale), problem.n_material
    paired = getattr(render, "paired", None)
    if paired is None:  # a plain JAX function of (x, seed): its own VJP

        def paired(x, seed, cotangent):
            image, vjp = jax.vjp(lambda x: render(x, seed), x)
            return image, vjp(cotangent)[0]

    def projected(u, seed, mean):
        x = to_physical(problem.free, u[:n], jnp)
        mean = jax.lax.stop_gradient(mean)
        size = problem.target(downscale)[0].size
        blank = jnp.zeros(size, jnp.float32)
        cotangent = jax.grad(lambda image: jnp.dot(mean, residual(u, image)))(blank)
        image, grad = paired(*jax.lax.stop_gradient((x, seed, cotangent)))
        r = residual(u, image)
        return jnp.dot(mean, r) + jnp.dot(grad, x.astype(grad.dtype)), r

    return projected


class GaussNewton(AbstractSolver):
    """Each step: the loss's gradient from a render with a fresh seed (its adjoint decorrelated,
    as Adam's; by default with the step image's noise taken through the curvature's Jacobian,
    `GNOptions.gradient`), times the inverse of a Gauss-Newton curvature `J^T J` rendered every
    `refresh` steps (two Jacobians of half `jacobian_spp` with yet other seeds, their noise
    discounted: `_curvature`), a fraction `eta` of that step.

    Under Monte Carlo noise Adam normalises each coordinate by its gradient noise: where the
    image barely depends on a parameter (a sharp highlight's width, alpha 0.02 on a 96 x 72
    sphere) its steps are noise, and at a rate that keeps them small it takes about a hundred
    steps to relax toward the optimum, far longer than a phase. The curvature scales every
    direction by how much the image depends on it, so the iterates relax in about 1/eta steps
    whatever the parameter, and the tail's average cancels the steps' noise. A noisy Jacobian
    only overestimates the curvature (shorter steps), never biases the fixed point, which is
    the zero of the expected gradient.

    Per-view gains are solver coordinates like the material's, stepped with it through the whole
    curvature (their derivative from an independent render, unbiased). Setting them in closed
    form between steps instead (Adam's profiling) leaves them one step behind the material, whose
    steps then meet the curvature that the gains were meant to absorb: where colours trade with
    the gains (the colours' common scale, pinned by one view of five on the cup: a Schur
    curvature about a fifth of the whole, so eta 0.5 steps about 2.5x too long) the steps flipped
    sign every step and were clipped to about a tenth (measured), stalling every parameter."""

    name = "gn"
    Options = GNOptions

    def run(
        self,
        problem,
        u0,
        *,
        steps,
        spp,
        seed,
        downscale,
        options,
        progress=None,
        resume=None,
        offer=None,
    ) -> Result:
        refuse_forward_mode(problem, "gn", "its curvature is a forward-mode Jacobian")
        u = np.asarray(u0 if resume is None else resume["u"], np.float32)
        note = ""
        # the phase's samples per pixel, raised with `spp_limit`, and what its message says of it
        level = spp if resume is None else int(resume.get("level", spp))
        raised = "" if resume is None else str(resume.get("raised", ""))
        # the step from which the phase renders at `level` (`relaxed` tests the steps since)
        since = 0 if resume is None else int(resume.get("since", 0))
        if resume is not None and "samples" in resume:
            primal_spp, grad_spp = (int(n) for n in resume["samples"])
        elif options.primal_spp == "auto":
            primal_spp, grad_spp, ratio = sample_split(problem, u, spp, seed, downscale)
            note = (
                f"samples: image {primal_spp}, reverse pass {grad_spp} (the render's noise "
                f"{ratio:.3g}x the rest of the residual)"
            )
        else:
            primal_spp, grad_spp = options.primal_spp or spp, spp
        control = options.gradient == "control"
        value_and_grad, projected_grad = _gradients(
            problem, primal_spp, grad_spp, downscale, control, options.shared_paths
        )
        mean = None if resume is None else resume.get("mean_residual")
        # every step's iterate after it and (iterate before, gradient): the result averages the
        # last `average` of the steps taken, `window` tests the last iterates
        history, iterates, pairs, rejected, first = [], [], [], 0, 0
        # the last step clipped to `max_step` that moved a value by more than `max_step_noise`
        # of its scale (-1: none)
        clipped = -1
        model = linear_model(problem, downscale)
        # (image, values, the means of the phase's two series of physical Jacobian renders)
        linear = None
        # per series, the mean over the refreshes of the linear image's constant part (image -
        # J x): with the mean Jacobians it is the mean of the refreshes' linear images, which
        # the uncertainty takes instead of rendering its own (`Result.linearisation`)
        constants = None
        if resume is not None:
            first = int(resume["step"])  # `u` is the saved one (above)
            history, rejected = list(resume["history"]), int(resume["rejected"])
            clipped = int(resume.get("clipped", -1))
            iterates = list(np.asarray(resume["tail"]))
            pairs = list(np.asarray(resume.get("tail_gradients", [])))
            if len(resume["leaves"]) == 4:  # the Jacobians in use when the state was offered
                linear = tuple(np.asarray(leaf, np.float32) for leaf in resume["leaves"])
                if "constants" in resume:
                    constants = np.asarray(resume["constants"], np.float32)
        settled_at, relaxed_at, noisy = None, None, []
        jac1 = jac2 = None  # the last step's Jacobians in the solver's coordinates
        limit = max(steps, options.max_steps or steps) if options.precision else steps

        def still_noisy() -> list[str]:
            """The free keys whose average is not yet within `precision` (`imprecise`)."""
            n = _averaged(iterates, options.average, options.eta)
            rows = np.asarray(pairs[len(pairs) - n :], np.float64).reshape(n, 2 * len(u))
            image, x, j1, j2 = linear
            jac = [np.asarray(model(u, image, j, x)[1], np.float64) for j in (j1, j2)]
            return imprecise(problem, rows[:, : len(u)], rows[:, len(u) :], *jac, options.precision)

        def finished(done: int) -> bool:
            """Whether the phase ends with `done` steps taken: settled (`window`), relaxed at a
            refresh (`relaxed`), or precise at a check (`precision`: after `steps`, then every
            `refresh`). Asked of the state before a step (after a raise of its samples), so
            that a resumed phase asks it of the state it saved."""
            nonlocal settled_at, relaxed_at, noisy
            window = options.window
            if window and len(iterates) > window and settled(iterates[-window - 1 :], tol):
                settled_at, noisy = done, []
                return True
            counted = done - since
            # before `relaxed_min`: from `relaxed_min_determined` where the curvature is signal
            early = counted < options.relaxed_min
            if (
                options.relaxed
                and done % options.refresh == 0
                and counted >= (options.relaxed_min_determined if early else options.relaxed_min)
                and (not early or determined(jac1, jac2))
            ):
                # quiet steps (noisy ones hide a trend; a step clipped to `max_step` that moved
                # a value is not a relaxation's) and what the phase hands on (its last half
                # since the raise) without one; early, none over all its steps since
                noise = step_noise(problem, iterates[-options.refresh - 1 :])
                quiet = bool(noise) and max(noise.values()) <= options.max_step_noise
                quiet = quiet and clipped < done - options.refresh
                tested = iterates[since if early else since + counted // 2 : done]
                moving = trending(tested, options.eta)
                if moving is not None:  # a value at its bound moves nothing where it wanders
                    centre = np.mean(np.asarray(tested, np.float64), axis=0)
                    moving = moving[~pinned(problem, centre)[moving]]
                if quiet and moving is not None and not moving.size:
                    relaxed_at = done
                    return True
            if options.precision and done >= steps and (done - steps) % options.refresh == 0:
                noisy = still_noisy()
                return not noisy
            return False

        tol = options.tolerance
        for i in range(first, limit):
            # a raise first: `relaxed` then tests only the steps at the new count (none yet)
            if options.spp_limit and level < options.spp_limit and i and i % options.refresh == 0:
                noise = step_noise(problem, iterates[-options.refresh - 1 :])
                worst = max(noise, key=noise.get, default=None)
                if worst is not None and noise[worst] > options.max_step_noise:
                    raised_to = min(SPP_RAISE * level, options.spp_limit)
                    primal_spp, grad_spp = (
                        min(max(1, round(n * raised_to / level)), MAX_SPP)
                        for n in (primal_spp, grad_spp)
                    )
                    level, since = raised_to, i
                    value_and_grad, projected_grad = _gradients(
                        problem, primal_spp, grad_spp, downscale, control, options.shared_paths
                    )
                    spec = next(f.spec for f in problem.free if f.key == worst)
                    raised = (
                        f"{level} spp from step {i + 1} ({worst}'s step noise "
                        f"{100 * noise[worst]:.0f} % of its "
                        f"{'value' if relative(spec) else 'range'})"
                    )
            if i > 0 and finished(i):
                break
            step_seed = seed * 100003 + i + 1
            if linear is None or i % options.refresh == 0:
                # Two Jacobians of half the samples each (independent seeds), each averaged
                # over the phase's refreshes so far (averaging k renders divides their noise's
                # excess curvature by k), in physical values: the transforms' derivatives change
                # along the way far more than the image's (alpha from 0.025 to 0.0135 next to
                # its bound 0.01: d alpha / d u 4x smaller), and a mean of solver-space
                # Jacobians kept the earlier, steeper ones (steps ~16x too short there).
                image, image2, x, j1, j2 = self._jacobians(
                    problem, u, options, step_seed, downscale
                )
                c = np.stack([image - j1 @ x, image2 - j2 @ x]).astype(np.float32)
                k = i // options.refresh + 1
                if linear is not None and k > 1:
                    j1 = linear[2] + (j1 - linear[2]) / k
                    j2 = linear[3] + (j2 - linear[3]) / k
                    constants = None if constants is None else constants + (c - constants) / k
                else:
                    constants = c
                linear = (image, x, j1, j2)
            image, x, j1, j2 = linear
            jac1, jac2 = (np.asarray(model(u, image, j, x)[1], np.float64) for j in (j1, j2))
            inverse = self._inverse(_curvature(jac1, jac2), options)
            if options.gradient == "control":
                if mean is None:
                    mean = np.zeros(problem.target(downscale)[0].size, np.float32)
                grad_mean, r = projected_grad(jnp.asarray(u), jax_seed(step_seed), mean)
                r = np.asarray(r, np.float64)
                d = r - mean
                grad = 0.5 * (jac1.T @ d + jac2.T @ d) + np.asarray(grad_mean, np.float64)
                value = 0.5 * float(r @ r)
                if np.all(np.isfinite(r)):
                    mean = (mean + (r - mean) / min(i + 1, CONTROL_WINDOW)).astype(np.float32)
            else:
                value, grad = value_and_grad(jnp.asarray(u), jax_seed(step_seed))
                value, grad = float(value), np.asarray(grad, np.float64)
            delta = -options.eta * (inverse @ grad)
            largest = max(float(np.max(np.abs(delta))), 1e-30)
            if largest > options.max_step:
                delta *= options.max_step / largest
            new_u = u + delta.astype(np.float32)
            if largest > options.max_step and options.relaxed and np.all(np.isfinite(new_u)):
                # a clipped step that moves a value by more than a quiet step's noise
                if largest_move(problem, u, new_u) > options.max_step_noise:
                    clipped = i
            pairs.append(np.concatenate([u, grad]).astype(np.float32))
            if np.all(np.isfinite(new_u)) and np.isfinite(value):
                u = new_u
            else:
                rejected += 1
            history.append(value)
            iterates.append(u.copy())
            if progress:
                progress(i + 1, value)
            if offer:
                offer(
                    {
                        "step": i + 1,
                        "u": u,
                        "leaves": list(linear),
                        **({} if constants is None else {"constants": constants}),
                        "history": history,
                        "n_history": len(history),
                        "tail": iterates,
                        "n_tail": len(iterates),
                        "n_averaged": _averaged(iterates, options.average, options.eta),
                        "tail_gradients": pairs,
                        "n_tail_gradients": len(pairs),
                        "rejected": rejected,
                        "clipped": clipped,
                        "samples": [primal_spp, grad_spp],
                        "level": level,
                        "raised": raised,
                        "since": since,
                        **({} if mean is None else {"mean_residual": mean}),
                    }
                )
        else:
            if options.precision and limit > steps:  # what was still noisy at the limit
                noisy = still_noisy()
        taken = len(iterates)
        n = _averaged(iterates, options.average, options.eta)
        tail = iterates[taken - n :] if n else []
        out = averaged_result(self.name, problem, u, tail, None, history, taken, rejected)
        report = out.reports[-1]
        ended = settled_at if settled_at is not None else relaxed_at
        if ended is not None and report.outcome != Outcome.DIVERGED:
            report.outcome = Outcome.CONVERGED
            how = "settled" if settled_at is not None else "relaxed"
            said = f"{how} after {ended} of {steps} steps"
            report.message = f"{said}; {report.message}" if report.message else said
        if n < round(options.average * taken):
            said = f"averaged its last {n} of {taken} steps (the first still relaxing)"
            note = f"{said}; {note}" if note else said
        if options.precision and (taken > steps or noisy):
            said = f"averaged {taken} steps for a Monte Carlo sd within {options.precision:.3g}"
            if noisy:
                said += f"; {', '.join(noisy)} still noisier at max_steps"
            note = f"{said}; {note}" if note else said
        if raised:
            note = f"{note}; {raised}" if note else raised
        if note:
            report.message = f"{report.message}; {note}" if report.message else note
        if constants is not None and taken:
            _, x, j1, j2 = linear
            refreshes = (taken - 1) // options.refresh + 1
            images = (constants[0] + j1 @ x, constants[1] + j2 @ x)
            out.linearisation = (*images, j1, j2, x, refreshes * max(options.jacobian_spp // 2, 1))
        finite = [p for p in pairs[taken - n :] if np.all(np.isfinite(p))] if n else []
        if finite:
            both = np.asarray(finite, np.float64)
            out.tail_gradients = (both[:, : len(u)], both[:, len(u) :])
        return out

    @staticmethod
    def _jacobians(problem, u, options, seed, downscale):
        """(the two renders' images, the values at `u`, their two Jacobians in physical
        values) from two renders of `jacobian_spp / 2` with their own seeds."""
        x = np.asarray(to_physical(problem.free, jnp.asarray(u[: problem.n_material]), jnp))
        renderer, half = problem.renderer(downscale), max(options.jacobian_spp // 2, 1)
        image, j1 = renderer.jacobian(x, seed + 0x5EED, half)
        image2, j2 = renderer.jacobian(x, seed + 0x5EED + CROSS_SEED_OFFSET, half)
        return image, image2, x, j1, j2

    @staticmethod
    def _inverse(h: np.ndarray, options) -> np.ndarray:
        """The damped inverse of a curvature (plus `marquardt` times its diagonal) through its
        eigenvalues, each at least `floor` of the largest; the identity if it is not finite."""
        if not np.all(np.isfinite(h)):
            return np.eye(len(h))
        h = 0.5 * (h + h.T)
        h = h + options.marquardt * np.diag(np.diag(h))
        values, vectors = np.linalg.eigh(h)
        floor = options.floor * max(float(values.max()), 1e-300)
        values = np.maximum(values, floor) * (1.0 + options.damping)
        return (vectors / values) @ vectors.T
