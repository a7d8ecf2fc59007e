"""Solvers on the bridge: Levenberg-Marquardt (explicit Jacobian), BFGS (reverse mode, one shared
seed), Adam (optax through `optimistix.OptaxMinimiser`, a fresh seed every step), schedules of
phases (solver, steps, spp, resolution), and Gauss-Newton uncertainty from the final Jacobian."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import jax
import jax.numpy as jnp
import numpy as np
import optax
import optimistix as optx

from captures.capture import Capture

from .bridge import make_render
from .free import Free, as_dict, to_physical, to_unconstrained
from .renderer import Renderer
from .schedule import DEFAULT_SCHEDULE, LOSSES, Phase


@dataclass
class Problem:
    """What a fit compares: the capture's views against renders of `material` with `free`
    parameters, weighted by the validity weights.

    With `gains`, every view but the first has a free RGB gain (photos rarely share an exact
    exposure or white balance; the first stays fixed to remove the albedo/gain ambiguity), solved
    as its logarithm and reported as `gain.<view>`.

    `loss` shapes each pixel's difference d = render - photo before weighting: "l2" (d itself, the
    default: unbiased under Monte Carlo noise), or robust ones that count differences beyond
    `loss_scale` (default: a tenth of the photos' mean valid value) less, "huber" (linear tails)
    and "cauchy" (logarithmic). Robust losses tame outliers (specks, unmodelled reflections) but
    are biased under noise: they shrink the noisy render's large deviations asymmetrically."""

    capture: Capture
    material: dict
    free: list[Free]
    gains: bool = False
    loss: str = "l2"
    loss_scale: float | None = None
    _cache: dict = field(default_factory=dict, repr=False, compare=False)

    def __post_init__(self):
        if self.loss not in LOSSES:
            raise ValueError(f"loss {self.loss!r}; choose one of {', '.join(LOSSES)}")

    def at(self, downscale: int) -> Capture:
        """The capture area-averaged by `downscale` (built once)."""
        key = ("capture", downscale)
        if key not in self._cache:
            self._cache[key] = self.capture.downscaled(downscale)
        return self._cache[key]

    def target(self, downscale: int = 1) -> tuple[np.ndarray, np.ndarray]:
        """(photos, sqrt of the normalised weights), flattened like the renders."""
        views = self.at(downscale).views
        image = np.concatenate([v.image.ravel() for v in views])
        weight = np.concatenate([np.repeat(v.weight.ravel(), 3) for v in views])
        return image.astype(np.float32), np.sqrt(weight / max(weight.sum() / 3, 1.0)).astype(
            np.float32
        )

    def renderer(self, downscale: int = 1) -> Renderer:
        """The loaded scenes at a resolution (built once: phases at the same resolution share
        kernels, whatever their spp)."""
        key = ("renderer", downscale)
        if key not in self._cache:
            self._cache[key] = Renderer(self.at(downscale), self.material, self.free)
        return self._cache[key]

    def robust_scale(self) -> float:
        """The width of a robust loss, in linear image units."""
        if self.loss_scale is not None:
            return self.loss_scale
        image, sqrt_w = self.target()
        return 0.1 * float(np.sum(image * sqrt_w**2) / max(np.sum(sqrt_w**2), 1e-12))

    @property
    def n_material(self) -> int:
        return sum(f.size for f in self.free)

    @property
    def gain_views(self) -> list[int]:
        return list(range(1, len(self.capture.views))) if self.gains else []

    def unconstrained(self, start: dict):
        """The solver's starting vector: material parameters, then log-gains (0: gain 1)."""
        return np.concatenate(
            [to_unconstrained(self.free, start), np.zeros(3 * len(self.gain_views))]
        ).astype(np.float32)

    def values(self, u) -> dict:
        u = np.asarray(u, dtype=np.float64)
        out = as_dict(self.free, to_physical(self.free, u[: self.n_material]))
        for i, view in enumerate(self.gain_views):
            start = self.n_material + 3 * i
            out[f"gain.{self.capture.views[view].name}"] = np.exp(u[start : start + 3]).tolist()
        return out

    def gain_multipliers(self, log_gains, downscale: int = 1):
        """Per-element multipliers of the flattened views (the first view's are 1)."""
        views = self.at(downscale).views
        parts = [jnp.ones(views[0].image.size, jnp.float32)]
        for i, view in enumerate(self.gain_views):
            gain = jnp.exp(log_gains[3 * i : 3 * i + 3]).astype(jnp.float32)
            parts.append(jnp.tile(gain, views[view].image.size // 3))
        return jnp.concatenate(parts)


@dataclass
class Result:
    values: dict
    u: np.ndarray
    loss: float
    steps: int
    history: list[float] = field(default_factory=list)
    std: dict | None = None
    correlation: np.ndarray | None = None
    poorly_determined: list[str] = field(default_factory=list)
    phase_ends: list[int] = field(default_factory=list)  # len(history) after each phase


def _shape(d, loss: str, scale: float):
    """The loss as a residual transform psi(d) with psi^2 / 2 = rho(d): smooth, psi(d) ~ d near 0
    (so least-squares solvers take robust losses too)."""
    if loss == "l2":
        return d
    x = d / scale
    x2 = x * x
    if loss == "huber":  # rho = x^2/2 inside, |x| - 1/2 outside
        safe = jnp.maximum(jnp.abs(x), 1.0)
        return jnp.where(jnp.abs(x) <= 1.0, d, jnp.sign(d) * scale * jnp.sqrt(2 * safe - 1))
    # cauchy: rho = log(1 + x^2) / 2; psi = x sqrt(log1p(x^2) / x^2), the ratio -> 1 at 0
    ratio = jnp.where(x2 > 1e-6, jnp.log1p(x2) / jnp.maximum(x2, 1e-6), 1.0 - x2 / 2)
    return d * jnp.sqrt(ratio)


#: With `independent_gains`, the gains' derivatives use a second render with the seed plus this
#: offset (far from `GRAD_SEED_OFFSET` and from a schedule's consecutive seeds).
GAIN_SEED_OFFSET = 0xB10C5


def _residuals(problem: Problem, render, downscale: int = 1, independent_gains: bool = False):
    """`residual(u, seed)`: the weighted, loss-shaped differences of `render(x, seed)` (a JAX
    function of the physical values) from the photos.

    A gain g's derivative of the loss is sum(w (g I - T) I) over its view and channel: with the
    same noisy image I in both factors its zero sits at g = T E[I] / E[I^2], biased low by the
    render's relative variance (measured -33 % at 8 spp on the glazed sphere's highlights). With
    `independent_gains` the derivative's second factor is an independent render I' (same value of
    the residual, derivative sum(w (g I - T) I'), zero at the unbiased T / E[I]); it costs one
    more primal render per evaluation, for solvers whose fixed point is a zero of an expected
    gradient (Adam with fresh seeds, LM with a decorrelated Jacobian)."""
    target, sqrt_w = (jnp.asarray(a) for a in problem.target(downscale))
    n, loss, scale = problem.n_material, problem.loss, problem.robust_scale()
    independent = independent_gains and problem.gains

    def residual(u, seed):
        x = to_physical(problem.free, u[:n], jnp)
        image = render(x, seed)
        if problem.gains:
            gain = problem.gain_multipliers(u[n:], downscale)
            if independent:
                other = jax.lax.stop_gradient(
                    render(jax.lax.stop_gradient(x), seed + GAIN_SEED_OFFSET)
                )
                fixed = jax.lax.stop_gradient(gain)
                image = fixed * image + (gain - fixed) * other  # value: gain * image
            else:
                image = image * gain
        return sqrt_w * _shape(image - target, loss, scale)

    return residual


def _finite_or(u, fallback) -> np.ndarray:
    """A solver's answer, or `fallback` when it is not finite (never apply a non-finite step)."""
    u = np.asarray(u)
    return u if np.all(np.isfinite(u)) else np.asarray(fallback)


def levenberg_marquardt(
    problem: Problem,
    u0,
    spp: int = 32,
    seed: int = 0,
    max_steps: int = 30,
    downscale: int = 1,
    jacobian_spp: int | None = None,
    rtol: float = 1e-4,
    atol: float = 1e-6,
) -> Result:
    """LM (optimistix) on the explicit Jacobian with one seed. By default the Jacobian is this
    seed's exact one (common random numbers: converges fast to the seed's own optimum, biased at
    low spp); with `jacobian_spp` it is rendered decorrelated at that spp (see
    `Renderer.jacobian`): the fixed point is unbiased and a cheap Jacobian serves an accurate,
    high-spp residual."""
    render = make_render(problem.renderer(downscale), "jacobian", spp, jacobian_spp)
    residual = _residuals(problem, render, downscale, independent_gains=jacobian_spp is not None)
    solution = optx.least_squares(
        residual,
        optx.LevenbergMarquardt(rtol=rtol, atol=atol),
        jnp.asarray(u0, jnp.float32),
        args=jnp.int32(seed),
        max_steps=max_steps,
        throw=False,
    )
    u = _finite_or(solution.value, u0)
    r = np.asarray(residual(jnp.asarray(u), jnp.int32(seed)))
    return Result(problem.values(u), u, float(0.5 * r @ r), int(solution.stats["num_steps"]))


def bfgs(
    problem: Problem,
    u0,
    spp: int = 32,
    seed: int = 0,
    max_steps: int = 50,
    downscale: int = 1,
    rtol: float = 1e-5,
    atol: float = 1e-7,
) -> Result:
    """BFGS (optimistix) on reverse-mode gradients with one shared seed (its line search needs a
    fixed objective; fresh seeds stall it). Converges to that seed's optimum, like LM."""
    render = make_render(problem.renderer(downscale), "reverse", spp)
    residual = _residuals(problem, render, downscale)

    def loss(u, seed):
        r = residual(u, seed)
        return 0.5 * jnp.dot(r, r)

    solution = optx.minimise(
        loss,
        optx.BFGS(rtol=rtol, atol=atol),
        jnp.asarray(u0, jnp.float32),
        args=jnp.int32(seed),
        max_steps=max_steps,
        throw=False,
    )
    u = _finite_or(solution.value, u0)
    value = float(loss(jnp.asarray(u), jnp.int32(seed)))
    return Result(problem.values(u), u, value, int(solution.stats["num_steps"]))


def adam(
    problem: Problem,
    u0,
    steps: int = 100,
    spp: int = 8,
    lr: float = 0.05,
    seed: int = 0,
    progress: Callable[[int, float], None] | None = None,
    average: float = 0.0,
    downscale: int = 1,
) -> Result:
    """Adam (optax through `optimistix.OptaxMinimiser`) with a fresh seed every step (a fixed seed
    converges to its own biased optimum); steps whose loss or gradient is not finite are rejected,
    never applied. With `average` > 0 the result is the mean of that fraction of the last iterates
    (Polyak averaging: it cancels the steps' Monte Carlo noise)."""
    render = make_render(problem.renderer(downscale), "reverse", spp)
    residual = _residuals(problem, render, downscale, independent_gains=True)

    def loss(u, seed):
        r = residual(u, seed)
        return 0.5 * jnp.dot(r, r), None

    solver = optx.OptaxMinimiser(optax.adam(lr), rtol=0.0, atol=0.0)
    u = jnp.asarray(u0, jnp.float32)
    f_struct = jax.ShapeDtypeStruct((), jnp.float32)
    state = solver.init(loss, u, jnp.int32(seed), {}, f_struct, None, frozenset())
    step = jax.jit(lambda u, s, st: solver.step(loss, u, s, {}, st, frozenset())[:2])
    history, tail = [], []
    first_averaged = steps - round(average * steps)
    for i in range(steps):
        new_u, new_state = step(u, jnp.int32(seed * 100003 + i + 1), state)
        value = float(new_state.f)  # the loss at `u`, before this update
        if np.all(np.isfinite(np.asarray(new_u))) and np.isfinite(value):
            u, state = new_u, new_state
        history.append(value)
        if i >= first_averaged:
            tail.append(np.asarray(u))
        if progress:
            progress(i + 1, value)
    if tail:
        u = jnp.asarray(np.mean(tail, axis=0))
    u = np.asarray(u)
    return Result(problem.values(u), u, history[-1] if history else float("nan"), steps, history)


def uncertainty(
    problem: Problem,
    u,
    spp: int = 64,
    seed: int = 0,
    threshold: float = 0.1,
    downscale: int = 1,
) -> tuple[dict, np.ndarray, list[str]]:
    """Gauss-Newton covariance at the solver's vector `u` in its sandwich form,
    `(J^T J)^-1 J^T diag(r^2) J (J^T J)^-1 * N / (N - P)` (J, r: the weighted Jacobian and
    residuals of one `spp` render), mapped to physical units through the transforms' derivatives.

    The plain form `s^2 (J^T J)^-1` assumes every pixel equally noisy; Monte Carlo noise gathers
    in highlights, where roughness and ior are decided. Measured on the synthetic 3-view sphere of
    the default job: plain std alpha 0.00008 / ior 0.0005 against actual errors 0.0014 / 0.0053;
    the sandwich gives 0.0015 / 0.0054 (at 64 spp; its render noise makes it conservative).

    Returns per-parameter standard deviations, the correlation matrix, and the parameters whose
    standard deviation exceeds `threshold` of their range (of their value, for gains and emitter
    scales) or that are not determined at all."""
    n = problem.n_material
    u = jnp.asarray(u, jnp.float32)
    x0 = to_physical(problem.free, u[:n], jnp)
    image0, jac_x = problem.renderer(downscale).jacobian(np.asarray(x0), seed, spp)
    # one Jacobian render; the residual's own Jacobian (gains, loss, weights) follows in JAX
    # through the render's linearisation at `u`
    residual = _residuals(problem, lambda x, _: image0 + jac_x @ (x - x0), downscale)
    r = np.asarray(residual(u, 0), np.float64)
    jac = np.asarray(jax.jacfwd(residual)(u, 0), np.float64)
    dxdu = np.concatenate(
        [
            np.diag(np.asarray(jax.jacfwd(lambda v: to_physical(problem.free, v, jnp))(u[:n]))),
            np.exp(np.asarray(u[n:], np.float64)),
        ]
    )
    n_obs = int(np.count_nonzero(np.any(jac != 0, axis=1)))
    bread = np.linalg.pinv(jac.T @ jac)
    meat = jac.T @ (jac * (r**2)[:, None])
    cov = n_obs / max(n_obs - jac.shape[1], 1) * bread @ meat @ bread
    cov = cov * np.outer(dxdu, dxdu)
    std_flat = np.sqrt(np.clip(np.diag(cov), 0, None))
    corr = cov / np.maximum(np.outer(std_flat, std_flat), 1e-30)
    values = problem.values(np.asarray(u))
    std, flagged, i = {}, [], 0
    # flagged against the range, or the value itself for scale factors (log-space bounds)
    scales = [
        None if f.spec.transform == "log_sigmoid" else f.spec.upper - f.spec.lower
        for f in problem.free
    ]
    sizes = [f.size for f in problem.free] + [3] * len(problem.gain_views)
    for key, size, scale in zip(
        values, sizes, scales + [None] * len(problem.gain_views), strict=True
    ):
        s = std_flat[i : i + size]
        std[key] = s.tolist() if size > 1 else float(s[0])
        reference = scale if scale is not None else np.asarray(values[key])
        if np.any(s > threshold * reference) or np.any(s == 0):
            flagged.append(key)
        i += size
    return std, corr, flagged


#: The uncertainty renders one forward-mode image per parameter component: skipped above this
#: many (textures), where the Jacobian would cost more than the fit.
MAX_UNCERTAINTY_PARAMS = 64


def run_schedule(
    problem: Problem,
    start: dict,
    phases: tuple[Phase, ...] | list[Phase] = DEFAULT_SCHEDULE,
    seed: int = 0,
    progress: Callable[[int, int, float], None] | None = None,
    uncertainty_spp: int = 64,
) -> Result:
    """Run `phases` in turn from `start` (phase k uses seed + k), then the uncertainty at the
    result (up to `MAX_UNCERTAINTY_PARAMS` components). `progress(phase, step, loss)` after
    every Adam step and at the end of each phase."""
    u = problem.unconstrained(start)
    history, steps, result, ends = [], 0, None, []
    for k, phase in enumerate(phases):
        report = (lambda i, value, k=k: progress(k, i, value)) if progress else None
        common = {"spp": phase.spp, "seed": seed + k, "downscale": phase.downscale}
        if phase.solver == "adam":
            result = adam(
                problem,
                u,
                phase.steps,
                lr=phase.lr,
                average=phase.average,
                progress=report,
                **common,
            )
            history += result.history
        elif phase.solver == "lm":
            result = levenberg_marquardt(
                problem, u, max_steps=phase.steps, jacobian_spp=phase.jacobian_spp, **common
            )
            history.append(result.loss)
        else:
            result = bfgs(problem, u, max_steps=phase.steps, **common)
            history.append(result.loss)
        if progress:
            progress(k, phase.steps, result.loss)
        u, steps = result.u, steps + result.steps
        ends.append(len(history))
    if result is None:
        result = Result(problem.values(u), u, float("nan"), 0)
    result.steps, result.history, result.phase_ends = steps, history, ends
    if len(u) <= MAX_UNCERTAINTY_PARAMS:
        result.std, result.correlation, result.poorly_determined = uncertainty(
            problem, u, uncertainty_spp, seed + len(phases)
        )
    return result
