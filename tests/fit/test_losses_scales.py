"""Robust losses and free emitter scales on a small synthetic glazed sphere (48x36, one view)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from captures.capture import Capture, View
from fit.config import load_render_config
from fit.material import resolve
from fit.render import load_scene, render, scene_dict
from fit.solvers import Phase, Problem, run_schedule, shape_loss, solve
from materials.params import BOUND_MARGIN, SCALE

ROOT = Path(__file__).resolve().parents[2]
PIGMENT = [0.1, 0.22, 0.55]


def sphere(lights: float = 1.0, environment: float = 1.0, spp: int = 512, sky: float = 1.0):
    """(config, a one-view capture of the glazed sphere, its environment `sky` times the
    config's, photographed with the emitters scaled by `lights` and `environment`)."""
    cfg = load_render_config(ROOT / "configs" / "glazed-sphere.toml")
    camera = dataclasses.replace(cfg.scene.cameras[0], width=48, height=36)
    sky_radiance = tuple(sky * c for c in cfg.scene.environment)
    scene = dataclasses.replace(cfg.scene, cameras=(camera,), environment=sky_radiance)
    shown = dataclasses.replace(
        scene,
        lights=tuple(
            dataclasses.replace(light, radiance=tuple(lights * c for c in light.radiance))
            for light in scene.lights
        ),
        environment=tuple(environment * c for c in scene.environment),
    )
    target = render(load_scene(scene_dict(shown, cfg.material, 0, 256)), spp, seed=99)
    return cfg, Capture(scene, [View("v", target, np.ones((36, 48), np.float32), camera)])


@pytest.mark.parametrize("loss", ["huber", "cauchy"])
def test_robust_residuals_are_the_loss(loss):
    """psi(d)^2 / 2 equals the loss rho(d); psi is d near 0 with a finite, unit slope there."""
    d = jnp.linspace(-5.0, 5.0, 1001)
    x = d / 0.5
    rho = {
        "huber": jnp.where(jnp.abs(x) <= 1, x**2 / 2, jnp.abs(x) - 0.5),
        "cauchy": jnp.log1p(x**2) / 2,
    }[loss] * 0.5**2
    psi = shape_loss(d, loss, 0.5)
    np.testing.assert_allclose(psi**2 / 2, rho, rtol=1e-4, atol=1e-7)
    assert np.all(np.diff(np.asarray(psi)) > 0)  # monotone: no sign flips
    slope = jax.grad(lambda d: shape_loss(d, loss, 0.5))(0.0)
    assert float(slope) == pytest.approx(1.0)
    assert np.all(np.isfinite(jax.vmap(jax.grad(lambda d: shape_loss(d, loss, 0.5)))(d)))


def test_robust_loss_ignores_outliers():
    """A tenth of the pixels replaced by garbage (a bright reflection the model lacks): L2 is
    dragged off, Huber (linear tails) less, Cauchy (logarithmic) hardly."""
    cfg, capture = sphere()
    image = capture.views[0].image
    garbage = np.random.default_rng(0).random(image.shape[:2]) < 0.1
    image[garbage] = 2.0
    free = resolve(cfg.material, ["glaze.pigment"])
    start = {"glaze.pigment": [0.3, 0.3, 0.3]}
    schedule = (
        Phase(solver="adam", steps=60, spp=8, lr=0.1),
        Phase(solver="adam", steps=30, spp=32, lr=0.02, average=0.5),
    )
    errors = {}
    for loss in ("l2", "huber", "cauchy"):
        result = run_schedule(Problem(capture, cfg.material, free, loss=loss), start, schedule)
        errors[loss] = np.abs(np.asarray(result.values["glaze.pigment"]) - PIGMENT).max()
    assert errors["l2"] > 0.05  # measured 0.078
    assert errors["huber"] < 0.03 and errors["cauchy"] < 0.01  # measured 0.017, 0.0035


def test_scale_transform_is_symmetric_in_log_space():
    assert float(SCALE.to_unconstrained(1.0)) == pytest.approx(0.0, abs=1e-9)
    assert float(SCALE.to_unconstrained(2.0)) == pytest.approx(-float(SCALE.to_unconstrained(0.5)))
    for value in (0.1, 0.37, 1.0, 4.2, 10.0):
        u = SCALE.to_unconstrained(value)
        assert np.isfinite(u)
        back = float(SCALE.from_unconstrained(u))
        inside = 100**BOUND_MARGIN  # a bound value starts the margin inside, in log space
        assert back == pytest.approx(float(np.clip(value, 0.1 * inside, 10 / inside)), rel=1e-6)


def test_emitter_scale_derivatives():
    """A render is linear in an emitter scale: forward-mode columns equal central differences
    with a shared seed, and the reverse pass equals J^T c (decorrelated seed: to noise)."""
    cfg, capture = sphere()
    problem = Problem(
        capture, cfg.material, resolve(cfg.material, ["lights.scale", "environment.scale"])
    )
    renderer = problem.renderer()
    x = np.array([1.3, 0.7], np.float32)
    image, jac = renderer.jacobian(x, 4, 64)
    for k, h in ((0, 0.05), (1, 0.05)):
        step = np.eye(2, dtype=np.float32)[k] * h
        fd = (renderer.render(x + step, 4, 64) - renderer.render(x - step, 4, 64)) / (2 * h)
        mismatched = ~np.isclose(jac[:, k], fd, rtol=2e-3, atol=1e-4 * np.abs(fd).max())
        # a sample's path now and then branches differently between the kernels (float rounding:
        # 1 pixel of 5184 off by 0.3 % on an AVX2 CPU, none with AVX-512); a wrong column is off
        # everywhere
        assert mismatched.mean() < 2e-3, mismatched.mean()
        assert np.abs(jac[:, k] - fd).sum() < 1e-3 * np.abs(fd).sum()
        assert np.abs(jac[:, k]).sum() > 0  # no silent zero gradient
    c = image / np.abs(image).max()
    vjp = renderer.vjp(x, 4, 256, c)
    _, jac256 = renderer.jacobian(x, 5, 256)
    np.testing.assert_allclose(vjp, jac256.T @ c, rtol=0.03)


def test_emitter_scales_are_recovered():
    """Lights 60 % brighter and the environment half as bright as configured: LM on a 512-spp
    residual recovers both from a 4096-spp target (measured over seeds 1-3: lights -0.9 to
    -1.8 %, environment +0.6 to +1.3 %). The two trade against each other, so a noisier target
    or fit misses by more: LM at 128 spp ended lights -5.6 to +1.6 % by seed; against a 512-spp
    target the optimum itself sat at lights -4 % for one target's noise.

    With the config's dim environment (0.05 against lights of ~200) the environment hardly shows
    outside the background and is weakly determined: measured +21 % (LM, fixed seed), -9 % (Adam
    schedule). Hence a 10x brighter sky here."""
    cfg, capture = sphere(lights=1.6, environment=0.5, spp=4096, sky=10.0)
    problem = Problem(
        capture, cfg.material, resolve(cfg.material, ["lights.scale", "environment.scale"])
    )
    start = {"lights.scale": 1.0, "environment.scale": 1.0}
    result = solve("lm", problem, problem.unconstrained(start), steps=30, spp=512, seed=1)
    assert result.values["lights.scale"] == pytest.approx(1.6, rel=0.04)
    assert result.values["environment.scale"] == pytest.approx(0.5, rel=0.04)


def test_emitter_keys_are_checked():
    cfg, capture = sphere()
    with pytest.raises(KeyError, match=r"emitters have one free parameter, lights.scale"):
        resolve(cfg.material, ["lights.power"])
    dark = dataclasses.replace(capture, scene=dataclasses.replace(capture.scene, lights=()))
    problem = Problem(dark, cfg.material, resolve(cfg.material, ["lights.scale"]))
    with pytest.raises(KeyError, match=r"lights\.scale: not in the scene of view v"):
        problem.renderer()
