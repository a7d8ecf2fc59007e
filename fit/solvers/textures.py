"""Textures after Adam: a smoothness prior whose weight the data choose, and each texel's sd.

Adam fits a free texture texel by texel; each texel's value is then what its pixels say, with
their noise (the photographs', the renders'), and a texel no pixel sees keeps its start. Near
that answer t0 the loss is quadratic in the texels, `(t - t0)^T H (t - t0) / 2` with H the
Gauss-Newton curvature, taken here as its diagonal h (each texel's own information; the
bilinear lookup couples neighbours, which this leaves out). With a smoothness prior
`lambda t^T L t / 2` (L the texture grid's Laplacian: squared differences of 4-neighbours, per
channel, no wrap) the regularised texels are

    t = (H + lambda L)^-1 H t0,

a linear smoother of t0: seen texels are pulled towards their neighbours by what their pixels
do not pin down, unseen ones (h = 0) filled by their neighbours (harmonic interpolation).
lambda is chosen on a log grid by the unbiased predictive risk (Mallows' C_L): the lambda
minimising `||H^1/2 (t - t0)||^2 + 2 sigma^2 tr A`, A the smoother's matrix (its trace by
Hutchinson's estimator, the same probes for every lambda), sigma^2 the residual's variance per
pixel: the expected error of predicting the texels' pixels anew, estimated from the data, so no
weight is tuned per capture. (Generalised cross-validation, `||.||^2 / (n - tr A)^2`, picked the
smallest weight on a noisy ramp: its estimated trace's noise dominates `n - tr A` there.)

h is estimated without rendering a Jacobian (one forward render per texel): for Rademacher
weights v over the pixels, `E[(J^T v)_i^2] = sum_p J_pi^2 = h_i`; two reverse passes of
independent seeds per v give `(J1^T v)_i (J2^T v)_i`, whose expectation is the same without the
renders' noise squared in it (as the uncertainty's cross curvature, `uncertainty`).

Each texel's sd is `sigma sqrt(((H + lambda L)^-1)_ii)` (sigma^2 the residual's variance per
pixel; the diagonal by Hutchinson's estimator, at least `1 / (h_i + lambda L_ii)`), at most the
sd of a value uniform over its bounds (`(upper - lower) / sqrt(12)`: what a texel no pixel sees
is known to be). The texels' coupling through the bilinear lookup and through the scalars is
not in it.

A mask's texels are not smoothed (`smooth_textures`); their sd is the texel's own term,
`sigma / sqrt(h_i)` with the same cap (`texel_sd`), from the curvature the scalars' trade renders
at the end of the fit.

The scalars' sd, the other way round, counts what the texels take from them: `texel_trade`,
the Schur complement's term of the curvature (each texel's cross curvature with a scalar from
one reverse pass per scalar, `H_tt` the diagonal above), which the uncertainty adds
(`fit.solvers.uncertainty.traded_inverse`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..material import to_physical, to_unconstrained
from .problem import Problem

#: Rademacher probes of the curvature (two reverse passes each).
PROBES = 8
#: The prior weights tried: this range of decades around the median seen texel's curvature.
DECADES = (-4.0, 2.0)
GRID = 13
#: Hutchinson probes of the smoother's trace per weight.
TRACE_PROBES = 8
#: Hutchinson probes of the texels' variances (the diagonal of the smoother's inverse).
VARIANCE_PROBES = 32
#: Seed offset of the probes' renders.
PROBE_SEED_OFFSET = 0x7E4E1


def uniform_sd(f) -> float:
    """The sd of a value uniform over free texture `f`'s bounds: what a texel no pixel sees is
    known to be, and the most a texel's sd is reported."""
    return (float(np.max(f.spec.upper)) - float(np.min(f.spec.lower))) / np.sqrt(12.0)


@dataclass
class Smoothed:
    """The smoothed vector, and per texture its texels' sd, the prior weight chosen and the
    share of its texels seen; the curvature's diagonal it was smoothed with (`curvature`)."""

    u: np.ndarray
    std: dict[str, np.ndarray]
    weight: dict[str, float]
    seen: dict[str, float]
    curvature: np.ndarray


def laplacian(height: int, width: int):
    """The grid's Laplacian `Dx^T Dx + Dy^T Dy` (sparse, height * width square, row-major)."""
    import scipy.sparse as sp

    def diff(n):
        return sp.diags([-np.ones(n - 1), np.ones(n - 1)], [0, 1], shape=(n - 1, n))

    dx = sp.kron(sp.identity(height), diff(width))
    dy = sp.kron(diff(height), sp.identity(width))
    return (dx.T @ dx + dy.T @ dy).tocsc()


def curvature(
    problem: Problem, u: np.ndarray, spp: int, seed: int, downscale: int = 1, stop=None
) -> np.ndarray:
    """The diagonal of the Gauss-Newton curvature of the loss in the physical material values
    (see the module; negative estimates, texels whose information is below the renders' noise,
    are 0). `stop()` is asked before each probe's reverse passes; True (a Ctrl-C) raises
    `KeyboardInterrupt` there."""
    renderer = problem.renderer(downscale)
    n = problem.n_material
    values = np.asarray(to_physical(problem.free, np.asarray(u, np.float64)[:n]), np.float32)
    scale = residual_scale(problem, u, downscale)
    rng = np.random.default_rng(seed)
    total = np.zeros(n)
    for k in range(PROBES):
        if stop is not None and stop():
            raise KeyboardInterrupt
        v = (rng.integers(0, 2, scale.size) * 2 - 1) * scale
        cotangent = v.astype(np.float32)
        s = seed + PROBE_SEED_OFFSET + 2 * k
        g1 = renderer.vjp(values, s, spp, cotangent).astype(np.float64)
        g2 = renderer.vjp(values, s + 1, spp, cotangent).astype(np.float64)
        total += g1 * g2
    return np.maximum(total / PROBES, 0.0)


def residual_scale(problem: Problem, u: np.ndarray, downscale: int = 1) -> np.ndarray:
    """d(weighted residual) / d(render), per pixel channel: the weights' square roots times the
    views' gains."""
    _, sqrt_w = problem.target(downscale)
    scale = sqrt_w.astype(np.float64)
    if problem.gain_views:
        gains = problem.gain_multipliers(np.asarray(u)[problem.n_material :], downscale)
        scale = scale * np.asarray(gains, np.float64)
    return scale


def residual_variance(
    problem: Problem, u: np.ndarray, spp: int, seed: int, downscale: int = 1
) -> float:
    """The weighted residual's variance per pixel channel at `u` (one render at `spp`)."""
    renderer = problem.renderer(downscale)
    n = problem.n_material
    values = np.asarray(to_physical(problem.free, np.asarray(u, np.float64)[:n]), np.float32)
    target, sqrt_w = problem.target(downscale)
    image = renderer.render(values, seed, spp).astype(np.float64)
    if problem.gain_views:
        gains = problem.gain_multipliers(np.asarray(u)[n:], downscale)
        image = image * np.asarray(gains, np.float64)
    r = sqrt_w * (image - target)
    used = int(np.count_nonzero(sqrt_w))
    return float(np.sum(r**2)) / max(used - n, 1)


def smooth(
    t0: np.ndarray, h: np.ndarray, sigma2: float, seed: int = 0
) -> tuple[np.ndarray, float, np.ndarray]:
    """One channel's texels (height, width) smoothed by the prior weight the predictive risk
    chooses (`sigma2`: the residual's variance per pixel, in the units of `h`): (texels,
    weight, each texel's information: 1 / its variance in units of sigma^2)."""
    import scipy.sparse as sp
    from scipy.sparse.linalg import splu

    height, width = t0.shape
    lap = laplacian(height, width)
    y, hd = t0.ravel().astype(np.float64), h.ravel().astype(np.float64)
    seen = hd > 0
    if not seen.any():
        return t0.copy(), float("inf"), np.zeros_like(hd).reshape(t0.shape)
    base = float(np.median(hd[seen]))
    rng = np.random.default_rng(seed)
    probes = rng.integers(0, 2, (TRACE_PROBES, hd.size)) * 2.0 - 1.0
    best = None
    for weight in base * np.logspace(*DECADES, GRID):
        lu = splu((sp.diags(hd) + weight * lap).tocsc())
        t = lu.solve(hd * y)
        trace = float(np.mean([z @ lu.solve(hd * z) for z in probes]))
        score = float(np.sum(hd * (t - y) ** 2)) + 2.0 * sigma2 * trace
        if best is None or score < best[0]:
            best = (score, weight, t)
    _, weight, t = best
    # the diagonal of (H + weight L)^-1: Hutchinson's estimate, at least the texel's own term
    lu = splu((sp.diags(hd) + weight * lap).tocsc())
    probes = rng.integers(0, 2, (VARIANCE_PROBES, hd.size)) * 2.0 - 1.0
    diagonal = np.mean([z * lu.solve(z) for z in probes], axis=0)
    variance = np.maximum(diagonal, 1.0 / (hd + weight * lap.diagonal()))
    return t.reshape(t0.shape), float(weight), (1.0 / variance).reshape(t0.shape)


def smooth_textures(problem: Problem, u: np.ndarray, spp: int, seed: int) -> Smoothed:
    """The colour textures of `problem` at `u` smoothed (see the module), each texel's sd, and
    the prior weights chosen; masks' texels, scalars and gains unchanged. A mask's texels are
    not smoothed: their gradients pass through the layer choice's Russian roulette, and 8
    probes left many texels' information at 0 on a 16x16 checkerboard mask, whose smoothing
    then blurred it (mean error 0.04 before, 0.16 after)."""
    n = problem.n_material
    u = np.asarray(u, np.float32)
    values = np.asarray(to_physical(problem.free, u[:n].astype(np.float64)), np.float64)
    h = curvature(problem, u, spp, seed)
    sigma2 = residual_variance(problem, u, spp, seed + PROBE_SEED_OFFSET - 1)
    out, std, weights, seen, i = values.copy(), {}, {}, {}, 0
    for f in problem.free:
        if f.shape and f.spec.kind == "rgb":
            texels = values[i : i + f.size].reshape(f.shape)
            curv = h[i : i + f.size].reshape(f.shape)
            smoothed = np.empty_like(texels)
            sd = np.empty_like(texels)
            chosen = []
            for c in range(f.shape[-1]):
                t, weight, information = smooth(texels[..., c], curv[..., c], sigma2, seed + c)
                smoothed[..., c] = t
                chosen.append(weight)
                with np.errstate(divide="ignore"):
                    sd[..., c] = np.sqrt(sigma2 / information)
            lo, hi = float(np.min(f.spec.lower)), float(np.max(f.spec.upper))
            std[f.key] = np.minimum(sd, uniform_sd(f)).astype(np.float32)
            out[i : i + f.size] = np.clip(smoothed, lo, hi).ravel()
            weights[f.key] = float(np.median(chosen))
            seen[f.key] = float(np.mean(curv > 0))
        i += f.size
    smoothed_u = u.copy()
    smoothed_u[:n] = np.asarray(to_unconstrained(problem.free, _by_key(problem, out)), np.float32)
    return Smoothed(smoothed_u, std, weights, seen, h)


def texel_sd(
    problem: Problem, u: np.ndarray, h: np.ndarray, sigma2: float, keys: set[str]
) -> tuple[dict[str, np.ndarray], dict[str, float]]:
    """The texels' sd of the textures named by `keys` where no smoothing gave them one (a
    mask's texels): `sqrt(sigma2 / h_i)`, each texel's own information with its neighbours and
    the scalars held (`h`: `curvature`'s diagonal at `u`, `sigma2` the residual's variance per
    pixel at the same resolution), at most the sd of a value uniform over its bounds (a texel no
    pixel sees: h = 0); with the share of each texture's texels seen."""
    std, seen, i = {}, {}, 0
    for f in problem.free:
        if f.shape and f.key in keys:
            curv = np.asarray(h[i : i + f.size], np.float64).reshape(f.shape)
            with np.errstate(divide="ignore"):
                sd = np.sqrt(sigma2 / curv)
            std[f.key] = np.minimum(sd, uniform_sd(f)).astype(np.float32)
            seen[f.key] = float(np.mean(curv > 0))
        i += f.size
    return std, seen


#: Seed offset of the renders of the scalars' trade with the texels.
TRADE_SEED_OFFSET = 0x7ADE5


def texel_trade(
    problem: Problem,
    u: np.ndarray,
    jacobians: tuple[np.ndarray, np.ndarray],
    spp: int,
    seed: int,
    downscale: int = 1,
    weights: dict[str, float] | None = None,
    h: np.ndarray | None = None,
    stop=None,
) -> np.ndarray:
    """What the free textures of `problem` at `u` take from the scalars' curvature: the Schur
    complement's term `H_st H_tt^-1 H_ts` (rows and columns: the held problem's coordinates,
    whose weighted residuals' Jacobians are `jacobians`, two independent renders), so that the
    scalars' curvature with the texels refitted is `H_ss - H_st H_tt^-1 H_ts`.

    `H_ts`, each texel's cross curvature with a coordinate k, is one reverse pass with that
    coordinate's Jacobian column as the cotangent (`sum_p J_pi J_pk`), from each Jacobian with
    its own seed: their product is unbiased for the noise-free one's. `H_tt` is taken as its
    diagonal (`curvature`: a texel's own pixels; the bilinear lookup's coupling of neighbours
    left out), plus a colour texture's smoothness prior (`weights`, the smoother's weight times
    the grid Laplacian's diagonal; `h`: the curvature's diagonal where the smoother has it at
    this resolution, else estimated here). Texels no pixel sees are held; texels on a bound
    trade like the others (a mask's texels reach 0 and 1: held there, as an active bound, the
    stained torus's glaze pigment ended 7-10 sd off, its sd a third of the one they give). `stop()`
    is asked before each reverse pass; True (a Ctrl-C) raises `KeyboardInterrupt` there."""
    n = problem.n_material
    u = np.asarray(u, np.float64)
    values = np.asarray(to_physical(problem.free, u[:n]), np.float64)
    if h is None:
        h = curvature(problem, u, spp, seed, downscale, stop)
    diagonal = np.zeros(n)
    texel = np.zeros(n, bool)
    i = 0
    for f in problem.free:
        if f.shape:
            part = slice(i, i + f.size)
            prior = 0.0
            if weights and np.isfinite(weights.get(f.key, np.inf)):
                height, width, channels = f.shape
                lap = np.repeat(laplacian(height, width).diagonal(), channels)
                prior = weights[f.key] * lap
            texel[part] = h[part] > 0
            diagonal[part] = h[part] + prior
        i += f.size
    if not texel.any():
        return np.zeros((jacobians[0].shape[1],) * 2)
    renderer = problem.renderer(downscale)
    scale = residual_scale(problem, u, downscale)
    x = values.astype(np.float32)
    cross = []
    for j, jac in enumerate(jacobians):
        columns = []
        for k in range(jac.shape[1]):
            if stop is not None and stop():
                raise KeyboardInterrupt
            cotangent = (scale * jac[:, k]).astype(np.float32)
            s = seed + TRADE_SEED_OFFSET + 2 * k + j
            columns.append(renderer.vjp(x, s, spp, cotangent).astype(np.float64)[texel])
        cross.append(np.stack(columns, axis=1))
    a1, a2 = cross
    product = (a1 / diagonal[texel, None]).T @ a2
    return 0.5 * (product + product.T)


def _by_key(problem: Problem, flat: np.ndarray) -> dict:
    out, i = {}, 0
    for f in problem.free:
        chunk = flat[i : i + f.size]
        out[f.key] = chunk if f.size > 1 else float(chunk[0])
        i += f.size
    return out
