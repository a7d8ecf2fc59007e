"""Stability over the whole declared range: every parameter of every plugin (from
`materials.params`) at its lower bound, just inside it (`BOUND_MARGIN`), just inside its upper bound
and at it, with the other parameters mid-range, at grazing and normal incidence and exitance.
Values, sample weights and forward-mode derivatives are finite, and wherever a central finite
difference is clearly non-zero the AD derivative is not zero and agrees with it (noise-free)."""

from __future__ import annotations

import itertools

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest
from bsdf_checks import direction, hemisphere, interaction, rgb, vec

from materials.params import (
    BOUND_MARGIN,
    EMITTER_PARAMS,
    FBM,
    GLAZE,
    LAYERED,
    OREN_NAYAR,
    ChoiceOption,
    ParamSpec,
    PluginDecl,
)

#: cos(theta) of the grazing directions (incident and outgoing).
GRAZING = 1e-3


def levels(spec: ParamSpec) -> dict[str, float]:
    """The four tested values: at each bound and `BOUND_MARGIN` of the range inside it (in the
    transform's space: log for `log_sigmoid`), where a fit started at a bound begins."""
    if spec.transform == "log_sigmoid":
        low, high = np.log(spec.lower), np.log(spec.upper)
        inside = np.exp([low + BOUND_MARGIN * (high - low), high - BOUND_MARGIN * (high - low)])
    else:
        span = spec.upper - spec.lower
        inside = [spec.lower + BOUND_MARGIN * span, spec.upper - BOUND_MARGIN * span]
    return {
        "lower": spec.lower,
        "lower+margin": float(inside[0]),
        "upper-margin": float(inside[1]),
        "upper": spec.upper,
    }


def mid(spec: ParamSpec):
    """A mid-range value (an RGB triple with distinct channels for `rgb` parameters)."""
    span = spec.upper - spec.lower
    if spec.kind == "rgb":
        return [spec.lower + f * span for f in (0.3, 0.5, 0.7)]
    return spec.lower + 0.3 * span


def prop(spec: ParamSpec, value):
    """`value` as a plugin property (an `rgb` texture for RGB parameters)."""
    if spec.kind == "rgb":
        return {"type": "rgb", "value": list(np.broadcast_to(value, 3).astype(float))}
    return float(value)


def plugin_dict(decl: PluginDecl, values: dict | None = None, **options) -> dict:
    """`decl`'s plugin with its parameters mid-range, optional ones off, unless `values` sets
    them (texture-valued parameters keep their defaults)."""
    props = {"type": decl.name, **options}
    for key, spec in decl.params.items():
        if spec.kind == "texture":
            continue
        if key in (values or {}):
            props[key] = prop(spec, values[key])
        elif key not in decl.optional:
            props[key] = prop(spec, mid(spec))
    return props


def choice_variants(decl: PluginDecl) -> list[dict]:
    """Every combination of the plugin's choice options."""
    choices = [o for o in decl.options.values() if isinstance(o, ChoiceOption)]
    return [
        {o.key: c for o, c in zip(choices, combo, strict=True)}
        for combo in itertools.product(*(o.choices for o in choices))
    ]


def directions() -> tuple[np.ndarray, np.ndarray]:
    """(wi, wo) rows: incidence at cos 1e-3, 0.5 and 1; exitance spread over the hemisphere, at
    cos 1e-3 in several azimuths and around the mirror direction (a sharp lobe's peak)."""
    rng = np.random.default_rng(7)
    wis, wos = [], []
    for cos_i in (GRAZING, 0.5, 1.0):
        wi = direction(np.degrees(np.arccos(cos_i)), 20.0)
        mirror = wi * np.array([-1, -1, 1])
        near = mirror + rng.normal(scale=0.02, size=(16, 3))
        near[:, 2] = np.abs(near[:, 2]) + GRAZING
        near /= np.linalg.norm(near, axis=1, keepdims=True)
        grazing = direction(np.degrees(np.arccos(GRAZING)), [0.0, 90.0, 160.0, 200.0, 300.0])
        wo = np.concatenate([hemisphere(96, seed=8), [mirror], near, grazing])
        wis.append(np.repeat(wi[None], len(wo), axis=0))
        wos.append(wo)
    return np.concatenate(wis), np.concatenate(wos)


#: The four levels of `levels`, each in its own block of lanes: one kernel tests all of them.
LEVELS = ("lower", "lower+margin", "upper-margin", "upper")
WI1, WO1 = directions()
N = len(WI1)
WI, WO = np.tile(WI1, (len(LEVELS), 1)), np.tile(WO1, (len(LEVELS), 1))
RNG = np.random.default_rng(9)
UV, P = np.tile(RNG.random((N, 2)), (4, 1)), np.tile(RNG.normal(size=(N, 3)), (4, 1))


def surface() -> mi.SurfaceInteraction3f:
    return interaction(WI, uv=UV, p=P)


def step(spec: ParamSpec, value: float) -> float:
    """Finite-difference step: a thousandth of the range, and at most a hundredth of the value for
    positive parameters (alpha and softness scale a lobe or an edge). ior acts through ior - 1
    and, at grazing angles, by a few float32 ulps per 1e-3 (F ~ 0.999): half its distance to 1,
    at most 0.01."""
    h = 1e-3 * (spec.upper - spec.lower)
    if spec.key == "ior":
        return min(0.01, (value - 1.0) / 2)
    if spec.lower > 0:
        h = min(h, 0.01 * value)
    return h


def lanes(values) -> np.ndarray:
    """One value per level, repeated over that level's block of lanes."""
    return np.repeat(np.asarray(values, dtype=float), N)


def set_lanes(bsdf, key: str, values: np.ndarray, grad: bool = False):
    """Set parameter `key` to a value per lane (every channel alike for RGB); with `grad`, with
    a unit tangent (forward mode). Returns the parameter as set."""
    params = mi.traverse(bsdf)
    x = mi.Float(values.astype(np.float32))
    x = mi.Color3f(x, x, x) if isinstance(params[key], mi.Color3f) else x
    if grad:
        dr.enable_grad(x)
    params[key] = x
    params.update()
    if grad:
        dr.set_grad(params[key], 1.0)
    return params[key]


def derivatives(bsdf, key: str, values: np.ndarray, steps: np.ndarray, fn, richardson=True):
    """(AD, FD, FD rounding error) per lane of `fn(bsdf)`: forward-mode AD along `key` (all
    channels together) and a central difference with per-lane `steps` (Richardson-extrapolated
    from `steps` and `steps / 2`, truncation O(h^4), unless not `richardson`)."""
    set_lanes(bsdf, key, values, grad=True)
    out = fn(bsdf)
    dr.forward_to(out)
    ad = rgb(dr.grad(out))
    set_lanes(bsdf, key, values)
    ks = (-2, -1, 1, 2) if richardson else (-2, 2)
    at = {}
    for k in ks:
        set_lanes(bsdf, key, values + k * steps / 2)
        at[k] = rgb(fn(bsdf)).astype(np.float64)
    set_lanes(bsdf, key, values)
    h = steps[:, None]
    fd = (at[2] - at[-2]) / (2 * h)
    if richardson:
        fd = (4 * (at[1] - at[-1]) / h - fd) / 3
    size = np.max(np.abs(np.stack(list(at.values()))), axis=0)
    return ad, fd, 3 * 64 * np.finfo(np.float32).eps * size / h


def check_derivative(ad, fd, rounding, what: str, must_depend: bool) -> None:
    """AD finite; where |FD| is clearly non-zero (ten times its error bound), AD is not zero and
    agrees within 5 % (98 % of the rows: a few sit on kinks of min/max/clip, where a central
    difference straddles two branches)."""
    assert np.all(np.isfinite(ad)), f"{what}: non-finite derivative"
    assert np.all(np.isfinite(fd)), f"{what}: non-finite value near it"
    noise = rounding + 1e-5 * np.abs(fd).max() + 1e-9
    clear = np.abs(fd) > 10 * noise
    if must_depend:
        assert clear.any(), f"{what}: the value does not depend on it (max |FD| {np.abs(fd).max()})"
    if not clear.any():
        return
    silent = clear & (ad == 0)
    assert silent.sum() <= 0.02 * clear.sum(), (
        f"{what}: AD is zero at {silent.sum()} of {clear.sum()} entries where FD is not, e.g. FD "
        f"{fd[silent][:3]}"
    )
    bad = clear & (np.abs(ad - fd) > 0.05 * np.abs(fd) + noise)
    rows = bad.reshape(len(bad), -1).any(axis=1)
    assert rows.mean() <= 0.02, (
        f"{what}: {rows.sum()} of {len(rows)} rows differ, e.g. AD {ad[bad][:3]} vs FD "
        f"{fd[bad][:3]}"
    )


def check_bsdf(bsdf, key: str, spec: ParamSpec, fn, what: str, steps=None, light=False):
    """At every level of `spec` (lane blocks): eval and sample finite, the sample weight's
    derivative finite, and AD against FD (`check_derivative`); the value must depend on the
    parameter just inside its bounds. `light` (for the costly stacks): a plain central
    difference, and no derivative of the sample weight."""
    values = lanes(list(levels(spec).values()))
    set_lanes(bsdf, key, values)
    ctx, si = mi.BSDFContext(), surface()
    assert np.all(np.isfinite(rgb(bsdf.eval(ctx, si, vec(WO))))), f"{what}: eval"
    rng = np.random.default_rng(10)
    n = len(WI)
    s1 = mi.Float(rng.random(n, dtype=np.float32))
    s2 = mi.Point2f(rng.random(n, dtype=np.float32), rng.random(n, dtype=np.float32))
    bs, weight = bsdf.sample(ctx, si, s1, s2)
    assert np.all(np.isfinite(rgb(weight))), f"{what}: sample weight"
    assert np.all(np.isfinite(np.asarray(bs.pdf))), f"{what}: sample pdf"
    if not light:
        set_lanes(bsdf, key, values, grad=True)
        _, weight = bsdf.sample(ctx, si, s1, s2)
        dr.forward_to(weight)
        assert np.all(np.isfinite(rgb(dr.grad(weight)))), f"{what}: sample weight derivative"
        set_lanes(bsdf, key, values)
    if steps is None:
        steps = lanes([step(spec, v) for v in levels(spec).values()])
    ad, fd, rounding = derivatives(bsdf, key, values, steps, fn, richardson=not light)
    for i, level in enumerate(LEVELS):
        block = slice(i * N, (i + 1) * N)
        where = f"{what} {level} ({values[i * N]:.6g})"
        check_derivative(ad[block], fd[block], rounding[block], where, "margin" in level)


def eval_fn(bsdf):
    return bsdf.eval(mi.BSDFContext(), surface(), vec(WO))


def traverse_key(spec: ParamSpec) -> str:
    return f"{spec.key}.value" if spec.kind == "rgb" else spec.key


def layer_cases(decl: PluginDecl, slow_variants: bool):
    """Every choice variant's parameters; with `slow_variants`, only the defaults and the EON
    diffuse lobe (a model of its own, not a variant of one formula) in the default run."""
    variants = choice_variants(decl)
    fast = [variants[0]]
    if "diffuse" in decl.options:
        fast.append({**variants[0], "diffuse": "eon"})
    for variant in variants:
        marks = [pytest.mark.slow] if variant not in fast and slow_variants else []
        for spec in decl.params.values():
            if spec.kind != "texture":
                name = "-".join([decl.name, *variant.values(), spec.key])
                yield pytest.param(decl, variant, spec, id=name, marks=marks)


@pytest.mark.parametrize(
    "decl, variant, spec",
    [case for decl in (GLAZE, OREN_NAYAR) for case in layer_cases(decl, slow_variants=True)],
)
def test_layer_bsdf_at_bounds(decl, variant, spec):
    """A layer BSDF (glaze, oren_nayar) with one parameter at and next to its bounds (RGB ones
    black or white in every channel), the others mid-range. Optional parameters are built
    whenever given, 0 included (a config leaves them out at 0). The default choice options run
    by default (and the EON diffuse lobe), the other combinations in the slow run."""
    bsdf = mi.load_dict(plugin_dict(decl, {spec.key: spec.default}, **variant))
    check_bsdf(bsdf, traverse_key(spec), spec, eval_fn, f"{decl.name} {variant} {spec.key}")


def stack(mask: dict | None = None, bump: float | None = None) -> dict:
    """A two-layer `layered` stack: an oren_nayar base under a glaze masked by an `fbm`."""
    props = {
        "type": LAYERED.name,
        "layers": "base,coat",
        "base": plugin_dict(OREN_NAYAR),
        "coat": plugin_dict(GLAZE),
        "coat_mask": plugin_dict(FBM, mask),
    }
    if bump is not None:
        props["bump"] = bump
    return props


def shares_fn(bsdf):
    base, coat = bsdf.shares(surface())
    return mi.Color3f(base, coat, coat)


@pytest.mark.parametrize("spec", list(FBM.params.values()), ids=list(FBM.params))
def test_mask_at_bounds(spec):
    """An fbm mask parameter at and next to its bounds in a stack: the shares (through which the
    masks act; the per-interaction layer choice is piecewise constant by design) differentiate
    like FD, and eval stays finite with finite derivatives."""
    bsdf = mi.load_dict(stack())
    key = f"coat.mask.{spec.key}"
    check_bsdf(bsdf, key, spec, shares_fn, f"fbm {spec.key}", light=True)
    set_lanes(bsdf, key, lanes(list(levels(spec).values())), grad=True)
    out = eval_fn(bsdf)
    dr.forward_to(out)
    assert np.all(np.isfinite(rgb(dr.grad(out)))), spec.key


def test_masks_at_zero_and_one():
    """Threshold at each bound with the sharpest softness saturates the mask (shares 0 and 1):
    every value and derivative is finite, and the parameters of the layer the mask shows still
    act (reverse mode: one backward pass gives every parameter's derivative of the sum)."""
    threshold, softness = FBM.params["threshold"], FBM.params["softness"]
    bump = LAYERED.params["bump"].upper
    for level, t in ((0.0, threshold.upper), (1.0, threshold.lower)):
        bsdf = mi.load_dict(stack({"threshold": t, "softness": softness.lower}, bump=bump))
        coat = np.asarray(bsdf.shares(surface())[1])
        np.testing.assert_allclose(coat, level, atol=1e-6)
        layer, decl = ("coat", GLAZE) if level == 1 else ("base", OREN_NAYAR)
        shown = [
            f"{layer}.{traverse_key(s)}" for s in decl.params.values() if s.key not in decl.optional
        ]
        params = mi.traverse(bsdf)
        keys = [f"coat.mask.{k}" for k in FBM.params] + ["bump"] + shown
        for key in keys:
            dr.enable_grad(params[key])
        params.update()
        out = eval_fn(bsdf)
        assert np.all(np.isfinite(rgb(out)))
        dr.backward(dr.sum(dr.sum(out)))
        grads = {key: np.ravel(dr.grad(params[key])) for key in keys}
        for key in keys:
            dr.disable_grad(params[key])
        params.update()
        for key, grad in grads.items():
            assert np.all(np.isfinite(grad)), key
            if key in shown:
                assert np.abs(grad).max() > 1e-4, f"{key}: no gradient from the shown layer"


def test_bump_at_bounds():
    """The stack's bump at and next to its bounds, at grazing angles, where the bent normal puts
    directions below its horizon. The FD step is 3 % of the range away from 0: at cos 1e-3 the
    bent frame's incident cosine loses most of its float32 digits to cancellation, and smaller
    steps measure that rounding (measured at bump 0.01: with steps of 1e-5 up to 15 % of the rows
    disagree, with 3e-4 about 1 %: AD is right). At 0 (and 1e-5) a step that size would tilt
    grazing directions across the horizon, where the value jumps: there it is 1e-5."""
    spec = LAYERED.params["bump"]
    bsdf = mi.load_dict(stack({"softness": 0.1, "threshold": 0.5}, bump=spec.default))
    values = list(levels(spec).values())
    steps = lanes(
        [1e-3 * spec.upper if v < 0.03 * spec.upper else 0.03 * spec.upper for v in values]
    )
    check_bsdf(bsdf, "bump", spec, eval_fn, "bump", steps=steps, light=True)


ALL_SPECS = {
    f"{decl.name}.{key}": spec
    for decl in (GLAZE, OREN_NAYAR, FBM, LAYERED)
    for key, spec in decl.params.items()
} | {f"{name}.scale": spec for name, spec in EMITTER_PARAMS.items()}


@pytest.mark.parametrize("spec", list(ALL_SPECS.values()), ids=list(ALL_SPECS))
def test_transform_at_bounds(spec):
    """A solver's view of every declared parameter (emitter scales included): a value at a
    bound maps to `BOUND_MARGIN` inside it, finitely, and the slope d value / d u there is
    finite and non-zero (a start at the bound is not stuck)."""
    for level, value in levels(spec).items():
        u = spec.to_unconstrained(value)
        assert np.isfinite(u), (spec.key, level)
        back = spec.from_unconstrained(u)
        expected = levels(spec)["lower+margin" if level == "lower" else "upper-margin"]
        expected = expected if level in ("lower", "upper") else value
        np.testing.assert_allclose(back, expected, rtol=1e-9, err_msg=f"{spec.key} {level}")
        h = 1e-6
        slope = (spec.from_unconstrained(u + h) - spec.from_unconstrained(u - h)) / (2 * h)
        assert np.isfinite(slope) and slope > 1e-4 * BOUND_MARGIN * (spec.upper - spec.lower)
