"""What every solver shares: its options model, what it returns, and how a phase ended."""

from __future__ import annotations

import abc
import enum
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np
from pydantic import BaseModel, ConfigDict

from .problem import Problem


class Outcome(enum.StrEnum):
    """How a phase ended."""

    CONVERGED = "converged"  # the solver's own tolerance was met
    STEP_LIMIT = "step_limit"  # its step count ran out (Adam always runs its steps)
    DIVERGED = "diverged"  # its answer was not finite: the phase's start is kept, and said so
    FAILED = "failed"  # the solver stopped on an error of its own (message says which)


@dataclass
class PhaseReport:
    """One phase's outcome: solver, outcome, steps taken, steps rejected (Adam: non-finite ones;
    LM and BFGS: all of them when the answer is still the start), the solver's message, final
    loss and wall time."""

    solver: str
    outcome: Outcome
    steps: int
    rejected: int = 0
    message: str = ""
    loss: float = float("nan")
    seconds: float = 0.0

    def as_dict(self) -> dict:
        return {**self.__dict__, "outcome": str(self.outcome)}

    @classmethod
    def from_dict(cls, saved: dict) -> PhaseReport:
        """The report `as_dict` wrote (a checkpoint's; fields a later layerfit added dropped)."""
        known = {k: v for k, v in saved.items() if k in cls.__dataclass_fields__}
        return cls(**{**known, "outcome": Outcome(saved["outcome"])})


@dataclass
class Result:
    """A solver's (or a schedule's) answer: physical values by key, the unconstrained vector,
    the final loss, steps, the loss history, and per phase its report."""

    values: dict
    u: np.ndarray
    loss: float
    steps: int
    history: list[float] = field(default_factory=list)
    reports: list[PhaseReport] = field(default_factory=list)
    std: dict | None = None
    correlation: np.ndarray | None = None
    poorly_determined: list[str] = field(default_factory=list)
    phase_ends: list[int] = field(default_factory=list)  # len(history) after each phase
    #: Per solver coordinate, the variance of the averaged answer from the steps' own Monte Carlo
    #: noise (solvers that average a tail of iterates; None otherwise): see `tail_variance`.
    tail_variance: np.ndarray | None = None
    #: The averaged tail's steps as (iterates before each step, the step's gradient), rows per
    #: step (solvers whose steps follow the loss's own fresh-seed gradient: `gn`); from them the
    #: uncertainty estimates the averaged answer's Monte Carlo error (see `uncertainty`).
    tail_gradients: tuple[np.ndarray, np.ndarray] | None = None
    #: A `gn` phase's mean linear images and Jacobians (`(image1, image2, jac1, jac2, x, spp)`:
    #: two independent series, each the mean of its refreshes' `spp` samples, linear in the
    #: physical values `x`), the uncertainty's Jacobian renders when they hold as many samples.
    linearisation: tuple | None = None
    #: Free textures (`fit.solvers.textures`): each texel's sd (the texture's shape; a colour's
    #: after its smoothing, a mask's its own term), a colour's prior weight chosen, and the
    #: share of each texture's texels the photos see.
    texture_std: dict | None = None
    texture_weight: dict | None = None
    texture_seen: dict | None = None


def tail_variance(tail: list) -> np.ndarray | None:
    """The variance of the mean of a tail of iterates (rows) from their own scatter, corrected
    for their correlation from step to step (each coordinate an AR(1): variance / n times
    (1 + rho) / (1 - rho), rho the lag-1 autocorrelation clipped to [0, 0.95]). None for fewer
    than 4 iterates. What the averaged answer would move by with other seeds: the reported
    uncertainty adds it to the data's (errors on the test spheres were up to 3x the data's
    sigma alone)."""
    if len(tail) < 4:
        return None
    x = np.asarray(tail, np.float64)
    d = x - x.mean(axis=0)
    var = (d**2).mean(axis=0)
    rho = np.where(var > 0, (d[1:] * d[:-1]).mean(axis=0) / np.where(var > 0, var, 1), 0.0)
    rho = np.clip(rho, 0.0, 0.95)
    return var / len(x) * (1 + rho) / (1 - rho)


class Options(BaseModel):
    """A solver's own settings in a `[[fit.phases]]` table (each field documented). Strict, as
    the rest of a config: `spp = "4"`, `steps = 3.0` or `profile_gains = "yes"` are refused (they
    ran; `steps = true` ran one step)."""

    model_config = ConfigDict(
        extra="forbid", frozen=True, strict=True, use_attribute_docstrings=True
    )


#: `progress(step, loss)` after a solver's step.
Progress = Callable[[int, float], None]


class AbstractSolver(abc.ABC):
    """A solver of a fit phase. Subclasses set `name`, their `Options` and implement `run`;
    registering one is one line in `fit/solvers/registry.py`."""

    name: ClassVar[str]
    Options: ClassVar[type[Options]] = Options

    @abc.abstractmethod
    def run(
        self,
        problem: Problem,
        u0: np.ndarray,
        *,
        steps: int,
        spp: int,
        seed: int,
        downscale: int,
        options: Options,
        progress: Progress | None = None,
        resume: dict | None = None,
        offer: Callable[[dict], None] | None = None,
    ) -> Result:
        """Minimise `problem`'s loss from the unconstrained vector `u0`; the result's
        `reports` holds this phase's report (outcome, steps, rejected steps).

        Solvers that can stop mid-phase `offer` their state (arrays and JSON-able values; the
        optimiser's state as `leaves`) after each step, and continue from such a state given as
        `resume`; others restart the phase."""


def solve_optimistix(
    name: str, problem: Problem, solve, u0, seed: int, steps: int, loss_at, progress
) -> Result:
    """An optimistix solve from `u0` on one seed's renders, at most `steps` steps: `solve(y0,
    args, max_steps, throw)` is `optx.minimise` or `optx.least_squares` with its function and
    solver given, run with `throw=False` and reported by `optimistix_result`. `loss_at(u, seed)`
    is the loss at an answer."""
    import jax.numpy as jnp

    from .problem import jax_seed

    args = jax_seed(seed)
    solution = solve(jnp.asarray(u0, jnp.float32), args=args, max_steps=steps, throw=False)

    def loss(u):
        return loss_at(jnp.asarray(u), args)

    return optimistix_result(name, problem, solution, u0, loss, progress)


def optimistix_result(name: str, problem: Problem, solution, u0, loss_at, progress) -> Result:
    """The `Result` of an optimistix solve run with `throw=False`, its outcome inspected; a
    non-finite answer is never applied (the phase's start is kept, and the outcome says so).
    `loss_at(u)` is the loss at the answer."""
    u = np.asarray(solution.value)
    loss = float(loss_at(u)) if np.all(np.isfinite(u)) else math.nan
    finite = math.isfinite(loss)
    if not finite:
        u = np.asarray(u0)
        loss = float(loss_at(u))
    outcome, message = _optimistix_outcome(solution, finite)
    taken = int(solution.stats["num_steps"])
    # optimistix does not count rejected steps; an answer equal to the start means every step
    # was (LM and BFGS keep the start until a step decreases the loss)
    rejected = taken if taken and finite and np.array_equal(u, np.asarray(u0)) else 0
    if rejected:
        message = f"every one of the {taken} steps was rejected; kept the start. {message}".strip()
    if progress:
        progress(taken, loss)
    report = PhaseReport(name, outcome, taken, rejected, message=message, loss=loss)
    return Result(problem.values(u), u, loss, taken, [loss], [report])


def _optimistix_outcome(solution, finite: bool) -> tuple[Outcome, str]:
    """An optimistix solution's outcome and message (`throw=False` results, inspected)."""
    import optimistix as optx

    if not finite:
        return Outcome.DIVERGED, "the loss at the solver's answer was not finite; kept the start"
    if bool(solution.result == optx.RESULTS.successful):
        return Outcome.CONVERGED, ""
    message = str(optx.RESULTS[solution.result])
    steps_out = solution.result == optx.RESULTS.max_steps_reached
    if bool(steps_out) or bool(solution.result == optx.RESULTS.nonlinear_max_steps_reached):
        return Outcome.STEP_LIMIT, message
    diverged = (optx.RESULTS.nonlinear_divergence, optx.RESULTS.nonfinite)
    if any(bool(solution.result == r) for r in (*diverged, optx.RESULTS.nonfinite_input)):
        return Outcome.DIVERGED, message
    return Outcome.FAILED, message
