"""Gauss-Newton uncertainty of a fit from one Jacobian render, in its sandwich form."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ..material import to_physical
from .problem import Problem, residuals

#: The uncertainty renders one forward-mode image per parameter component: skipped above this
#: many (textures), where the Jacobian would cost more than the fit.
MAX_UNCERTAINTY_PARAMS = 64


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
    residual = residuals(problem, lambda x, _: image0 + jac_x @ (x - x0), downscale)
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
