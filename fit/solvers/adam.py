"""Adam (optax through `optimistix.OptaxMinimiser`) with a fresh seed every step."""

from __future__ import annotations

import functools
from typing import Annotated

import jax
import jax.numpy as jnp
import numpy as np
import optax
import optimistix as optx
from pydantic import Field, PositiveFloat

from .base import AbstractSolver, Options, Outcome, PhaseReport, Result, tail_variance
from .problem import jax_seed, residuals
from .pyramid import Pyramid


class AdamOptions(Options):
    lr: PositiveFloat = 0.05
    """Learning rate (in the solver's unconstrained space)."""
    lr_end: PositiveFloat | None = None
    """The last step's learning rate: the rate decays geometrically from `lr` over the phase
    (None: constant). Adam's iterates wander by about the rate under Monte Carlo noise; a phase
    that ends at a small rate hands the next one a start near its optimum."""
    average: float = Field(0.0, ge=0.0, le=1.0)
    """Fraction of the last iterates averaged into the result (Polyak; 0: the last iterate)."""
    hold: Annotated[tuple[str, ...], Field(strict=False)] = ()  # TOML's array, a list
    """Material keys (or fnmatch patterns: `"*.mask.threshold"`) held at their values through
    this phase. A mask's threshold moves the boundary between two layers, so its gradient is the
    difference of their radiances: from neutral starting colours that has the wrong sign as often
    as not, and a threshold pushed out of the noise's range (about [0.2, 0.8]) lands where the mask
    no longer changes, with no gradient to bring it back. Held for a first phase, the thresholds
    move once the colours are near."""
    profile_gains: bool = True
    """Free gains solved in closed form between steps (variable projection) rather than as
    Adam's coordinates; over the averaged tail, from the least-squares sums of its steps."""
    levels: int = Field(0, ge=0, le=8)
    """Coarser grids of each free texture that Adam moves with its texels, each half the last
    one's size (`fit.solvers.pyramid`: a texel is its own coordinate plus its cells'): a
    texture's broad shape moves with the gradients of many pixels at once. 0: texels alone."""


class Adam(AbstractSolver):
    """Adam with a fresh seed every step (a fixed seed converges to its own biased optimum);
    steps whose loss or gradient is not finite are rejected, never applied, and counted. With
    `average` > 0 the result is the mean of that fraction of the last iterates (Polyak averaging:
    it cancels the steps' Monte Carlo noise). It always runs its steps (outcome `step_limit`);
    a phase whose every step was rejected has `diverged`."""

    name = "adam"
    Options = AdamOptions

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
        render = problem.render_fn("reverse", spp, downscale)
        # the closed form is the L2 loss's; robust losses keep the gains as Adam's coordinates
        profile = options.profile_gains and bool(problem.gain_views) and problem.loss == "l2"
        residual = residuals(
            problem, render, downscale, independent_gains=True, profile_gains=profile
        )
        n, size = problem.n_material, len(u0)
        pyramid = Pyramid(problem.free, options.levels)
        expand = pyramid.expand  # the solver's coordinates z -> u

        def loss(z, seed):
            u = expand(z)
            r, sums = residual(u, seed) if profile else (residual(u, seed), None)
            return 0.5 * jnp.dot(r, r), sums

        rate = options.lr
        if options.lr_end is not None and steps > 1:
            decay = (options.lr_end / options.lr) ** (1.0 / (steps - 1))
            rate = functools.partial(_geometric, options.lr, decay)
        optimiser = optax.adam(rate)
        if options.hold:  # zeroed before Adam: held coordinates keep zero moments, never move
            keep = np.asarray(problem.held(options.hold) == 0, np.float32)
            keep = jnp.asarray(np.concatenate([keep, keep[pyramid.owners()]]))
            zero = optax.stateless(lambda updates, params=None: updates * keep)
            optimiser = optax.chain(zero, optimiser)
        solver = optx.OptaxMinimiser(optimiser, rtol=0.0, atol=0.0)
        z = jnp.asarray(pyramid.start(u0), jnp.float32)
        f_struct = jax.ShapeDtypeStruct((), jnp.float32)
        state = solver.init(loss, z, jax_seed(seed), {}, f_struct, None, frozenset())
        step = jax.jit(lambda z, s, st: solver.step(loss, z, s, {}, st, frozenset()))
        history, tail, rejected, first, gain_sums = [], [], 0, 0, None
        if resume is not None:  # the state offered at step `first`
            leaves, treedef = jax.tree.flatten(state)
            saved = [
                jnp.asarray(v, dtype=x.dtype) for x, v in zip(leaves, resume["leaves"], strict=True)
            ]
            state = jax.tree.unflatten(treedef, saved)
            z = jnp.asarray(resume.get("z", resume["u"]), jnp.float32)
            first = int(resume["step"])
            history, rejected = list(resume["history"]), int(resume["rejected"])
            tail = list(np.asarray(resume["tail"]))
            gain_sums = resume.get("gain_sums")
        first_averaged = steps - round(options.average * steps)
        for i in range(first, steps):
            new_z, new_state, sums = step(z, jax_seed(seed * 100003 + i + 1), state)
            if profile and np.all(np.isfinite(sums := np.asarray(sums, np.float64))):
                # the gains from this step's least-squares sums (num, den), so they never lag
                # the material (averaging them over earlier steps, which lags, left the cup's
                # colours and gains 10 % along their valley twice out of two); over the averaged
                # tail from the sums of all its steps so far (one step's ratio is biased high by
                # its denominator's variance)
                if i >= first_averaged:
                    gain_sums = sums if gain_sums is None else gain_sums + sums
                    sums = gain_sums
                new_z = new_z.at[n:size].set(problem.gain_coordinates(_log_gains(sums)))
            value = float(new_state.f)  # the loss at `z`, before this update
            if np.all(np.isfinite(np.asarray(new_z))) and np.isfinite(value):
                z, state = new_z, new_state
            else:
                rejected += 1
            u = expand(z)
            history.append(value)
            if i >= first_averaged:
                tail.append(np.asarray(u))
            if progress:
                progress(i + 1, value)
            if offer:
                # references, not copies: the checkpoint converts them only when it writes
                offer(
                    {
                        "step": i + 1,
                        "u": u,
                        **({"z": z} if pyramid.extra else {}),
                        "leaves": jax.tree.leaves(state),
                        "history": history,
                        "n_history": len(history),
                        "tail": tail,
                        "n_tail": len(tail),
                        "rejected": rejected,
                        **({"gain_sums": gain_sums} if gain_sums is not None else {}),
                    }
                )
        u = expand(z)
        return averaged_result(self.name, problem, u, tail, gain_sums, history, steps, rejected)


def averaged_result(name, problem, u, tail, gain_sums, history, steps, rejected) -> Result:
    """A fresh-seed phase's `Result`: the mean of its averaged tail (else the last iterate `u`),
    its gains from the whole tail's least-squares sums (not a mean of ratios), the tail's own
    Monte Carlo variance, and its report (`diverged` when every step was rejected)."""
    u = np.asarray(u, np.float32)
    if tail:
        u = np.mean(tail, axis=0).astype(np.float32)
        if gain_sums is not None:
            u[problem.n_material :] = problem.gain_coordinates(_log_gains(gain_sums))
    final = history[-1] if history else float("nan")
    if steps and rejected == steps:
        outcome, message = Outcome.DIVERGED, "every step was non-finite; kept the start"
    else:
        outcome = Outcome.STEP_LIMIT
        message = f"{rejected} of {steps} steps rejected as non-finite" if rejected else ""
    report = PhaseReport(name, outcome, steps, rejected, message, final)
    out = Result(problem.values(u), u, final, steps, history, [report])
    out.tail_variance = tail_variance(tail)
    return out


def _geometric(lr: float, decay: float, count):
    """The rate at step `count` (a partial of this, not a closure: optimistix turns the optimiser's
    closures into pytrees and cannot take optax's schedules')."""
    return lr * decay**count


def _log_gains(sums: np.ndarray) -> np.ndarray:
    """log(num / den) of least-squares sums `(num, den)`; 0 (gain 1) where either is not positive
    (a view or channel with no signal)."""
    num, den = sums
    ok = (num > 0) & (den > 0)
    return np.where(ok, np.log(np.where(ok, num, 1) / np.where(ok, den, 1)), 0).astype(np.float32)
