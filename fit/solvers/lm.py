"""Levenberg-Marquardt (optimistix) on the explicit Jacobian of one seed's render."""

from __future__ import annotations

from typing import Annotated

import jax.numpy as jnp
import numpy as np
import optimistix as optx
from pydantic import Field, PositiveInt

from captures.errors import InputError

from ..limits import MAX_SPP
from .base import AbstractSolver, Options, Result, optimistix_result
from .problem import jax_seed, residuals
from .uncertainty import forward_mode_refusal


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
        refusal = forward_mode_refusal(problem)
        if refusal:
            raise InputError(
                f"solver lm: {refusal}, and it renders a forward-mode Jacobian: use adam for "
                "textures"
            )
        render = problem.render_fn("jacobian", spp, downscale, options.jacobian_spp)
        independent = options.jacobian_spp is not None
        residual = residuals(problem, render, downscale, independent_gains=independent)
        solution = optx.least_squares(
            residual,
            optx.LevenbergMarquardt(rtol=options.rtol, atol=options.atol),
            jnp.asarray(u0, jnp.float32),
            args=jax_seed(seed),
            max_steps=steps,
            throw=False,
        )

        def loss_at(u):
            r = np.asarray(residual(jnp.asarray(u), jax_seed(seed)))
            return 0.5 * r @ r

        return optimistix_result(self.name, problem, solution, u0, loss_at, progress)
