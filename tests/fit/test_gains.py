"""Per-view gains on the glazed sphere: their gauge, profiled least-squares sums and recovery."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from sphere_problems import ROOT, TRUTH, _gn, two_views

from captures.capture import Capture, View
from fit.config import load_render_config
from fit.material import resolve
from fit.render import Renderer, load_scene, make_render, render, scene_dict
from fit.solvers import Problem, solve, uncertainty


@pytest.mark.slow  # 34 s (LM at 256 spp); gains: the Adam and gn tests below in the default run
def test_per_view_gains_are_recovered():
    """Two views, the second photographed 25 % brighter in red and 10 % darker in green than
    the first: with free gains (their geometric mean 1) and a free pigment, LM recovers both.

    LM with one shared seed minimises that seed's loss: its gains are biased low by about
    Var/I^2 (noise inflates the render's energy): measured -5 % at 32 spp, and -4.5 % at 128
    spp with both views in one batch render (a seed's realisation), hence 256 spp here. Measured
    (2026-12-06): gains within 2.0 % (red), pigment within 0.006; with the glaze's lobes sampled
    at their weight estimate alone the green gain ended 3.04 % off.
    (Adam and LM with a decorrelated Jacobian take the gains' derivatives from an independent
    render: unbiased, see below.)

    (With roughness and ior free too, LM at 32 spp lands at alpha +30 %, ior +0.07 and gains
    -5 %: a gain also scales the highlight, so it trades against ior. Measured; left for the
    fitter's next round: more views, the default schedule, priors on gains.)"""
    gain = np.array([1.25, 0.9, 1.0], np.float32)
    cfg, capture = two_views(gain)
    free = resolve(cfg.material, ["glaze.pigment"])
    problem = Problem(capture, cfg.material, free, gains=True)
    start = {"glaze.pigment": [0.3, 0.3, 0.3]}
    result = solve("lm", problem, problem.unconstrained(start), steps=30, spp=256, seed=1)
    np.testing.assert_allclose(result.values["gain.v0"], 1 / gain, rtol=0.03)
    np.testing.assert_allclose(result.values["gain.v1"], gain, rtol=0.03)
    np.testing.assert_allclose(result.values["glaze.pigment"], TRUTH["glaze.pigment"], atol=0.02)
    std, corr, _ = uncertainty(problem, result.u, spp=32, seed=2)
    assert len(std["gain.v0"]) == len(std["gain.v1"]) == 3 and corr.shape == (9, 9)


def test_adam_gains_are_unbiased_at_low_spp():
    """Adam at 16 spp with free gains: the gains' derivatives use an independent render, so
    the noise's energy does not pull them low (the same image in both factors of the derivative
    measured gains -20 to -22 % and pigment +0.09 here). Measured over seeds 0 and 1: gains as
    Adam's coordinates +4.5 / +3.9 % in red, pigment within 0.005; profiled (the default), red
    +5.6 % (pigment's red 0.094 for 0.1: red is mostly highlight on this blue sphere, and the
    second view's red gain trades against it), green and blue within 3.8 %."""
    gain = np.array([1.25, 0.9, 1.0], np.float32)
    cfg, capture = two_views(gain)
    problem = Problem(capture, cfg.material, resolve(cfg.material, ["glaze.pigment"]), gains=True)
    u0 = problem.unconstrained({"glaze.pigment": [0.3, 0.3, 0.3]})
    result = solve("adam", problem, u0, steps=100, spp=16, lr=0.05, seed=0, average=0.5)
    np.testing.assert_allclose(result.values["gain.v0"], 1 / gain, rtol=0.08)
    np.testing.assert_allclose(result.values["gain.v1"], gain, rtol=0.08)
    np.testing.assert_allclose(result.values["glaze.pigment"], TRUTH["glaze.pigment"], atol=0.02)


def test_profiled_gains_are_the_least_squares_solution():
    """With `profile_gains` a residual returns each gained view and channel's least-squares sums:
    for a render that is the photo divided by known gains, num / den gives those gains exactly
    (views and channels in order), and the residual at them is zero; the gains held in `u` get
    no derivative."""
    from fit.solvers import residuals

    gain = np.array([1.25, 0.9, 1.1], np.float32)
    cfg, capture = two_views(gain)
    problem = Problem(capture, cfg.material, resolve(cfg.material, ["glaze.pigment"]), gains=True)
    target, _ = problem.target()
    first = capture.views[0].image.size
    exact = np.concatenate(
        [target[:first] * np.tile(gain, first // 3), target[first:] / np.tile(gain, first // 3)]
    )
    residual = residuals(
        problem, lambda x, seed: jnp.asarray(exact) * (1 + 0 * x[0]), profile_gains=True
    )
    u = jnp.asarray(problem.unconstrained({"glaze.pigment": [0.3, 0.3, 0.3]}))
    _, (num, den) = residual(u, jnp.int32(0))
    both = np.concatenate([1 / gain, gain])
    np.testing.assert_allclose(np.asarray(num) / np.asarray(den), both, rtol=1e-4)  # float32 sums
    u = u.at[3:].set(problem.gain_coordinates(np.log(both)))
    r, _ = residual(u, jnp.int32(0))
    assert float(jnp.max(jnp.abs(r))) < 1e-5
    grad = jax.grad(lambda u: 0.5 * jnp.sum(residual(u, jnp.int32(0))[0] ** 2))(u + 0.1)
    assert np.all(np.asarray(grad[3:]) == 0)


def test_exposure_gains_are_one_grey_gain_per_view():
    """`gains = "exposure"`: one grey gain per view. The profiled least-squares sums give them
    exactly for a render that is the photo divided by known exposures (the three channels
    pooled), the solver's vector holds one log-gain per view but the first, and the values
    report each as a number."""
    from fit.solvers import residuals

    cfg, capture = two_views(np.float32(1.3))
    free = resolve(cfg.material, ["glaze.pigment"])
    problem = Problem(capture, cfg.material, free, gains="exposure")
    target, _ = problem.target()
    first = capture.views[0].image.size
    exact = np.concatenate([target[:first] * np.float32(1.3), target[first:] / np.float32(1.3)])
    residual = residuals(
        problem, lambda x, seed: jnp.asarray(exact) * (1 + 0 * x[0]), profile_gains=True
    )
    u = jnp.asarray(problem.unconstrained({"glaze.pigment": [0.3, 0.3, 0.3]}))
    assert u.shape == (4,)
    _, (num, den) = residual(u, jnp.int32(0))
    np.testing.assert_allclose(np.asarray(num) / np.asarray(den), [1 / 1.3, 1.3], rtol=1e-4)
    u = u.at[3:].set(jnp.log(1.3))
    r, _ = residual(u, jnp.int32(0))
    assert float(jnp.max(jnp.abs(r))) < 1e-5
    assert problem.values(np.asarray(u))["gain.v0"] == pytest.approx(1 / 1.3, rel=1e-6)
    assert problem.values(np.asarray(u))["gain.v1"] == pytest.approx(1.3, rel=1e-6)
    std, corr, _ = uncertainty(problem, np.asarray(u), spp=4, seed=3)
    assert isinstance(std["gain.v1"], float) and np.isfinite(std["gain.v1"])
    # two views: one coordinate, so the two gains' errors are perfectly anti-correlated
    assert std["gain.v0"] * 1.3 == pytest.approx(std["gain.v1"] / 1.3, rel=1e-4)
    assert corr.shape == (5, 5) and corr[3, 4] == pytest.approx(-1.0, abs=1e-4)
    with pytest.raises(ValueError, match="gains 'rgb'"):
        Problem(capture, cfg.material, free, gains="rgb")


@pytest.mark.parametrize("gains, channels", [(True, 3), ("exposure", 1)])
def test_gains_gauge_is_their_geometric_mean(gains, channels):
    """The gains' gauge: every view has a gain, their log-gains sum to zero per channel, and the
    solver holds all but the first view's. Any per-view log-gains map to coordinates whose gains
    differ from them by one common factor per channel (the gauge's freedom), the coordinates'
    gains map back to the same coordinates, and `gain_jacobian` is the derivative of the
    reported gains (central differences)."""
    cfg = load_render_config(ROOT / "configs" / "glazed-sphere.toml")
    camera = cfg.scene.cameras[0]
    views = [
        View(f"v{i}", np.ones((2, 3, 3), np.float32), np.ones((2, 3), np.float32), camera)
        for i in range(4)
    ]
    free = resolve(cfg.material, ["glaze.ior"])
    problem = Problem(Capture(cfg.scene, views), cfg.material, free, gains=gains)
    assert problem.gain_views == [0, 1, 2, 3] and problem.n_gain == 3 * channels
    logs = np.random.default_rng(0).normal(size=(4, channels))
    coords = problem.gain_coordinates(logs.ravel())
    back = problem.log_gains(coords)
    np.testing.assert_allclose(
        back - logs, np.broadcast_to(back[0] - logs[0], logs.shape), atol=1e-6
    )
    np.testing.assert_allclose(back.sum(axis=0), 0.0, atol=1e-6)
    np.testing.assert_allclose(problem.gain_coordinates(back.ravel()), coords, atol=1e-6)

    def reported(c):
        values = problem.values(np.concatenate([[0.0], c]))
        return np.ravel([values[f"gain.v{i}"] for i in range(4)])

    h, c0 = 1e-5, coords.astype(np.float64)
    numeric = np.stack(
        [(reported(c0 + h * e) - reported(c0 - h * e)) / (2 * h) for e in np.eye(c0.size)], 1
    )
    np.testing.assert_allclose(problem.gain_jacobian(c0), numeric, rtol=1e-6, atol=1e-8)
    one = Problem(Capture(cfg.scene, views[:1]), cfg.material, free, gains=gains)
    assert one.gain_views == [] and one.n_gain == 0 and set(one.values([0.0])) == {"glaze.ior"}


def test_independent_gain_render_keeps_value_and_cost(monkeypatch):
    """The independent render changes the gains' derivatives only: the residual's value is the
    same, the material's gradient is the same, and it costs one primal render (no reverse pass)."""
    from fit.solvers import residuals

    cfg, capture = two_views(np.array([1.25, 0.9, 1.0], np.float32))
    problem = Problem(capture, cfg.material, resolve(cfg.material, ["glaze.pigment"]), gains=True)
    renderer = problem.renderer()
    render = make_render(renderer, "reverse", 4)
    calls = {"render": 0, "vjp": 0}
    for name in calls:
        method = getattr(Renderer, name)

        def counted(self, *args, _method=method, _name=name):
            calls[_name] += 1
            return _method(self, *args)

        monkeypatch.setattr(Renderer, name, counted)
    u = jnp.asarray(problem.unconstrained({"glaze.pigment": [0.3, 0.3, 0.3]}) + 0.1)
    seed = jnp.int32(5)

    def loss(independent_gains):
        residual = residuals(problem, render, independent_gains=independent_gains)
        return jax.value_and_grad(lambda u: 0.5 * jnp.sum(residual(u, seed) ** 2))(u)

    # JAX dispatches asynchronously: count the callbacks once the results exist (on a loaded
    # machine the second reverse pass had not yet run when they were counted)
    (v_same, g_same), (v_indep, g_indep) = jax.block_until_ready((loss(False), loss(True)))
    assert calls == {"render": 3, "vjp": 2}
    assert float(v_same) == float(v_indep)
    np.testing.assert_allclose(g_indep[:3], g_same[:3], rtol=1e-4)  # parallel atomics' rounding
    assert not np.allclose(g_indep[3:], g_same[3:], rtol=1e-3)


def test_gauss_newton_steps_gains_with_the_material():
    """With free gains the gains are Gauss-Newton coordinates like the material's: the second
    view's exposure and the pigment are recovered."""
    gain = np.array([1.25, 0.9, 1.0], np.float32)
    cfg, capture = two_views(gain)
    problem = Problem(capture, cfg.material, resolve(cfg.material, ["glaze.pigment"]), gains=True)
    result = _gn(problem, problem.unconstrained({"glaze.pigment": [0.3, 0.3, 0.3]}), 24, spp=32)
    np.testing.assert_allclose(result.values["gain.v0"], 1 / gain, rtol=0.05)
    np.testing.assert_allclose(result.values["gain.v1"], gain, rtol=0.05)
    np.testing.assert_allclose(result.values["glaze.pigment"], TRUTH["glaze.pigment"], atol=0.02)


def test_gauss_newton_with_five_unknown_exposures():
    """Five views with unknown exposures: the colours' common scale trades with the gains.
    Gains set in closed form a step behind the material made its steps along that trade
    overshoot (about 2.5x): the scale flipped every step (lag-1 autocorrelation -0.86 to -1.0,
    spread 0.26-0.35 in log; seeds 1-3 at 16 and 32 spp, measured when the first view's gain was
    fixed) and ior ended 0.03-0.10 low. Stepped with the material the iterates only carry the
    steps' noise."""
    from captures.scene import Camera

    cfg = load_render_config(ROOT / "configs" / "glazed-sphere.toml")
    gains = np.array([1.0, 1.3, 0.8, 1.15, 0.9])
    gains /= np.exp(np.mean(np.log(gains)))  # the gauge: geometric mean 1
    cameras = tuple(
        Camera((4.9 * np.cos(a), 4.9 * np.sin(a), 0.8), (0.0, 0.0, 0.0), (0, 0, 1.0), 36.0, 32, 24)
        for a in np.linspace(-2.4, -0.8, len(gains))
    )
    scene = dataclasses.replace(cfg.scene, cameras=cameras)
    views = []
    for i, (camera, gain) in enumerate(zip(cameras, gains, strict=True)):
        target = render(load_scene(scene_dict(scene, cfg.material, i, 256)), 256, seed=9 + i)
        views.append(View(f"v{i}", gain * target, np.ones((24, 32), np.float32), camera))
    free = resolve(cfg.material, ["glaze.pigment", "glaze.ior"])
    problem = Problem(Capture(scene, views), cfg.material, free, gains="exposure")
    start = problem.unconstrained({"glaze.pigment": [0.3, 0.3, 0.3], "glaze.ior": 1.4})
    iterates = []
    result = _gn(
        problem,
        start,
        16,
        spp=32,
        jacobian_spp=8,
        refresh=8,
        offer=lambda state: iterates.append(problem.values(state["u"])["glaze.pigment"]),
    )
    scale = np.log(np.mean(np.array(iterates) / TRUTH["glaze.pigment"], axis=1))[4:]
    d = scale - scale.mean()
    assert np.mean(d[1:] * d[:-1]) / np.mean(d * d) > -0.5  # no step-to-step flip
    assert d.std() < 0.15
    # the colours within the project's target: with the first view's gain fixed they came out
    # 8 % low in green and blue (-0.045), the gains as many high; with the gauge within 0.013
    np.testing.assert_allclose(result.values["glaze.pigment"], TRUTH["glaze.pigment"], atol=0.02)
    assert abs(result.values["glaze.ior"] - TRUTH["glaze.ior"]) < 0.07  # 32x24: noisy
    fitted = [result.values[f"gain.v{i}"] for i in range(len(gains))]
    np.testing.assert_allclose(fitted, gains, rtol=0.15)
    assert np.mean(np.log(fitted)) == pytest.approx(0.0, abs=1e-5)


def test_one_pass_control_gradient_is_the_two_pass_one(monkeypatch):
    """`gn`'s control gradient from one pass (`_one_pass`: the image and the reverse pass share
    their paths) is the two-pass one, `m . r`'s gradient with `r` from `residuals`, where the
    image does not depend on the seed: the same derivative through the weights, the gains (here
    free, grey) and the values' transforms, and the same residual."""
    from fit.solvers.gn import _gradients
    from fit.solvers.problem import jax_seed, residuals

    gain = np.array([1.25, 0.9, 1.0], np.float32)
    cfg, capture = two_views(gain)
    free = resolve(cfg.material, ["glaze.pigment", "glaze.roughness"])
    problem = Problem(capture, cfg.material, free, gains="exposure")
    size = sum(v.image.size for v in capture.views)
    base = np.random.default_rng(0).uniform(0.1, 1.0, (size, 4)).astype(np.float32)

    def image(x, seed):  # smooth in the values, the same for every seed
        return jnp.asarray(base) @ jnp.stack([x[0], x[1] ** 2, jnp.sin(x[2]), jnp.sqrt(x[3])])

    monkeypatch.setattr(problem, "render_fn", lambda *a, **k: image)
    _, projected = _gradients(problem, 16, 16, 1, True, True)
    residual = residuals(problem, image)

    def two_pass(u, seed, mean):
        r = residual(u, seed)
        return jnp.dot(jax.lax.stop_gradient(mean), r), r

    u = problem.unconstrained({"glaze.pigment": [0.2, 0.3, 0.4], "glaze.roughness": 0.1})
    assert len(u) == problem.n_material + 1
    u[-1] = 0.2  # the second view's log-gain
    mean = np.random.default_rng(1).normal(size=size).astype(np.float32)
    got, r_got = projected(jnp.asarray(u), jax_seed(3), jnp.asarray(mean))
    want, r_want = jax.grad(two_pass, has_aux=True)(jnp.asarray(u), jax_seed(3), mean)
    np.testing.assert_allclose(r_got, r_want, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-4 * float(jnp.abs(want).max()))
    assert np.all(np.asarray(want) != 0)
