"""Solvers on the bridge: Levenberg-Marquardt (explicit Jacobian, one shared seed), Adam (optax
through `optimistix.OptaxMinimiser`, a fresh seed every step), the default schedule (Adam, a few LM
steps, a Polyak-averaged Adam polish), and Gauss-Newton uncertainty from the final Jacobian."""

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


@dataclass
class Problem:
    """What a fit compares: the capture's views against renders of `material` with `free`
    parameters, weighted by the validity weights (L2). With `gains`, every view but the first
    has a free RGB gain (photos rarely share an exact exposure or white balance; the first stays
    fixed to remove the albedo/gain ambiguity), solved as its logarithm and reported as
    `gain.<view>`."""

    capture: Capture
    material: dict
    free: list[Free]
    gains: bool = False
    _renderers: dict = field(default_factory=dict, repr=False, compare=False)

    def target(self) -> tuple[np.ndarray, np.ndarray]:
        image = np.concatenate([v.image.ravel() for v in self.capture.views])
        weight = np.concatenate([np.repeat(v.weight.ravel(), 3) for v in self.capture.views])
        return image.astype(np.float32), np.sqrt(weight / max(weight.sum() / 3, 1.0)).astype(
            np.float32
        )

    def renderer(self, spp: int) -> Renderer:
        """The loaded scenes at `spp` (built once: phases at the same spp share kernels)."""
        if spp not in self._renderers:
            self._renderers[spp] = Renderer(self.capture, self.material, self.free, spp)
        return self._renderers[spp]

    @property
    def n_material(self) -> int:
        return sum(f.size for f in self.free)

    @property
    def gain_views(self) -> list:
        return self.capture.views[1:] if self.gains else []

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
            out[f"gain.{view.name}"] = np.exp(u[start : start + 3]).tolist()
        return out

    def gain_multipliers(self, log_gains):
        """Per-element multipliers of the flattened views (the first view's are 1)."""
        parts = [jnp.ones(self.capture.views[0].image.size, jnp.float32)]
        for i, view in enumerate(self.gain_views):
            gain = jnp.exp(log_gains[3 * i : 3 * i + 3]).astype(jnp.float32)
            parts.append(jnp.tile(gain, view.image.size // 3))
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


def _residuals(problem: Problem, renderer: Renderer, mode: str):
    render = make_render(renderer, mode)
    target, sqrt_w = (jnp.asarray(a) for a in problem.target())
    n = problem.n_material

    def residual(u, seed):
        image = render(to_physical(problem.free, u[:n], jnp), seed)
        if problem.gains:
            image = image * problem.gain_multipliers(u[n:])
        return sqrt_w * (image - target)

    return residual


def levenberg_marquardt(
    problem: Problem,
    u0,
    spp: int = 32,
    seed: int = 0,
    max_steps: int = 30,
    rtol: float = 1e-4,
    atol: float = 1e-6,
) -> Result:
    """LM on the explicit Jacobian with one shared seed (common random numbers)."""
    residual = _residuals(problem, problem.renderer(spp), "jacobian")
    solution = optx.least_squares(
        residual,
        optx.LevenbergMarquardt(rtol=rtol, atol=atol),
        jnp.asarray(u0, jnp.float32),
        args=jnp.int32(seed),
        max_steps=max_steps,
        throw=False,
    )
    u = np.asarray(solution.value)
    r = np.asarray(residual(jnp.asarray(u), jnp.int32(seed)))
    return Result(problem.values(u), u, float(0.5 * r @ r), int(solution.stats["num_steps"]))


def adam(
    problem: Problem,
    u0,
    steps: int = 100,
    spp: int = 8,
    lr: float = 0.05,
    seed: int = 0,
    progress: Callable[[int, float], None] | None = None,
    average_last: int = 0,
) -> Result:
    """Adam with a fresh seed every step (a fixed seed converges to its own biased optimum);
    steps whose loss or gradient is not finite are rejected, never applied. With `average_last`
    the result is the mean of the last iterates (Polyak averaging: it cancels the steps' Monte
    Carlo noise)."""
    residual = _residuals(problem, problem.renderer(spp), "reverse")

    def loss(u, seed):
        r = residual(u, seed)
        return 0.5 * jnp.dot(r, r), None

    solver = optx.OptaxMinimiser(optax.adam(lr), rtol=0.0, atol=0.0)
    u = jnp.asarray(u0, jnp.float32)
    f_struct = jax.ShapeDtypeStruct((), jnp.float32)
    state = solver.init(loss, u, jnp.int32(seed), {}, f_struct, None, frozenset())
    step = jax.jit(lambda u, s, st: solver.step(loss, u, s, {}, st, frozenset())[:2])
    history, tail = [], []
    for i in range(steps):
        new_u, new_state = step(u, jnp.int32(seed * 100003 + i + 1), state)
        value = float(new_state.f)  # the loss at `u`, before this update
        if np.all(np.isfinite(np.asarray(new_u))) and np.isfinite(value):
            u, state = new_u, new_state
        history.append(value)
        if i >= steps - average_last:
            tail.append(np.asarray(u))
        if progress:
            progress(i + 1, value)
    if tail:
        u = jnp.asarray(np.mean(tail, axis=0))
    u = np.asarray(u)
    return Result(problem.values(u), u, history[-1] if history else float("nan"), steps, history)


def uncertainty(
    problem: Problem, u, spp: int = 64, seed: int = 0, threshold: float = 0.1
) -> tuple[dict, np.ndarray, list[str]]:
    """Gauss-Newton covariance `s^2 (J^T W J)^-1` at the solver's vector `u`, mapped to physical
    units through the transforms' derivatives (s^2 = weighted residual sum of squares / (N - P)).
    Returns per-parameter standard deviations, the correlation matrix, and the parameters whose
    standard deviation exceeds `threshold` of their range (of their value, for gains) or that are
    not determined at all."""
    residual = _residuals(problem, problem.renderer(spp), "jacobian")
    u = jnp.asarray(u, jnp.float32)
    r = np.asarray(residual(u, jnp.int32(seed)), np.float64)
    jac = np.asarray(jax.jacfwd(residual)(u, jnp.int32(seed)), np.float64)
    n = problem.n_material
    dxdu = np.concatenate(
        [
            np.diag(np.asarray(jax.jacfwd(lambda v: to_physical(problem.free, v, jnp))(u[:n]))),
            np.exp(np.asarray(u[n:], np.float64)),
        ]
    )
    dof = max(int(np.count_nonzero(np.any(jac != 0, axis=1))) - jac.shape[1], 1)
    cov = float(r @ r) / dof * np.linalg.pinv(jac.T @ jac)
    cov = cov * np.outer(dxdu, dxdu)
    std_flat = np.sqrt(np.clip(np.diag(cov), 0, None))
    corr = cov / np.maximum(np.outer(std_flat, std_flat), 1e-30)
    values = problem.values(np.asarray(u))
    std, flagged, i = {}, [], 0
    scales = [f.spec.upper - f.spec.lower for f in problem.free]
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


def default_schedule(
    problem: Problem,
    start: dict,
    seed: int = 0,
    adam_steps: int = 100,
    adam_lr: float = 0.1,
    adam_spp: int = 8,
    lm_spp: int = 64,
    lm_steps: int = 6,
    progress: Callable[[int, float], None] | None = None,
    polish_steps: int = 50,
    polish_spp: int = 32,
    polish_lr: float = 0.01,
) -> Result:
    """Three phases, then the uncertainty at the result:

    1. Adam with fresh seeds at low spp: robust from far away (scale-free steps also move a
       parameter started next to a bound, where its sigmoid is flat);
    2. a few LM steps with one seed at higher spp: jumps to that seed's optimum;
    3. Adam with fresh seeds, a small rate and Polyak averaging of the last 60 % of the iterates:
       removes the fixed seed's bias (measured on the Cycles sphere: alpha +4-7 % after LM alone).
    """
    u0 = problem.unconstrained(start)
    first = adam(problem, u0, adam_steps, adam_spp, adam_lr, seed=seed, progress=progress)
    middle = levenberg_marquardt(problem, first.u, lm_spp, seed + 1, lm_steps)
    result = adam(
        problem,
        middle.u,
        polish_steps,
        polish_spp,
        polish_lr,
        seed=seed + 2,
        average_last=int(0.6 * polish_steps),
    )
    result.steps = first.steps + middle.steps + result.steps
    result.history = [*first.history, middle.loss, *result.history]
    result.std, result.correlation, result.poorly_determined = uncertainty(
        problem, result.u, lm_spp, seed + 3
    )
    return result
