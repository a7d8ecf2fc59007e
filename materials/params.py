"""One declaration per fittable value (key, default, bounds, transform, unit, doc), and per plugin
its parameters and options (integers, choices): `PLUGINS`.

Everything else (plugin defaults and validation, ``traverse`` keys, solver transforms, preset keys,
exports) is derived from these declarations. Transforms are written against an array namespace
(``numpy`` by default; the fitter passes ``jax.numpy``), so this module never imports JAX.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

Transform = Literal["sigmoid", "log_sigmoid", "clipped_sigmoid", "identity"]
Kind = Literal["float", "rgb", "texture"]

#: A fit that starts at a bound starts this share of the range inside it (DESIGN.md).
BOUND_MARGIN = 1e-3
#: A `clipped_sigmoid` value's sigmoid is widened this share of the range past either bound and
#: clipped to them, so the value reaches its bounds at a finite coordinate (a mask's texels: with
#: the plain sigmoid a texel whose truth is 0 or 1 never got there, its gradient fading with the
#: sigmoid's slope while Adam's noise stays; BENCHMARKS, "Stained objects").
OVERSHOOT = 0.05
#: `from_unconstrained` clips the solver's coordinate to +-this: beyond it a float32 sigmoid is
#: at its bound anyway, and `exp(-u)` overflowing made its derivative inf / inf (NaN) where a
#: diverged fit had walked (u = -100: every derivative of the render NaN, the fit's
#: uncertainty lost).
MAX_COORDINATE = 80.0


@dataclass(frozen=True)
class ParamSpec:
    """A fittable material parameter.

    **Arguments:**

    - `key`: name inside its plugin (`roughness`); the full key is `<layer>.<key>`.
    - `default`: value used when a config does not set it (a float, or an RGB triple).
    - `lower`, `upper`: closed bounds, per channel for RGB values.
    - `transform`: how solvers see the value unconstrained (`sigmoid` maps (lower, upper) to R;
      `log_sigmoid` does so in log space, for positive scale factors: a doubling and a halving
      are equally far from 1; `clipped_sigmoid` widens the sigmoid `OVERSHOOT` past the bounds
      and clips it there, for values that sit on them: a mask's texels).
    - `unit`: physical unit or `""`.
    - `doc`: one line for users.
    - `kind`: `float` (a scalar), `rgb` (a texture whose constant value is an RGB triple) or
      `texture` (a bitmap's texels, each bounded like a float).
    """

    key: str
    default: float | tuple[float, float, float]
    lower: float
    upper: float
    transform: Transform
    unit: str
    doc: str
    kind: Kind = "float"

    def __post_init__(self):
        if not self.lower < self.upper:
            raise ValueError(
                f"ParamSpec {self.key}: lower {self.lower} must be < upper {self.upper}"
            )
        if self.transform == "log_sigmoid" and self.lower <= 0:
            raise ValueError(f"ParamSpec {self.key}: log_sigmoid needs lower > 0")
        values = np.atleast_1d(np.asarray(self.default, dtype=float))
        if np.any(values < self.lower) or np.any(values > self.upper):
            raise ValueError(f"ParamSpec {self.key}: default {self.default} is outside the bounds")

    def check(self, value, where: str) -> None:
        """Raise a `ValueError` naming `where` and the fix when `value` is outside the bounds."""
        values = np.atleast_1d(np.asarray(value, dtype=float))
        if not np.all(np.isfinite(values)):
            raise ValueError(f"{where}: {self.key} = {value} is not finite; give a number")
        if np.any(values < self.lower) or np.any(values > self.upper):
            raise ValueError(
                f"{where}: {self.key} = {value} is outside its bounds [{self.lower}, {self.upper}]"
                f" ({self.doc}); choose a value inside them"
            )

    def to_unconstrained(self, value, xp=np):
        """Map a bounded value to the solver's unconstrained space (values at a bound move
        `BOUND_MARGIN` of the range inside it; with `clipped_sigmoid` they map to where the
        widened sigmoid crosses it)."""
        if self.transform == "identity":
            return xp.asarray(value)
        if self.transform == "log_sigmoid":
            low, high = np.log(self.lower), np.log(self.upper)
            t = (xp.log(xp.asarray(value)) - low) / (high - low)
        else:
            t = (xp.asarray(value) - self.lower) / (self.upper - self.lower)
        if self.transform == "clipped_sigmoid":
            t = (xp.clip(t, 0.0, 1.0) + OVERSHOOT) / (1.0 + 2.0 * OVERSHOOT)
        t = xp.clip(t, BOUND_MARGIN, 1.0 - BOUND_MARGIN)
        return xp.log(t) - xp.log1p(-t)

    def from_unconstrained(self, u, xp=np, stop_gradient=None):
        """Inverse of `to_unconstrained`. With `clipped_sigmoid` and a `stop_gradient` (the
        array library's, e.g. `jax.lax.stop_gradient`), the derivative passes straight through
        the clip: a value past a bound keeps its data's gradient and comes back when they ask,
        where a clipped derivative of 0 would hold it there for good."""
        if self.transform == "identity":
            return xp.asarray(u)
        u = xp.clip(xp.asarray(u), -MAX_COORDINATE, MAX_COORDINATE)
        if self.transform == "log_sigmoid":
            low, high = np.log(self.lower), np.log(self.upper)
            return xp.exp(low + (high - low) / (1.0 + xp.exp(-u)))
        t = 1.0 / (1.0 + xp.exp(-u))
        if self.transform == "clipped_sigmoid":
            wide = (1.0 + 2.0 * OVERSHOOT) * t - OVERSHOOT
            t = xp.clip(wide, 0.0, 1.0)
            if stop_gradient is not None:
                t = wide + stop_gradient(t - wide)
        return self.lower + (self.upper - self.lower) * t


def spec_table(*specs: ParamSpec) -> dict[str, ParamSpec]:
    """A plugin's declarations keyed by name, refusing duplicates."""
    table: dict[str, ParamSpec] = {}
    for spec in specs:
        if spec.key in table:
            raise ValueError(f"parameter {spec.key} is declared twice")
        table[spec.key] = spec
    return table


# Shared declarations ------------------------------------------------------------------------------

SIGMA = ParamSpec(
    "sigma",
    0.0,
    0.0,
    1.0,
    "sigmoid",
    "rad",
    "Oren-Nayar facet slope standard deviation (with diffuse = 'eon': EON's roughness in [0, 1],"
    " no unit); 0 is Lambert",
)
REFLECTANCE = ParamSpec(
    "reflectance",
    (0.5, 0.5, 0.5),
    0.0,
    1.0,
    "sigmoid",
    "",
    "diffuse albedo, linear RGB",
    kind="rgb",
)
PIGMENT = ParamSpec(
    "pigment",
    (0.5, 0.5, 0.5),
    0.0,
    1.0,
    "sigmoid",
    "",
    "colour of the pigment under the glaze, linear RGB",
    kind="rgb",
)
ROUGHNESS = ParamSpec(
    "roughness",
    0.1,
    0.002,
    1.0,
    "sigmoid",
    "",
    "Beckmann alpha of the glaze's specular lobe (other tools' roughness r maps to alpha = r^2)",
)
IOR = ParamSpec("ior", 1.5, 1.01, 3.0, "sigmoid", "", "index of refraction of the glaze coat")

PIGMENT_NOISE = ParamSpec(
    "pigment_noise",
    0.0,
    0.0,
    1.0,
    "sigmoid",
    "",
    "relative variation of the pigment with an fbm noise (0 = off, not built)",
)
NORMAL_NOISE = ParamSpec(
    "normal_noise",
    0.0,
    0.0,
    0.2,
    "sigmoid",
    "",
    "slope of the fbm perturbation of the glaze's normal (0 = off, not built)",
)
THRESHOLD = ParamSpec(
    "threshold",
    0.5,
    0.0,
    1.0,
    "sigmoid",
    "",
    "fbm level at which a mask is half on; the noise spans about [0.2, 0.8], mean 0.5",
)
SOFTNESS = ParamSpec(
    "softness",
    0.05,
    0.005,
    0.5,
    "sigmoid",
    "",
    "width of a mask's edge in fbm units (sigmoid scale)",
)
MASK_TEXTURE = ParamSpec(
    "texture",
    1.0,
    0.0,
    1.0,
    "clipped_sigmoid",
    "",
    "a mask's painted texture (linear texels; fitted texel by texel)",
    kind="texture",
)
BUMP = ParamSpec(
    "bump",
    0.0,
    0.0,
    0.01,
    "sigmoid",
    "m",
    "thickness of each masked layer as a height field (bump mapping); 0 = off, not built",
)

OREN_NAYAR_PARAMS = spec_table(REFLECTANCE, SIGMA)
GLAZE_PARAMS = spec_table(PIGMENT, SIGMA, ROUGHNESS, IOR)
#: Declared, but built only when enabled (a non-zero value in the config).
GLAZE_OPTIONAL_PARAMS = spec_table(PIGMENT_NOISE, NORMAL_NOISE)
MASK_PARAMS = spec_table(THRESHOLD, SOFTNESS)
LAYERED_PARAMS = spec_table(BUMP)

SCALE = ParamSpec(
    "scale",
    1.0,
    0.1,
    10.0,
    "log_sigmoid",
    "",
    "multiplies the emitters' radiance as configured (lights are rarely calibrated)",
)
#: Scene-side fittable values: `lights.scale` (every light, one factor) and `environment.scale`.
EMITTER_PARAMS = {"lights": SCALE, "environment": SCALE}


# Options and plugins ------------------------------------------------------------------------------


@dataclass(frozen=True)
class IntOption:
    """A structural integer option of a plugin (not differentiable), in `[lower, upper]`."""

    key: str
    default: int
    lower: int
    upper: int
    doc: str

    def check(self, value, where: str) -> int:
        """`value` as an int, or a `ValueError` naming `where` and the range."""
        number = isinstance(value, int | float) and not isinstance(value, bool)
        if (
            not number
            or value != value
            or int(min(max(value, -1e18), 1e18)) != value
            or not (self.lower <= value <= self.upper)
        ):
            raise ValueError(
                f"{where}: {self.key} = {value!r}; use an integer in [{self.lower}, {self.upper}]"
            )
        return int(value)


@dataclass(frozen=True)
class ChoiceOption:
    """A string option of a plugin; the first choice is the default."""

    key: str
    choices: tuple[str, ...]
    doc: str

    @property
    def default(self) -> str:
        return self.choices[0]

    def check(self, value, where: str) -> str:
        if value not in self.choices:
            raise ValueError(
                f"{where}: {self.key} = {value!r}; choose one of {', '.join(self.choices)}"
            )
        return value


Option = IntOption | ChoiceOption


@dataclass(frozen=True)
class PluginDecl:
    """What a plugin reads: its declared parameters and options.

    - `optional`: parameters whose zero value means "off": the plugin builds nothing for them.
    - `needs`: options that apply only when one of these parameters is on (noise scales without a
      noise are not built).
    """

    name: str
    params: dict[str, ParamSpec]
    options: dict[str, Option]
    optional: frozenset[str] = frozenset()
    needs: dict[str, tuple[str, ...]] | None = None

    def applies(self, option: str, params) -> bool:
        """Whether `option` is built given the parameter keys `params` that are on."""
        needed = (self.needs or {}).get(option)
        return needed is None or any(p in params for p in needed)


def _options(*options: Option) -> dict[str, Option]:
    return {o.key: o for o in options}


_SEED_MAX = 2**31 - 1
#: The diffuse lobe of a glaze's pigment and of an `oren_nayar` layer; `sigma` is its roughness.
DIFFUSE = ChoiceOption(
    "diffuse",
    ("qualitative", "eon"),
    "the diffuse lobe: the qualitative Oren-Nayar (sigma: facet slope in radians) or OpenPBR's "
    "energy-preserving EON (sigma: its roughness in [0, 1]; Blender's, MaterialX's)",
)
GLAZE = PluginDecl(
    "glaze",
    {**GLAZE_PARAMS, **GLAZE_OPTIONAL_PARAMS},
    _options(
        ChoiceOption(
            "coupling", ("paper", "reciprocal"), "how the specular and diffuse lobes combine"
        ),
        ChoiceOption("fresnel", ("schlick", "exact"), "Schlick's approximation or the exact one"),
        DIFFUSE,
        IntOption("pigment_noise_scale", 8, 1, 4096, "noise cells per UV unit of the pigment"),
        IntOption("normal_noise_scale", 16, 1, 4096, "noise cells per UV unit of the normal"),
        IntOption("noise_seed", 0, 0, _SEED_MAX, "seed of both noises"),
    ),
    optional=frozenset(GLAZE_OPTIONAL_PARAMS),
    needs={
        "pigment_noise_scale": ("pigment_noise",),
        "normal_noise_scale": ("normal_noise",),
        "noise_seed": ("pigment_noise", "normal_noise"),
    },
)
OREN_NAYAR = PluginDecl("oren_nayar", OREN_NAYAR_PARAMS, _options(DIFFUSE))
FBM = PluginDecl(
    "fbm",
    MASK_PARAMS,
    _options(
        IntOption("scale", 4, 1, 4096, "noise cells per UV unit (an integer: the noise tiles)"),
        IntOption("octaves", 4, 1, 12, "octaves of the fbm"),
        IntOption("seed", 0, 0, _SEED_MAX, "seed of the noise"),
    ),
)
LAYERED = PluginDecl("layered", LAYERED_PARAMS, {}, optional=frozenset(LAYERED_PARAMS))
#: The BSDFs a layer (or a whole material) can be, by type name.
LAYER_PLUGINS = {decl.name: decl for decl in (GLAZE, OREN_NAYAR)}
