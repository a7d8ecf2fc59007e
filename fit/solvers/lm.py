"""Levenberg-Marquardt (optimistix) on the explicit Jacobian of one seed's render."""

from __future__ import annotations

import functools
from typing import Annotated

import numpy as np
import optimistix as optx
from pydantic import Field, PositiveInt

from ..limits import MAX_SPP
from .base import AbstractSolver, Options, Result, solve_optimistix
from .problem import residuals
from .uncertainty import refuse_forward_mode


class LMOptions(Options):
    jacobian_spp: Annotated[PositiveInt, Field(le=MAX_SPP)] | None = None
    """Render the Jacobian decorrelated at this spp (absent: the residual's own seed and spp)."""
    rtol: float = 1e-4
    """Relative tolerance of convergence."""
    atol: float = 1e-6
    """Absolute tolerance of convergence."""


class LevenbergMarquardt(AbstractSolver):
    """LM on the explicit Jacobian with one seed. By default the Jacobian is this seed's exact
    one (common random numbers: converges fast to the seed's own optimum, biased at low spp);
    with `jacobian_spp` it is rendered decorrelated at that spp (see `Renderer.jacobian`): the
    fixed point is unbiased and a cheap Jacobian serves an accurate, high-spp residual."""

    name = "lm"
    Options = LMOptions

    def run(
        self, problem, u0, *, steps, spp, seed, downscale, options, progress=None, **_
    ) -> Result:
        refuse_forward_mode(problem, "lm", "it renders a forward-mode Jacobian")
        render = problem.render_fn("jacobian", spp, downscale, options.jacobian_spp)
        independent = options.jacobian_spp is not None
        residual = residuals(problem, render, downscale, independent_gains=independent)

        def loss_at(u, seed):
            r = np.asarray(residual(u, seed))
            return 0.5 * r @ r

        solver = optx.LevenbergMarquardt(rtol=options.rtol, atol=options.atol)
        solve = functools.partial(optx.least_squares, residual, solver)
        return solve_optimistix(self.name, problem, solve, u0, seed, steps, loss_at, progress)
