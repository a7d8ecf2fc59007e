"""Derivatives on the BSDFs alone (noise-free): AD equals central finite differences for every
declared parameter, and every parameter stays finite and differentiable at its extremes."""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest
from bsdf_checks import (
    ad_and_fd,
    ad_derivative,
    assert_derivative,
    direction,
    hemisphere,
    interaction,
    rgb,
    set_param,
    vec,
)

from materials.params import BOUND_MARGIN, GLAZE_PARAMS, OREN_NAYAR_PARAMS

MID = {
    "sigma": 0.3,
    "roughness": 0.3,
    "ior": 1.5,
    "pigment": [0.3, 0.5, 0.7],
    "reflectance": [0.3, 0.5, 0.7],
}


def traverse_key(spec) -> str:
    return f"{spec.key}.value" if spec.kind == "rgb" else spec.key


def derivatives(bsdf, spec, value, fn, h):
    """[(channel, AD, FD, FD rounding error)] for each channel of the parameter."""
    channels = range(3) if spec.kind == "rgb" else [None]
    return [(c, *ad_and_fd(bsdf, traverse_key(spec), value, fn, h, c)) for c in channels]


def make(kind: str, **options) -> mi.BSDF:
    """A BSDF with every declared parameter mid-range unless `options` sets it."""
    props = {"type": kind}
    for spec in (GLAZE_PARAMS if kind == "glaze" else OREN_NAYAR_PARAMS).values():
        value = MID[spec.key]
        props[spec.key] = {"type": "rgb", "value": value} if spec.kind == "rgb" else value
    return mi.load_dict({**props, **options})


def eval_fn(wi, wo):
    si, wo = interaction(wi), vec(wo)
    return lambda bsdf: bsdf.eval(mi.BSDFContext(), si, wo)


BSDFS = {
    "oren_nayar": ("oren_nayar", {}),
    **{
        f"glaze-{c}-{f}": ("glaze", {"coupling": c, "fresnel": f})
        for c in ("paper", "reciprocal")
        for f in ("schlick", "exact")
    },
}


def params_of(kind):
    return (GLAZE_PARAMS if kind == "glaze" else OREN_NAYAR_PARAMS).values()


@pytest.mark.parametrize("name", list(BSDFS))
def test_ad_matches_finite_differences(name):
    kind, options = BSDFS[name]
    bsdf = make(kind, **options)
    wi, wo = hemisphere(512, seed=21, min_cos=0.02), hemisphere(512, seed=22, min_cos=0.02)
    fn = eval_fn(wi, wo)
    for spec in params_of(kind):
        for channel, ad, fd, rounding in derivatives(bsdf, spec, MID[spec.key], fn, h=1e-3):
            what = f"{name} {spec.key} channel {channel}"
            assert np.abs(fd).max() > 1e-4, f"{what}: the value does not depend on it here"
            assert_derivative(ad, fd, rounding, 1e-2, what)


def extreme_directions():
    """Incident directions at cos(theta) 1e-4 and 1; outgoing ones spread over the hemisphere, at
    grazing, and around the mirror direction (where a sharp lobe lives)."""
    wis, wos = [], []
    rng = np.random.default_rng(31)
    for cos_i in (1e-4, 1.0):
        wi = direction(np.degrees(np.arccos(cos_i)), 20.0)
        mirror = wi * np.array([-1, -1, 1])
        near = mirror + rng.normal(scale=0.02, size=(64, 3))
        near[:, 2] = np.abs(near[:, 2]) + 1e-3
        near /= np.linalg.norm(near, axis=1, keepdims=True)
        wo = np.concatenate(
            [
                hemisphere(128, seed=32),
                [mirror],
                near,
                direction(np.degrees(np.arccos(1e-4)), [0.0, 90.0, 200.0]),
            ]
        )
        wis.append(np.repeat(wi[None], len(wo), axis=0))
        wos.append(wo)
    return np.concatenate(wis), np.concatenate(wos)


EXTREMES = [
    ("roughness", 0.01),
    ("roughness", 1.0),
    ("ior", 1.01),
    ("ior", 3.0),
    ("sigma", 0.0),
    ("sigma", 1.0),
    ("pigment", [0.0, 0.0, 0.0]),
    ("pigment", [1.0, 1.0, 1.0]),
]


@pytest.mark.parametrize("name", [n for n in BSDFS if n.startswith("glaze")])
@pytest.mark.parametrize("key, value", EXTREMES, ids=[f"{k}={v}" for k, v in EXTREMES])
def test_glaze_extremes(name, key, value):
    """One parameter at a bound, the others mid-range: eval, sample weights and all derivatives
    finite; each derivative agrees with finite differences, so it is not silently zero."""
    _, options = BSDFS[name]
    bsdf = make(
        "glaze", **{**options, key: {"type": "rgb", "value": value} if key == "pigment" else value}
    )
    check_extreme(bsdf, GLAZE_PARAMS, {**MID, key: value})


@pytest.mark.parametrize("value", [0.0, 1.0])
@pytest.mark.parametrize("reflectance", [[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]])
def test_oren_nayar_extremes(value, reflectance):
    bsdf = make("oren_nayar")
    set_param(bsdf, "sigma", value)
    set_param(bsdf, "reflectance.value", reflectance)
    check_extreme(bsdf, OREN_NAYAR_PARAMS, {**MID, "sigma": value, "reflectance": reflectance})


def check_extreme(bsdf, specs, values):
    wi, wo = extreme_directions()
    fn = eval_fn(wi, wo)
    assert np.all(np.isfinite(rgb(fn(bsdf))))

    rng = np.random.default_rng(41)
    n = len(wi)
    s1 = mi.Float(rng.random(n, dtype=np.float32))
    s2 = mi.Point2f(rng.random(n, dtype=np.float32), rng.random(n, dtype=np.float32))
    si = interaction(wi)
    ctx = mi.BSDFContext()
    bs, weight = bsdf.sample(ctx, si, s1, s2)
    assert np.all(np.isfinite(rgb(weight))) and np.all(np.isfinite(np.asarray(bs.pdf)))
    sampled_wo = dr.detach(bs.wo)
    pdf = np.asarray(bs.pdf)[:, None]
    # sigma changes nothing at 0 (the Oren-Nayar terms are even in it) or under a black colour
    colour = values["pigment" if any(s.key == "pigment" for s in specs.values()) else "reflectance"]
    flat = {"sigma"} if values.get("sigma") == 0 or not np.any(colour) else set()

    for spec in specs.values():
        value = values[spec.key]
        # Steps: relative for alpha (lobe widths scale with it); larger for ior, whose effect at
        # grazing angles (F ~ 0.9994 at cos 1e-4) is a few float32 ulps per 1e-3, but never down
        # to ior 1, where the exact Fresnel term jumps to 0 at grazing angles
        h = 1e-3 * (spec.upper - spec.lower)
        if spec.key == "roughness":
            h = 0.01 * value
        elif spec.key == "ior":
            h = min(0.01, (value - 1.0) / 2)
        depends = False
        for channel, ad, fd, rounding in derivatives(bsdf, spec, value, fn, h):
            where = f"{spec.key} channel {channel} at {values}"
            assert_derivative(ad, fd, rounding, 3e-2, where)
            depends |= bool(np.any(np.abs(fd) > 10 * (rounding + 1e-12)))
            if spec.key in flat:  # no dependence to find: AD must say so too
                assert np.abs(ad).max() <= 1e-6, f"{where}: AD {np.abs(ad).max()} where none"
            # the sample weight's derivative is eval's derivative over the (detached) pdf
            key = traverse_key(spec)
            ad_w = ad_derivative(bsdf, key, value, lambda b: b.sample(ctx, si, s1, s2)[1], channel)
            ad_e = ad_derivative(bsdf, key, value, lambda b: b.eval(ctx, si, sampled_wo), channel)
            assert np.all(np.isfinite(ad_w)), where
            ok = pdf[:, 0] > 0
            np.testing.assert_allclose(
                ad_w[ok],
                ad_e[ok] / pdf[ok],
                rtol=1e-3,
                atol=1e-5 * (np.abs(ad_w).max() + 1e-12),
                err_msg=where,
            )
        # not silently zero: where the value depends on the parameter, FD shows it (and AD agrees)
        assert depends or spec.key in flat, f"{spec.key} at {values}: no dependence found"


@pytest.mark.parametrize("kind", ["oren_nayar", "glaze"])
def test_sigma_gradient_at_fit_start(kind):
    """d f / d sigma is exactly 0 at sigma = 0 (A and B are even in sigma), but where a fit starts
    (BOUND_MARGIN inside the bound) it is not zero and matches finite differences."""
    bsdf = make(kind)
    wi, wo = hemisphere(256, seed=51, min_cos=0.05), hemisphere(256, seed=52, min_cos=0.05)
    fn = eval_fn(wi, wo)
    spec = (GLAZE_PARAMS if kind == "glaze" else OREN_NAYAR_PARAMS)["sigma"]
    ((_, ad0, _, _),) = derivatives(bsdf, spec, 0.0, fn, 1e-4)
    assert np.all(ad0 == 0)
    start = spec.lower + BOUND_MARGIN * (spec.upper - spec.lower)
    ((_, ad, fd, rounding),) = derivatives(bsdf, spec, start, fn, 5e-4)
    assert np.abs(ad).max() > 1e-4
    assert_derivative(ad, fd, rounding, 0.05, f"{kind} sigma at {start}")
