"""Gauss-Newton uncertainty of a fit from one Jacobian render, in its sandwich form."""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
from scipy.linalg import block_diag

from captures.errors import InputError

from ..material import to_physical
from .problem import Problem, residuals

#: The uncertainty renders one forward-mode image per parameter component: skipped above this
#: many (textures), where the Jacobian would cost more than the fit.
MAX_UNCERTAINTY_PARAMS = 64


def forward_mode_refusal(problem: Problem) -> str | None:
    """Why the forward-mode Jacobian (the solvers `gn` and `lm`, the uncertainty) cannot be
    rendered for `problem`, or None: a free texture (Mitsuba 3.9's forward mode through a
    bitmap's texels fails inside its integrator's loop: "tried to forward-propagate derivatives
    across edge ... outside of the current dr.isolate_grad() scope", an 8x8 mask measured), or
    more than `MAX_UNCERTAINTY_PARAMS` components (one forward pass each)."""
    textures = [f.key for f in problem.free if f.shape]
    if textures:
        return f"{', '.join(textures)} {'is a texture' if len(textures) == 1 else 'are textures'}"
    if problem.n_material > MAX_UNCERTAINTY_PARAMS:
        return f"{problem.n_material} free components (one forward-mode render each)"
    return None


def refuse_forward_mode(problem: Problem, solver: str, needs: str) -> None:
    """An `InputError` where `forward_mode_refusal` refuses `problem` to `solver`, which `needs`
    (what it renders in forward mode)."""
    refusal = forward_mode_refusal(problem)
    if refusal:
        raise InputError(f"solver {solver}: {refusal}, and {needs}: use adam for textures")


#: The second Jacobian render of the uncertainty uses the seed plus this offset.
CROSS_SEED_OFFSET = 0xC2055


#: Where the two Jacobians leave a direction undetermined, each is averaged with this many
#: more renders of its own (other seeds), one at a time until every direction is determined.
#: The main job's seed 4 (`configs/cup-fit.toml`, 32 spp) reported alpha, ior, the pigment's
#: red and the stain's green undetermined with all their errors within the targets.
UNDETERMINED_RETRIES = 1
#: Seed offset of each retry's pair of renders.
RETRY_SEED_OFFSET = 0x7E7A1

#: A coordinate whose share of an undetermined direction (its unit eigenvector's component)
#: exceeds this is undetermined; below it, the direction is another parameters' trade.
UNDETERMINED_LOADING = 0.1
#: An eigenvalue of the curvature scaled to a unit diagonal above this is determined: its
#: Jacobians are float32 (a relative precision of 6e-8), so a scaled eigenvalue under about
#: 1e-6 is rounding, not information.
DETERMINED_FLOOR = 1e-6


def cross_product(a: np.ndarray, b: np.ndarray, weight: np.ndarray | None = None) -> np.ndarray:
    """`(a^T W b + b^T W a) / 2`, W = diag(weight): unbiased for `E[a]^T W E[a]` when a and b
    are independent estimates of one matrix."""
    wb = b if weight is None else b * weight[:, None]
    product = a.T @ wb
    return 0.5 * (product + product.T)


def inverse_determined(h: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The inverse of a symmetric matrix on the span of its clearly positive eigenvalues, and
    which coordinates load on a direction that is not by more than `UNDETERMINED_LOADING`
    (undetermined). Decided on the matrix scaled to a unit diagonal (its correlation form), so
    that a coordinate's units do not decide it: an eigenvalue above `DETERMINED_FLOOR` there is
    determined. A coordinate whose own curvature is not positive (noise larger than its
    signal) or whose row is not finite is undetermined (its row and column of the inverse
    zero), and all are where the eigendecomposition fails: an uncertainty never loses the fit
    it reports on.

    Unscaled, an eigenvalue under 1e-9 of the largest was cut: ior at 1.011 of its [1.01, 3]
    (its sigmoid's slope 0.001) had a clean curvature of 4.5e-11 against the pigment's 0.05,
    and came out undetermined though its scaled eigenvalues were all above 0.64."""
    h = np.asarray(h, np.float64)
    finite = np.all(np.isfinite(h), axis=1)
    inverse, undetermined = np.zeros_like(h), ~finite
    block = np.ix_(finite, finite)
    diagonal = np.diag(h)[finite]
    positive = diagonal > 0
    scale = np.where(positive, 1.0 / np.sqrt(np.where(positive, diagonal, 1.0)), 0.0)
    try:
        values, vectors = np.linalg.eigh(h[block] * np.outer(scale, scale))
    except np.linalg.LinAlgError:
        return inverse, np.ones(len(h), bool)
    good = values > DETERMINED_FLOOR
    scaled_inverse = (vectors[:, good] / values[good]) @ vectors[:, good].T
    inverse[block] = np.outer(scale, scale) * scaled_inverse
    loading = np.abs(vectors[:, ~good]).max(axis=1, initial=0.0)
    undetermined[finite] = ~positive | (loading > UNDETERMINED_LOADING)
    return inverse, undetermined


def finite_rows(r: np.ndarray, jac: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`r` and `jac` with what is not finite zeroed: a residual that is not finite is no
    observation (its row of `jac` zeroed too), a derivative that is not finite no information
    on its parameter. A render at a diverged fit's extreme values was NaN throughout (Adam at
    lr 100); a parameter left without information is reported undetermined, the others keep
    theirs."""
    bad_r, bad_j = ~np.isfinite(r), ~np.isfinite(jac)
    if not (bad_r.any() or bad_j.any()):
        return r, jac
    r, jac = np.where(bad_r, 0.0, r), np.where(bad_j, 0.0, jac)
    jac[bad_r] = 0.0
    return r, jac


def _meat(jac1, jac2, r1, r2, channels: int = 3) -> np.ndarray:
    """`sum_p (J_p^T r1_p)(J_p^T r2_p)^T` over pixels p (each `channels` consecutive rows), J the
    two renders' mean Jacobian, symmetrised, its negative eigenvalues set to zero: `r1 r2` is
    unbiased for the squared residual of a noise-free render.

    Summed within a pixel first because a pixel's channels share its light paths, so their
    noise is correlated: per channel (`J^T diag(r1 r2) J`) the meat left out that covariance.
    Measured on the recovery sweep's sphere at ior 2.8 (160x120, three views; eight independent
    256-spp targets against a 4096-spp mean, the offset `H^-1 J^T t` exactly): alpha's offset
    spread 0.98 % (ior 0.055), per channel the sandwich said 0.37 % (0.029), per pixel 0.63 %
    (0.050); 2x2 or 4x4 pixel blocks added nothing (the box filter keeps pixels apart)."""
    mean = 0.5 * (jac1 + jac2)
    return pixel_meat(
        mean * np.asarray(r1, np.float64)[:, None],
        mean * np.asarray(r2, np.float64)[:, None],
        channels,
    )


def pixel_meat(a: np.ndarray, b: np.ndarray, channels: int = 3) -> np.ndarray:
    """The positive part of `sum_p a_p^T b_p` (symmetrised), a_p and b_p the sums over a pixel's
    `channels` consecutive rows of two independent series of per-residual gradient terms (rows:
    residuals, columns: parameters); rows of one channel each where they do not divide."""
    if len(a) % channels:
        channels = 1
    p = a.shape[1]
    sa, sb = (x.reshape(-1, channels, p).sum(axis=1) for x in (a, b))
    values, vectors = np.linalg.eigh(cross_product(sa, sb))
    return (vectors * np.clip(values, 0.0, None)) @ vectors.T


#: The most of the curvature, in any direction, that the textures' trade takes: the scalars'
#: sd grows at most `1 / sqrt(1 - MAX_TRADE)` times (10x).
MAX_TRADE = 0.99


def traded_inverse(trade: np.ndarray, inverse: np.ndarray) -> np.ndarray:
    """`(H - T)^-1 - H^-1` on the span of `inverse` (H's inverse where determined): in H's
    whitened coordinates T's eigenvalues are cut to [0, `MAX_TRADE`] (its estimate is noisy),
    so the result is positive semi-definite."""
    values, vectors = np.linalg.eigh(0.5 * (inverse + inverse.T))
    keep = values > values.max(initial=0.0) * 1e-12
    root = vectors[:, keep] * np.sqrt(values[keep])  # inverse = root @ root.T
    whitened = root.T @ np.asarray(trade, np.float64) @ root
    w, q = np.linalg.eigh(0.5 * (whitened + whitened.T))
    w = np.clip(w, 0.0, MAX_TRADE)
    # (I - W)^-1 - I = W (I - W)^-1 in the whitened coordinates
    return (root @ q) * (w / (1.0 - w)) @ (root @ q).T


def averaging_covariance(iterates, gradients, u, h, inverse) -> np.ndarray:
    """The covariance of an averaged answer `u` from the fresh-seed `gradients` at `iterates`
    (rows, one per averaged step): `H^-1 S H^-1 / n`, S the covariance of the gradients' noise
    `g_i - H (u_i - u)` (their mean's change along the steps taken out), `inverse` = H^-1."""
    iterates, gradients = np.asarray(iterates, np.float64), np.asarray(gradients, np.float64)
    noise = gradients - (iterates - np.asarray(u, np.float64)) @ h
    return inverse @ np.atleast_2d(np.cov(noise, rowvar=False)) @ inverse / len(noise)


def transform_jacobian(free, u) -> np.ndarray:
    """d(physical values)/du of the material's part `u` of a solver vector (its transforms'
    derivatives: diagonal per component, zero past the coordinate's clip; a `clipped_sigmoid`'s
    passes straight through its clip at the bounds, as `to_physical` gives it under JAX)."""
    jacobian, _ = _transform_derivatives(free)
    return np.asarray(jacobian(jnp.asarray(u, jnp.float32)), np.float64)


def transform_slope(free, u) -> np.ndarray:
    """The diagonal of `transform_jacobian` (each transform acts on its own component), from
    one forward-mode pass: no N x N matrix where textures are free."""
    _, slope = _transform_derivatives(free)
    return np.asarray(slope(jnp.asarray(u, jnp.float32)), np.float64)


def _transform_derivatives(free) -> tuple[Callable, Callable]:
    """`transform_jacobian`'s and `transform_slope`'s derivatives of `to_physical`, jitted once
    per free parameters' declarations and sizes (all `to_physical` reads of them): traced op by
    op, the two took 4-7 ms a call on the Cycles sphere's six components, and a `gn` phase
    asks for them at every noise and precision check."""
    key = tuple((f.spec, f.size) for f in free)
    if key not in _derivatives:
        free = list(free)

        def physical(v):
            return to_physical(free, v, jnp)

        _derivatives[key] = (
            jax.jit(jax.jacfwd(physical)),
            jax.jit(lambda v: jax.jvp(physical, (v,), (jnp.ones_like(v),))[1]),
        )
    return _derivatives[key]


#: `_transform_derivatives`' jitted functions by the free parameters' declarations and sizes (a
#: cache, named as none of the constants that `fit.bench.constants_digest` reads).
_derivatives: dict[tuple, tuple[Callable, Callable]] = {}


def linearised(
    problem: Problem, u, spp: int, seed: int, downscale: int = 1
) -> tuple[np.ndarray, np.ndarray]:
    """The weighted residuals at `u` and their Jacobian in the solver's space (gains included),
    from one Jacobian render at `spp` (one forward-mode pass per material component); the
    residual's own derivatives (gains, loss, weights) follow in JAX through the render's
    linearisation."""
    u = jnp.asarray(u, jnp.float32)
    x0 = np.asarray(to_physical(problem.free, u[: problem.n_material], jnp))
    image0, jac_x = problem.renderer(downscale).jacobian(x0, seed, spp)
    r, jac = linear_model(problem, downscale)(u, image0, jac_x, x0)
    return np.asarray(r, np.float64), np.asarray(jac, np.float64)


def linear_model(problem: Problem, downscale: int = 1):
    """`f(u, image0, jac_x, x0)`: the weighted residuals and their Jacobian in the solver's space
    at `u` of the linear image `image0 + jac_x (x - x0)` (a render and its Jacobian in physical
    values at `x0`), jitted: a Jacobian rendered at one point serves the solver's coordinates at
    another (the transforms' derivatives taken where `u` is). One per problem and resolution
    (kept in its cache: compiled once for every phase and the uncertainty)."""
    key = ("linear_model", downscale)
    if key not in problem._cache:

        def f(u, image0, jac_x, x0):
            residual = residuals(problem, lambda x, _: image0 + jac_x @ (x - x0), downscale)
            u = jnp.asarray(u, jnp.float32)
            return residual(u, 0), jax.jacfwd(residual)(u, 0)

        problem._cache[key] = jax.jit(f)
    return problem._cache[key]


def uncertainty(
    problem: Problem,
    u,
    spp: int = 64,
    seed: int = 0,
    threshold: float = 0.1,
    downscale: int = 1,
    extra_variance: np.ndarray | None = None,
    tail_gradients: tuple[np.ndarray, np.ndarray] | None = None,
    stop: Callable[[], bool] | None = None,
    linearisation: tuple | None = None,
    trade: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None,
) -> tuple[dict, np.ndarray, list[str]]:
    """Gauss-Newton covariance at the solver's vector `u` in its sandwich form,
    `H^-1 (sum_p J_p^T r_p r_p^T J_p) H^-1 * N / (N - P)` (p: a pixel's channels; `_meat`) with
    `H = J^T J` (J, r: the weighted Jacobian and residuals), mapped to physical units through
    the transforms' derivatives (so the same as the covariance in physical units: a value near
    its bound, where its sigmoid is flat, keeps the sd its images give it).

    The plain form `s^2 (J^T J)^-1` assumes every pixel equally noisy; Monte Carlo noise gathers
    in highlights, where roughness and ior are decided (measured on the default job's sphere:
    plain std alpha 0.00008 / ior 0.0005 against actual errors 0.0014 / 0.0053).

    A rendered Jacobian is noisy, and `J^T J` of one render is `E[J]^T E[J]` plus the noise's
    covariance: where the image barely depends on a parameter (alpha 0.01 on a small sphere:
    the forward derivative's noise is 40 % of its mean over 40 x 32 spp) that noise is the
    curvature, and the standard deviation came out 7x too small. So the Jacobian is rendered
    twice with independent seeds at `spp / 2` each, and the curvature is their symmetrised cross
    product `(J1^T J2 + J2^T J1) / 2`, whose expectation is the noise-free one. A direction
    whose cross curvature is not positive (its noise larger than its signal) gets more samples
    (`UNDETERMINED_RETRIES`: each Jacobian averaged with another render of its own), and if it is
    still not positive it is undetermined: its standard deviation is reported as infinite.

    The meat comes from the two renders' mean Jacobian and per pixel the squared residual less
    the renders' own noise, `((r1 + r2) / 2)^2 - ((r1 - r2) / 2)^2 = r1 r2` (unbiased for the
    squared residual of a noise-free render: the target's noise and the model's misfit), summed
    and then cut to its positive part. Its plain square counted the uncertainty render's noise
    as the target's (alpha 0.02 on a sphere, 64 spp against a 256-spp target: the data's part
    of alpha's sd 0.0031 with it, 0.0020 without).

    Added to that, the fit's own Monte Carlo error. With `tail_gradients` (the averaged steps'
    iterates and fresh-seed gradients, `Result.tail_gradients`): `H^-1 S H^-1 / n` (Polyak), S
    the covariance of the gradients' noise `g_i - H (u_i - u)` over the n steps. The noise of a
    reverse-mode gradient is mostly its adjoint's noise times the primal's (alpha 0.02 on a
    sphere: a 16-spp gradient's Newton step has a standard deviation of 105 % of alpha, the
    primal image's noise alone about 20 %), far more than the image's noise says. Otherwise
    `extra_variance` (per solver coordinate, from the iterates' scatter: `Result.tail_variance`).

    With `linearisation` (`Result.linearisation`: a `gn` phase's two series of Jacobian
    renders at this resolution, each the mean of its refreshes) those are the two Jacobians,
    taken to `u` through their linear images (the phase's iterates and `u` differ by its Monte
    Carlo noise), each series topped up to `spp / 2` samples by a render of the rest: on the
    Cycles sphere the default's last phase renders as many samples as the uncertainty did (3.5
    s of a 28 s command), and the draft's, of 4 steps, half of them.
    `stop()` is asked before each render; True (a Ctrl-C) raises `KeyboardInterrupt` there.

    With `trade` (`u`'s coordinates are the scalars of a fit whose textures are held: `trade(J1,
    J2)` is what the textures take from their curvature H, the Schur complement's term T,
    `fit.solvers.textures.texel_trade`) the covariance gains `s^2 ((H - T)^-1 - H^-1)`, s^2 the
    residual's variance per pixel channel: what the scalars' sd is with the texels refitted
    beside them (a stain's colour trades with its mask's texels), less what it is with them
    held. T is cut to at most `MAX_TRADE` of H in every direction.

    Returns per-parameter standard deviations, the correlation matrix, and the parameters whose
    standard deviation exceeds `threshold` of their range (of their value, for gains and emitter
    scales) or that are not determined at all."""
    n = problem.n_material
    u = jnp.asarray(u, jnp.float32)
    half = max(spp // 2, 1)

    def rendered(spp_k: int, seed_k: int):
        """One Jacobian render, every row; a stop asked for (Ctrl-C) raises between two."""
        if stop is not None and stop():
            raise KeyboardInterrupt
        return linearised(problem, u, spp_k, seed_k, downscale)

    def render(spp_k: int, seed_k: int):
        """One Jacobian render, its finite rows."""
        return finite_rows(*rendered(spp_k, seed_k))

    if linearisation is not None:
        # a `gn` phase's two series of Jacobian renders at this resolution (the mean of its
        # refreshes, linear in the values: taken to `u`), each topped up to `half` samples
        image1, image2, j1, j2, x0, held = linearisation
        model = linear_model(problem, downscale)

        def series(image, jac_x, seed_k: int):
            r, jac = (np.asarray(a, np.float64) for a in model(u, image, jac_x, x0))
            if held >= half:
                return finite_rows(r, jac)
            r_more, jac_more = rendered(half - held, seed_k)
            share = held / half  # each sample counts once: the mean of all of them
            return finite_rows(r + (1 - share) * (r_more - r), jac + (1 - share) * (jac_more - jac))

        r1, jac1 = series(image1, j1, seed)
        r2, jac2 = series(image2, j2, seed + CROSS_SEED_OFFSET)
    else:
        r1, jac1 = render(half, seed)
        r2, jac2 = render(half, seed + CROSS_SEED_OFFSET)
    bread, undetermined = inverse_determined(cross_product(jac1, jac2))
    for k in range(1, UNDETERMINED_RETRIES + 1):
        if not undetermined.any():
            break
        # more samples where the noise hid a direction: each series the mean of its renders
        # (still independent of the other, so their cross product stays unbiased)
        more = seed + k * RETRY_SEED_OFFSET
        r3, jac3 = render(half, more)
        r4, jac4 = render(half, more + CROSS_SEED_OFFSET)
        r1, jac1 = r1 + (r3 - r1) / (k + 1), jac1 + (jac3 - jac1) / (k + 1)
        r2, jac2 = r2 + (r4 - r2) / (k + 1), jac2 + (jac4 - jac2) / (k + 1)
        bread, undetermined = inverse_determined(cross_product(jac1, jac2))
    # d(values)/du: the material's transforms, then a block for the gains (each view's gain
    # depends on every gain coordinate through the first view's)
    dxdu = transform_jacobian(problem.free, u[:n])
    if problem.gain_views:
        dxdu = block_diag(dxdu, problem.gain_jacobian(u[n:]))
    n_obs = int(np.count_nonzero(np.any((jac1 != 0) | (jac2 != 0), axis=1)))
    cov = n_obs / max(n_obs - jac1.shape[1], 1) * bread @ _meat(jac1, jac2, r1, r2) @ bread
    if trade is not None:
        r_sq = float(np.sum(np.asarray(r1, np.float64) * np.asarray(r2, np.float64)))
        sigma2 = max(r_sq, 0.0) / max(n_obs - jac1.shape[1], 1)
        cov += sigma2 * traded_inverse(trade(jac1, jac2), bread)
    if tail_gradients is not None and len(tail_gradients[0]) >= 2:
        cov += averaging_covariance(*tail_gradients, u, cross_product(jac1, jac2), bread)
    elif extra_variance is not None:
        cov[np.diag_indices_from(cov)] += np.asarray(extra_variance, np.float64)
    cov[undetermined, :] = cov[:, undetermined] = 0.0
    cov = dxdu @ cov @ dxdu.T
    # a value that depends on an undetermined coordinate is undetermined: each material value on
    # its own coordinate even where the transform's derivative is zero (a value at its bound:
    # its sd came out 0 from the zero derivative)
    depends = dxdu != 0
    depends[:n, :n] |= np.eye(n, dtype=bool)
    unknown = np.any(depends[:, undetermined], axis=1)
    cov[unknown, :] = cov[:, unknown] = 0.0
    cov[unknown, unknown] = np.inf
    std_flat = np.sqrt(np.clip(np.diag(cov), 0, None))
    with np.errstate(invalid="ignore"):  # inf / inf where undetermined: no correlation known
        corr = cov / np.maximum(np.outer(std_flat, std_flat), 1e-30)
    corr = np.where(np.isfinite(corr), corr, np.nan)
    corr[unknown, :] = corr[:, unknown] = np.nan  # unknown, not 0 ("uncorrelated")
    np.fill_diagonal(corr, 1.0)
    values = problem.values(np.asarray(u))
    std, flagged, i = {}, [], 0
    # flagged against the range, or the value itself for scale factors (log-space bounds)
    scales = [
        None if f.spec.transform == "log_sigmoid" else f.spec.upper - f.spec.lower
        for f in problem.free
    ]
    sizes = [f.size for f in problem.free] + [problem.gain_channels] * len(problem.gain_views)
    for key, size, scale in zip(
        values, sizes, scales + [None] * len(problem.gain_views), strict=True
    ):
        s = std_flat[i : i + size]
        std[key] = s.tolist() if size > 1 else float(s[0])
        reference = scale if scale is not None else np.asarray(values[key])
        if np.any(s > threshold * reference) or np.any(s == 0) or not np.all(np.isfinite(s)):
            flagged.append(key)
        i += size
    return std, corr, flagged
