"""BFGS (optimistix) on reverse-mode gradients with one shared seed."""

from __future__ import annotations

import jax.numpy as jnp
import optimistix as optx

from .base import AbstractSolver, Options, Result, optimistix_result
from .problem import jax_seed, residuals


class BFGSOptions(Options):
    rtol: float = 1e-5
    """Relative tolerance of convergence."""
    atol: float = 1e-7
    """Absolute tolerance of convergence."""


class BFGS(AbstractSolver):
    """BFGS with one shared seed (its line search needs a fixed objective; fresh seeds stall
    it). Converges to that seed's optimum, like LM."""

    name = "bfgs"
    Options = BFGSOptions

    def run(
        self, problem, u0, *, steps, spp, seed, downscale, options, progress=None, **_
    ) -> Result:
        residual = residuals(problem, problem.render_fn("reverse", spp, downscale), downscale)

        def loss(u, seed):
            r = residual(u, seed)
            return 0.5 * jnp.dot(r, r)

        solution = optx.minimise(
            loss,
            optx.BFGS(rtol=options.rtol, atol=options.atol),
            jnp.asarray(u0, jnp.float32),
            args=jax_seed(seed),
            max_steps=steps,
            throw=False,
        )

        def loss_at(u):
            return loss(jnp.asarray(u), jax_seed(seed))

        return optimistix_result(self.name, problem, solution, u0, loss_at, progress)
