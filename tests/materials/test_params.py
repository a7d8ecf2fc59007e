"""Parameter declarations: bounds, transforms, and what `register()` does (and does not do)."""

from __future__ import annotations

import subprocess
import sys

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from materials.params import BOUND_MARGIN, GLAZE_PARAMS, OREN_NAYAR_PARAMS, ParamSpec, spec_table

ALL = [*GLAZE_PARAMS.values(), *OREN_NAYAR_PARAMS.values()]


def test_design_bounds():
    """The bounds DESIGN.md fixes, alpha's lower one below its 0.01: polished glazes go under
    0.01, and a truth on a bound cannot be told from the bound."""
    assert (GLAZE_PARAMS["roughness"].lower, GLAZE_PARAMS["roughness"].upper) == (0.002, 1.0)
    assert (GLAZE_PARAMS["ior"].lower, GLAZE_PARAMS["ior"].upper) == (1.01, 3.0)
    assert (OREN_NAYAR_PARAMS["sigma"].lower, OREN_NAYAR_PARAMS["sigma"].upper) == (0.0, 1.0)
    assert OREN_NAYAR_PARAMS["sigma"].unit == "rad"


def gradient_share(alpha: float, n: int = 20000) -> float:
    """The share of directions uniform in solid angle within 0.05 rad of the mirror (30 degree
    incidence) where the Beckmann distribution's derivative in alpha is non-zero and finite."""
    rng = np.random.default_rng(0)
    incident = np.array([np.sin(np.radians(30)), 0.0, np.cos(np.radians(30))])
    mirror = incident * [-1, 1, 1]
    cos = 1 - rng.random(n) * (1 - np.cos(0.05))
    sin, phi = np.sqrt(1 - cos**2), rng.random(n) * 2 * np.pi
    t1 = np.cross(mirror, [0.0, 1.0, 0.0])
    t1 /= np.linalg.norm(t1)
    t2 = np.cross(mirror, t1)
    out = cos[:, None] * mirror + sin[:, None] * (
        np.cos(phi)[:, None] * t1 + np.sin(phi)[:, None] * t2
    )
    half = out + incident
    half /= np.linalg.norm(half, axis=1)[:, None]
    a = mi.Float(alpha)
    dr.enable_grad(a)
    dr.set_grad(a, 1.0)
    density = mi.MicrofacetDistribution(mi.MicrofacetType.Beckmann, a).eval(mi.Vector3f(half.T))
    # (Mitsuba clamps alpha at 1e-4: no derivative at all there)
    grad = np.asarray(dr.forward_to(density, flags=dr.ADFlag.Default | dr.ADFlag.AllowNoGrad))
    return float(np.mean((grad != 0) & np.isfinite(grad)))


def test_alphas_lower_bound_keeps_a_gradient():
    """At alpha's lower bound the lobe still carries a derivative in alpha across a third of the
    directions near the mirror; ten times below, float32's exp underflows almost everywhere
    (docs/material.md, "Bounds")."""
    lower = GLAZE_PARAMS["roughness"].lower
    assert gradient_share(2.5 * lower) == 1.0
    assert 0.25 <= gradient_share(lower) <= 0.4
    assert gradient_share(0.5 * lower) < 0.1
    assert gradient_share(0.05 * lower) == 0.0


@pytest.mark.parametrize("spec", ALL, ids=lambda s: s.key)
def test_transform_round_trip(spec):
    x = np.linspace(spec.lower, spec.upper, 11)[1:-1]
    np.testing.assert_allclose(spec.from_unconstrained(spec.to_unconstrained(x)), x, rtol=1e-9)


@pytest.mark.parametrize("spec", ALL, ids=lambda s: s.key)
def test_start_at_bound_moves_inside(spec):
    span = spec.upper - spec.lower
    for bound, inside in (
        (spec.lower, spec.lower + BOUND_MARGIN * span),
        (spec.upper, spec.upper - BOUND_MARGIN * span),
    ):
        u = spec.to_unconstrained(bound)
        assert np.isfinite(u)
        assert spec.from_unconstrained(u) == pytest.approx(inside, rel=1e-9)


def test_transform_works_with_jax():
    jnp = pytest.importorskip("jax.numpy")
    spec = GLAZE_PARAMS["roughness"]
    u = spec.to_unconstrained(jnp.asarray(0.3), xp=jnp)
    assert float(spec.from_unconstrained(u, xp=jnp)) == pytest.approx(0.3, rel=1e-6)


def test_bad_declarations():
    with pytest.raises(ValueError, match="lower 1 must be < upper 0"):
        ParamSpec("x", 0.5, 1, 0, "sigmoid", "", "")
    with pytest.raises(ValueError, match=r"default 2\.0 is outside"):
        ParamSpec("x", 2.0, 0, 1, "sigmoid", "", "")
    with pytest.raises(ValueError, match="declared twice"):
        spec_table(GLAZE_PARAMS["ior"], GLAZE_PARAMS["ior"])


def test_check_names_the_place():
    with pytest.raises(
        ValueError, match=r"cup.toml: material: ior = 0.5 is outside .*\[1.01, 3.0\]"
    ):
        GLAZE_PARAMS["ior"].check(0.5, "cup.toml: material")
    with pytest.raises(ValueError, match="not finite"):
        GLAZE_PARAMS["ior"].check(float("nan"), "here")


@pytest.mark.parametrize(
    "plugin, specs", [("glaze", GLAZE_PARAMS), ("oren_nayar", OREN_NAYAR_PARAMS)]
)
def test_traverse_exposes_every_declared_parameter(plugin, specs):
    params = mi.traverse(mi.load_dict({"type": plugin}))
    keys = {f"{s.key}.value" if s.kind == "rgb" else s.key for s in specs.values()}
    assert keys == set(params.keys())
    for key in keys:
        assert params.flags(key) & int(mi.ParamFlags.NonDifferentiable) == 0, key
    for spec in specs.values():  # plugin defaults are the declared defaults
        key = f"{spec.key}.value" if spec.kind == "rgb" else spec.key
        np.testing.assert_allclose(np.ravel(params[key]), np.ravel(spec.default), rtol=1e-6)


def test_import_has_no_side_effects():
    """Importing `materials` sets no variant and registers nothing; `register()` needs a variant."""
    code = (
        "import mitsuba as mi, materials\n"
        "assert mi.variant() is None, mi.variant()\n"
        "try:\n    materials.register()\nexcept RuntimeError as e:\n    print(e)\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=False
    )
    assert out.returncode == 0, out.stderr
    assert "set a Mitsuba variant first" in out.stdout
