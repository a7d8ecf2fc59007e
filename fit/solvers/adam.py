"""Adam (optax through `optimistix.OptaxMinimiser`) with a fresh seed every step."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import optax
import optimistix as optx
from pydantic import Field, PositiveFloat

from .base import AbstractSolver, Options, Outcome, PhaseReport, Result
from .problem import residuals


class AdamOptions(Options):
    lr: PositiveFloat = 0.05
    """Learning rate (in the solver's unconstrained space)."""
    average: float = Field(0.0, ge=0.0, le=1.0)
    """Fraction of the last iterates averaged into the result (Polyak; 0: the last iterate)."""


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
        residual = residuals(problem, render, downscale, independent_gains=True)

        def loss(u, seed):
            r = residual(u, seed)
            return 0.5 * jnp.dot(r, r), None

        solver = optx.OptaxMinimiser(optax.adam(options.lr), rtol=0.0, atol=0.0)
        u = jnp.asarray(u0, jnp.float32)
        f_struct = jax.ShapeDtypeStruct((), jnp.float32)
        state = solver.init(loss, u, jnp.int32(seed), {}, f_struct, None, frozenset())
        step = jax.jit(lambda u, s, st: solver.step(loss, u, s, {}, st, frozenset())[:2])
        history, tail, rejected, first = [], [], 0, 0
        if resume is not None:  # the state offered at step `first`
            leaves, treedef = jax.tree.flatten(state)
            saved = [
                jnp.asarray(v, dtype=x.dtype) for x, v in zip(leaves, resume["leaves"], strict=True)
            ]
            state = jax.tree.unflatten(treedef, saved)
            u, first = jnp.asarray(resume["u"], jnp.float32), int(resume["step"])
            history, rejected = list(resume["history"]), int(resume["rejected"])
            tail = list(np.asarray(resume["tail"]))
        first_averaged = steps - round(options.average * steps)
        for i in range(first, steps):
            new_u, new_state = step(u, jnp.int32(seed * 100003 + i + 1), state)
            value = float(new_state.f)  # the loss at `u`, before this update
            if np.all(np.isfinite(np.asarray(new_u))) and np.isfinite(value):
                u, state = new_u, new_state
            else:
                rejected += 1
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
                        "leaves": jax.tree.leaves(state),
                        "history": history,
                        "tail": tail,
                        "rejected": rejected,
                    }
                )
        if tail:
            u = jnp.asarray(np.mean(tail, axis=0))
        u = np.asarray(u)
        final = history[-1] if history else float("nan")
        if steps and rejected == steps:
            outcome, message = Outcome.DIVERGED, "every step was non-finite; kept the start"
        else:
            outcome = Outcome.STEP_LIMIT
            message = f"{rejected} of {steps} steps rejected as non-finite" if rejected else ""
        report = PhaseReport(self.name, outcome, steps, rejected, message, final)
        return Result(problem.values(u), u, final, steps, history, [report])
