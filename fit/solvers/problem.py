"""What a fit compares: the capture's views against renders of a material, as weighted,
loss-shaped residuals that solvers minimise (no Mitsuba import: renders come through the bridge,
loaded on first use)."""

from __future__ import annotations

import fnmatch
from collections.abc import Callable
from dataclasses import dataclass, field

import jax
import jax.numpy as jnp
import numpy as np

from captures.capture import Capture
from captures.errors import InputError

from ..material import Free, Material, as_dict, to_physical, to_unconstrained

LOSSES = ("l2", "huber", "cauchy")


@dataclass
class Problem:
    """What a fit compares: the capture's views against renders of `material` with `free`
    parameters, weighted by the validity weights.

    With `gains`, every view has a free gain (photos rarely share an exact exposure or white
    balance), reported as `gain.<view>`: an RGB gain (`True`: exposure and white balance), or one
    grey gain per view (`"exposure"`: one camera's fixed white balance, where free RGB gains would
    let every colour trade against three of them). The gains' geometric mean is 1 (per channel):
    the declared exposures are taken as right on average, which removes the albedo/gain
    ambiguity. (Fixing the first view's gain instead let that one view's noise set every colour's
    scale: on the cup, the other four gains moved -9.5 % together and the colours +5 to +8 %.)
    The solver's coordinates are the log-gains of every view but the first; the first's is minus
    their sum.

    `loss` shapes each pixel's difference d = render - photo before weighting: "l2" (d itself, the
    default: unbiased under Monte Carlo noise), or robust ones that count differences beyond
    `loss_scale` (default: a tenth of the photos' mean valid value) less, "huber" (linear tails)
    and "cauchy" (logarithmic). Robust losses tame outliers (specks, unmodelled reflections) but
    are biased under noise: they shrink the noisy render's large deviations asymmetrically."""

    capture: Capture
    material: Material
    free: list[Free]
    gains: bool | str = False
    loss: str = "l2"
    loss_scale: float | None = None
    _cache: dict = field(default_factory=dict, repr=False, compare=False)

    def __post_init__(self):
        if self.loss not in LOSSES:
            raise ValueError(f"loss {self.loss!r}; choose one of {', '.join(LOSSES)}")
        if self.gains not in (False, True, "exposure"):
            raise ValueError(f"gains {self.gains!r}; choose false, true or 'exposure'")

    def at(self, downscale: int) -> Capture:
        """The capture area-averaged by `downscale` (built once)."""
        key = ("capture", downscale)
        if key not in self._cache:
            self._cache[key] = self.capture.downscaled(downscale)
        return self._cache[key]

    def target(self, downscale: int = 1) -> tuple[np.ndarray, np.ndarray]:
        """(photos, sqrt of the normalised weights), flattened like the renders."""
        views = self.at(downscale).views
        image = np.concatenate([v.image.ravel() for v in views])
        weight = np.concatenate([np.repeat(v.weight.ravel(), 3) for v in views])
        return image.astype(np.float32), np.sqrt(weight / max(weight.sum() / 3, 1.0)).astype(
            np.float32
        )

    def renderer(self, downscale: int = 1):
        """The loaded scenes at a resolution, a `fit.render.Renderer` (built once: phases at the
        same resolution share kernels, whatever their spp)."""
        key = ("renderer", downscale)
        if key not in self._cache:
            from ..render import Renderer

            self._cache[key] = Renderer(self.at(downscale), self.material, self.free)
        return self._cache[key]

    def render_fn(
        self,
        mode: str,
        spp: int,
        downscale: int = 1,
        jacobian_spp: int | None = None,
        grad_spp: int | None = None,
    ):
        """`render(x, seed)` as a JAX function at this resolution (see `fit.render.make_render`)."""
        from ..render import make_render

        return make_render(self.renderer(downscale), mode, spp, jacobian_spp, grad_spp)

    def robust_scale(self) -> float:
        """The width of a robust loss, in linear image units."""
        if self.loss_scale is not None:
            return self.loss_scale
        image, sqrt_w = self.target()
        return 0.1 * float(np.sum(image * sqrt_w**2) / max(np.sum(sqrt_w**2), 1e-12))

    @property
    def n_material(self) -> int:
        return sum(f.size for f in self.free)

    @property
    def gain_views(self) -> list[int]:
        """The views with a gain: all of them, with `gains` and at least two views."""
        if not self.gains or len(self.capture.views) < 2:
            return []
        return list(range(len(self.capture.views)))

    @property
    def n_gain(self) -> int:
        """The solver's gain coordinates: the log-gains of every gained view but the first."""
        return self.gain_channels * max(len(self.gain_views) - 1, 0)

    def log_gains(self, coords, xp=np):
        """Every gained view's log-gain (views x channels) from the solver's coordinates: the
        first view's is minus the sum of the others', so that they sum to zero."""
        rest = xp.reshape(coords, (-1, self.gain_channels))
        return xp.concatenate([-xp.sum(rest, axis=0, keepdims=True), rest])

    def gain_coordinates(self, log_gains) -> np.ndarray:
        """The solver's coordinates for per-view log-gains (flattened views x channels): their
        mean over views is removed (the gauge), then the first view's dropped."""
        table = np.reshape(np.asarray(log_gains, np.float64), (-1, self.gain_channels))
        return (table - table.mean(axis=0))[1:].ravel().astype(np.float32)

    def gain_jacobian(self, coords) -> np.ndarray:
        """d(gains)/d(coordinates): (views x channels) x `n_gain`."""
        c, n_views = self.gain_channels, len(self.gain_views)
        sums = np.vstack([-np.tile(np.eye(c), (1, n_views - 1)), np.eye(c * (n_views - 1))])
        gains = np.exp(self.log_gains(np.asarray(coords, np.float64)).ravel())
        return gains[:, None] * sums

    @property
    def gain_channels(self) -> int:
        """Components of each view's gain: 3 (RGB) or 1 (exposure)."""
        return 1 if self.gains == "exposure" else 3

    def unconstrained(self, start: dict):
        """The solver's starting vector: material parameters, then log-gains (0: gain 1)."""
        return np.concatenate(
            [
                to_unconstrained(self.free, start),
                np.zeros(self.n_gain),
            ]
        ).astype(np.float32)

    def held(self, patterns) -> np.ndarray:
        """1 for each solver coordinate of a material key matching one of `patterns` (keys or
        fnmatch patterns), else 0; a pattern matching no free key is an error."""
        mask, i = np.zeros(self.n_material + self.n_gain, np.int8), 0
        hits = dict.fromkeys(patterns, False)
        for f in self.free:
            for p in patterns:
                if fnmatch.fnmatchcase(f.key, p):
                    mask[i : i + f.size], hits[p] = 1, True
            i += f.size
        if missing := [p for p, hit in hits.items() if not hit]:
            keys = ", ".join(f.key for f in self.free)
            raise InputError(
                f"hold: {', '.join(map(repr, missing))} matches no free parameter; hold some of "
                f"fit.free ({keys})"
            )
        return mask

    def values(self, u) -> dict:
        u = np.asarray(u, dtype=np.float64)
        out = as_dict(self.free, to_physical(self.free, u[: self.n_material]))
        if self.gain_views:
            gains = np.exp(self.log_gains(u[self.n_material :]))
            for view, gain in zip(self.gain_views, gains, strict=True):
                name = f"gain.{self.capture.views[view].name}"
                out[name] = gain.tolist() if gain.size > 1 else float(gain[0])
        return out

    @property
    def textures(self) -> list[str]:
        """The free parameters that are textures (texel by texel)."""
        return [f.key for f in self.free if f.shape]

    def holding_textures(self, u) -> tuple[Problem, Callable, Callable]:
        """The problem of the scalars (and gains) with every texture held at its value in `u`:
        (that problem, `take(u)` its coordinates of a full vector, `put(u, v)` the full vector
        with them replaced). Forward-mode solvers and the uncertainty render one image per
        coordinate, and none through a bitmap's texels (`forward_mode_refusal`): they move the
        scalars while the textures, fitted by Adam, are held."""
        from ..material.textures import cached_texture

        values = self.values(u)
        kept = [f for f in self.free if not f.shape]
        if not kept:
            raise InputError(
                "every free parameter is a texture: no scalar for gn, lm or bfgs to move; fit "
                "textures with adam phases only"
            )
        files = {
            f.key: cached_texture(np.asarray(values[f.key], np.float32).reshape(f.shape), f.key)
            for f in self.free
            if f.shape
        }
        material = self.material.with_values(values).with_textures(files)
        held = Problem(self.capture, material, kept, self.gains, self.loss, self.loss_scale)
        index, i = [], 0
        for f in self.free:
            if not f.shape:
                index.extend(range(i, i + f.size))
            i += f.size
        index = np.asarray(index + list(range(i, i + self.n_gain)), np.int64)

        def take(full):
            return np.asarray(full, np.float32)[index]

        def put(full, part):
            out = np.array(full, np.float32)
            out[index] = np.asarray(part, np.float32)
            return out

        return held, take, put

    def gain_multipliers(self, log_gains, downscale: int = 1):
        """Per-element multipliers of the flattened views from the solver's gain coordinates."""
        views = self.at(downscale).views
        gains = jnp.exp(self.log_gains(log_gains, jnp)).astype(jnp.float32)
        parts = [
            jnp.tile(gain, views[view].image.size // self.gain_channels)
            for view, gain in zip(self.gain_views, gains, strict=True)
        ]
        return jnp.concatenate(parts)


def shape_loss(d, loss: str, scale: float):
    """The loss as a residual transform psi(d) with psi^2 / 2 = rho(d): smooth, psi(d) ~ d near 0
    (so least-squares solvers take robust losses too)."""
    if loss == "l2":
        return d
    x = d / scale
    x2 = x * x
    if loss == "huber":  # rho = x^2/2 inside, |x| - 1/2 outside
        safe = jnp.maximum(jnp.abs(x), 1.0)
        return jnp.where(jnp.abs(x) <= 1.0, d, jnp.sign(d) * scale * jnp.sqrt(2 * safe - 1))
    # cauchy: rho = log(1 + x^2) / 2; psi = x sqrt(log1p(x^2) / x^2), the ratio -> 1 at 0
    ratio = jnp.where(x2 > 1e-6, jnp.log1p(x2) / jnp.maximum(x2, 1e-6), 1.0 - x2 / 2)
    return d * jnp.sqrt(ratio)


#: With `independent_gains`, the gains' derivatives use a second render with the seed plus this
#: offset (far from `GRAD_SEED_OFFSET` and from a schedule's consecutive seeds).
GAIN_SEED_OFFSET = 0xB10C5
#: `noise_ratio`'s two renders use the seed plus this and one more.
NOISE_SEED_OFFSET = 0x0A7105


def jax_seed(seed: int) -> jax.Array:
    """A render seed as the int32 scalar the bridge takes: `seed` modulo 2^32, signed. The
    renderer takes its seeds modulo 2^32 (`Renderer._seed`), so it renders the same samples as
    `seed` itself; and the seeds derived from a fit's (a step's `seed * 100003 + i + 1`) never
    overflow int32 (they did from `fit.seed = 21475` on: an internal error)."""
    return jnp.int32((int(seed) + 2**31) % 2**32 - 2**31)


def residuals(
    problem: Problem,
    render,
    downscale: int = 1,
    independent_gains: bool = False,
    profile_gains: bool = False,
):
    """`residual(u, seed)`: the weighted, loss-shaped differences of `render(x, seed)` (a JAX
    function of the physical values) from the photos.

    A gain g's derivative of the loss is sum(w (g I - T) I) over its view and channel: with the
    same noisy image I in both factors its zero sits at g = T E[I] / E[I^2], biased low by the
    render's relative variance (measured -33 % at 8 spp on the glazed sphere's highlights). With
    `independent_gains` the derivative's second factor is an independent render I' (same value of
    the residual, derivative sum(w (g I - T) I'), zero at the unbiased T / E[I]); it costs one
    more primal render per evaluation, for solvers whose fixed point is a zero of an expected
    gradient (Adam with fresh seeds, LM with a decorrelated Jacobian).

    With `profile_gains` the gains in `u` are held fixed (no derivative) and each evaluation also
    returns the sums of their weighted least-squares solution per view and channel,
    `(sum(w T I'), sum(w I I'))` with the independent render I': `residual(u, seed)` returns
    `(residual, (num, den))`. A solver sets the gains to `num / den` between steps, their
    geometric mean divided out (`Problem.gain_coordinates`; variable projection: the material then
    descends the loss with the gains at their best, and gains and colours cannot trade along a
    shallow valley); summing them over steps before dividing keeps the ratio's own noise bias
    small.
    """
    target, sqrt_w = (jnp.asarray(a) for a in problem.target(downscale))
    n, loss, scale = problem.n_material, problem.loss, problem.robust_scale()
    independent = independent_gains and bool(problem.gain_views)
    profile = profile_gains and bool(problem.gain_views)
    if profile:
        segments, n_segments = _gain_segments(problem, downscale)
        weight = sqrt_w * sqrt_w
    plain = image_residual(problem, downscale)

    def residual(u, seed):
        x = to_physical(problem.free, u[:n], jnp)
        image = render(x, seed)
        if profile:
            other = jax.lax.stop_gradient(render(jax.lax.stop_gradient(x), seed + GAIN_SEED_OFFSET))
            fixed = jax.lax.stop_gradient(image)
            num = jax.ops.segment_sum(weight * target * other, segments, n_segments)
            den = jax.ops.segment_sum(weight * fixed * other, segments, n_segments)
            gain = jax.lax.stop_gradient(problem.gain_multipliers(u[n:], downscale))
            return sqrt_w * shape_loss(image * gain - target, loss, scale), (num, den)
        if independent:
            gain = problem.gain_multipliers(u[n:], downscale)
            other = jax.lax.stop_gradient(render(jax.lax.stop_gradient(x), seed + GAIN_SEED_OFFSET))
            fixed = jax.lax.stop_gradient(gain)
            image = fixed * image + (gain - fixed) * other  # value: gain * image
            return sqrt_w * shape_loss(image - target, loss, scale)
        return plain(u, image)

    return residual


def image_residual(problem: Problem, downscale: int = 1):
    """`residual(u, image)`: `residuals`' residual of a rendered `image` at the solver's `u`,
    the gains' derivative through that image."""
    target, sqrt_w = (jnp.asarray(a) for a in problem.target(downscale))
    n, loss, scale = problem.n_material, problem.loss, problem.robust_scale()

    def residual(u, image):
        if problem.gain_views:
            image = image * problem.gain_multipliers(u[n:], downscale)
        return sqrt_w * shape_loss(image - target, loss, scale)

    return residual


def _gain_segments(problem: Problem, downscale: int) -> tuple[jnp.ndarray, int]:
    """Each flattened element's gain: c i + channel for the i-th view with a gain of c components
    (channel 0 for a grey gain)."""
    views, c = problem.at(downscale).views, problem.gain_channels
    parts = [
        c * i + np.arange(views[view].image.size, dtype=np.int32) % c
        for i, view in enumerate(problem.gain_views)
    ]
    return jnp.asarray(np.concatenate(parts)), c * len(problem.gain_views)


def noise_ratio(problem: Problem, u, spp: int, seed: int, downscale: int = 1) -> float:
    """How much of the residual at `u` is the render's own Monte Carlo noise at `spp`: from two
    renders with independent seeds, the weighted squared difference's half (that noise) over
    the rest of the mean residual's square (the photos' noise, unmodelled differences, the
    parameters' error); infinite where the rest is not positive."""
    renderer = problem.renderer(downscale)

    def render(x, s):
        return jnp.asarray(renderer.render(np.asarray(x, np.float32), int(s), spp))

    residual = residuals(problem, render, downscale)
    u = jnp.asarray(u, jnp.float32)
    r1, r2 = (
        np.asarray(residual(u, seed + k), np.float64)
        for k in (NOISE_SEED_OFFSET, NOISE_SEED_OFFSET + 1)
    )
    noise = 0.5 * float(np.sum((r1 - r2) ** 2))
    rest = float(np.sum((0.5 * (r1 + r2)) ** 2)) - 0.5 * noise
    return noise / rest if rest > 0 else float("inf")
