"""BFGS (optimistix) on reverse-mode gradients with one shared seed."""

from __future__ import annotations

import functools

import jax.numpy as jnp
import optimistix as optx

from .base import AbstractSolver, Options, Result, solve_optimistix
from .problem import residuals


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

        solver = optx.BFGS(rtol=options.rtol, atol=options.atol)
        solve = functools.partial(optx.minimise, loss, solver)
        return solve_optimistix(self.name, problem, solve, u0, seed, steps, loss, progress)
