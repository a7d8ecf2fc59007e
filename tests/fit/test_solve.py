"""The solvers on the small glazed sphere: recovery, held and rejected steps, Gauss-Newton."""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from sphere_problems import ROOT, TRUTH, _gn, check, keep_offered

from captures.errors import InputError
from fit.config import load_render_config
from fit.material import resolve, to_physical, to_unconstrained
from fit.solvers import Phase, Problem, run_schedule, solve


@pytest.mark.slow  # LM's convergence stays in the default run through the emitter scales' fit
def test_levenberg_marquardt_recovers_the_sphere(larger):
    """LM with one seed ends at that seed's optimum: at 48x36 and 32 spp its pigment was off by
    0.022-0.056 over seeds 0-3 (the variance's gradient), at 128 spp alpha by up to 22 %; at
    96x72 and 64 spp every seed 0-3 within the tolerances (pigment 0.009-0.017, alpha +7 to
    +15 %, ior within 0.036)."""
    start = {"glaze.pigment": [0.3, 0.3, 0.3], "glaze.roughness": 0.2, "glaze.ior": 1.3}
    u0 = to_unconstrained(larger.free, start)
    check(solve("lm", larger, u0, steps=30, spp=64, seed=1).values)


#: The default schedule's shape at this size: Adam at half resolution, then an averaged polish
#: (longer at fewer spp: one view leaves alpha and ior a long, noisy valley).
SCHEDULE = (
    Phase(solver="adam", steps=80, spp=8, downscale=2, lr=0.1),
    Phase(solver="adam", steps=120, spp=16, lr=0.03, average=0.5),
)


@pytest.mark.slow  # 25 s; the default run fits a recovery case with the default schedule
def test_schedule_recovers_and_reports_uncertainty(larger):
    """Recovered, with standard deviations that cover the actual errors (the sandwich form:
    the plain Gauss-Newton one was 10-20x too small where Monte Carlo noise gathers)."""
    problem = larger
    start = {"glaze.pigment": [0.3, 0.3, 0.3], "glaze.roughness": 0.2, "glaze.ior": 1.3}
    result = run_schedule(problem, start, SCHEDULE, seed=0)
    check(result.values)
    assert all(np.all(np.asarray(s) > 0) for s in result.std.values())
    for key in ("glaze.roughness", "glaze.ior"):  # measured at seeds 0-3: within 2.9 sigma
        assert abs(result.values[key] - TRUTH[key]) < 4 * result.std[key]
    assert result.correlation.shape == (5, 5)
    np.testing.assert_allclose(np.diag(result.correlation), 1.0, rtol=1e-4)
    again = run_schedule(problem, start, SCHEDULE, seed=0)
    # same config and seed: same values (to float32 rounding: the adjoint pass sums gradients
    # with parallel atomics, whose order varies)
    for key, value in result.values.items():
        np.testing.assert_allclose(again.values[key], value, rtol=1e-4)


def test_schedule_from_a_bound(problem):
    """ior started at its lower bound (inside by the 1e-3 margin, where its sigmoid is flat): the
    scale-free Adam phase moves it (it needs ~60 steps of lr 0.1 to cross the flat part: 40
    left ior at 1.13). LM gets there too, creeping: 51 steps with tight tolerances (it stops at
    ior 1.14 after 30).

    Measured, not asserted: from this start a valley where a sharper, dimmer highlight (low
    alpha, low ior) trades against the truth holds a local minimum. The Cycles sphere ends there
    with the default schedule (alpha -18 %, ior -0.04; its loss 2.2x the truth's at 1024 spp), and
    so do seeds 0 and 2 of the 96x72 sphere; an LM phase at half resolution does not escape it.
    A start at alpha = 1 with ior = 3 is another local minimum (alpha wants to grow)."""
    start = {"glaze.pigment": [0.3, 0.3, 0.3], "glaze.roughness": 0.2, "glaze.ior": 1.01}
    check(run_schedule(problem, start, SCHEDULE, seed=0).values)


@pytest.mark.slow
@pytest.mark.xfail(
    strict=True,
    reason="LM alone from ior's bound ends off the truth (2026-12-05: pigment blue 0.502 for "
    "0.55 at 32 spp, red 0.128 for 0.1 at 64 spp): not yet understood; the default schedule "
    "never runs LM alone",
)
def test_levenberg_marquardt_from_a_bound(problem):
    """LM alone from ior's lower bound: it creeps off the flat end of the sigmoid (51 steps)."""
    start = {"glaze.pigment": [0.3, 0.3, 0.3], "glaze.roughness": 0.2, "glaze.ior": 1.01}
    u0 = problem.unconstrained(start)
    lm = solve("lm", problem, u0, steps=80, spp=32, seed=1, rtol=1e-7, atol=1e-9)
    check(lm.values)


def test_non_finite_steps_are_rejected(problem, monkeypatch):
    """Adam skips a step whose loss or gradient is not finite (and goes on with the next seed);
    LM and BFGS that end non-finite return their start: nothing non-finite is ever applied."""
    renderer = problem.renderer()
    real, calls = renderer.render, {"n": 0}

    def every_third_is_nan(values, seed, spp):
        calls["n"] += 1
        return real(values, seed, spp) * (np.nan if calls["n"] % 3 == 0 else 1.0)

    monkeypatch.setattr(renderer, "render", every_third_is_nan)
    start = {"glaze.pigment": [0.3, 0.3, 0.3], "glaze.roughness": 0.2, "glaze.ior": 1.3}
    u0 = problem.unconstrained(start)
    result = solve("adam", problem, u0, steps=9, spp=4, lr=0.1, seed=0)
    assert np.isnan(result.history).sum() == 3
    assert result.reports[0].rejected == 3 and result.reports[0].outcome == "step_limit"
    assert np.all(np.isfinite(result.u)) and not np.array_equal(result.u, u0)
    monkeypatch.setattr(renderer, "render", lambda v, s, spp: real(v, s, spp) * np.nan)
    for solver in ("lm", "bfgs"):
        result = solve(solver, problem, u0, steps=3, spp=4)
        np.testing.assert_array_equal(result.u, u0)
        assert result.reports[0].outcome == "diverged", solver  # said, never silent


def test_adam_holds_what_it_is_told_to(problem):
    """`hold` (keys or patterns) keeps those coordinates exactly where they started while the
    rest move; a pattern that matches no free parameter is an error naming it and the keys."""
    start = {"glaze.pigment": [0.3, 0.3, 0.3], "glaze.roughness": 0.2, "glaze.ior": 1.3}
    u0 = problem.unconstrained(start)
    result = solve("adam", problem, u0, steps=4, spp=4, lr=0.1, seed=0, hold=["*.ior"])
    assert result.u[4] == u0[4]
    assert np.all(result.u[:4] != u0[:4])
    free = solve("adam", problem, u0, steps=4, spp=4, lr=0.1, seed=0)
    assert free.u[4] != u0[4]  # the same steps without `hold` move it
    # a held phase stopped after step 2 and resumed from its offered state ends the same
    from fit.solvers.registry import SOLVERS

    phase = Phase(solver="adam", steps=4, spp=4, lr=0.1, hold=["*.ior"])
    saved = {}
    run = functools.partial(SOLVERS["adam"]().run, problem, u0, steps=4, spp=4, seed=0)
    whole = run(downscale=1, options=phase.options, offer=keep_offered(2, saved))
    resumed = run(downscale=1, options=phase.options, resume=saved)
    np.testing.assert_allclose(resumed.u, whole.u, rtol=1e-5, atol=1e-6)
    assert resumed.u[4] == u0[4]
    with pytest.raises(InputError, match=r"'clay\.\*' matches no free parameter.*glaze\.ior"):
        solve("adam", problem, u0, steps=1, spp=4, hold=["glaze.ior", "clay.*"])


def test_a_solver_that_never_moved_says_so():
    """optimistix does not count rejected steps: an answer equal to the start after some steps
    is reported as every step rejected (an LM polish at 64 spp from the cup's fit did not move
    at all and said `rejected: 0`)."""
    import types

    import optimistix as optx

    from fit.solvers.base import optimistix_result

    material = load_render_config(ROOT / "configs" / "glazed-sphere.toml").material
    problem = Problem(None, material, resolve(material, ["glaze.ior"]))
    u0 = np.zeros(1, np.float32)
    for value, rejected in ((u0, 3), (u0 + 1, 0)):
        solution = types.SimpleNamespace(
            value=jnp.asarray(value), stats={"num_steps": 3}, result=optx.RESULTS.max_steps_reached
        )
        result = optimistix_result("lm", problem, solution, u0, lambda u: 1.0, None)
        assert result.reports[0].rejected == rejected
        assert ("every one of the 3 steps was rejected" in result.reports[0].message) == bool(
            rejected
        )


def _linear_images(problem, monkeypatch, optimum: dict) -> None:
    """Make `problem` render an exact linear image of the physical values whose least-squares
    optimum is `optimum` (possibly outside the bounds), Jacobians exact."""
    target, _ = problem.target(1)
    jac = np.random.default_rng(0).normal(size=(target.size, 5)).astype(np.float32) * 0.05
    x_opt = np.array([*optimum["glaze.pigment"], optimum["glaze.roughness"], optimum["glaze.ior"]])

    def image(x):
        return jnp.asarray(target) + jnp.asarray(jac) @ (x - jnp.asarray(x_opt, jnp.float32))

    class Linear:
        def jacobian(self, values, seed, spp):
            return np.asarray(image(jnp.asarray(values))), jac

    monkeypatch.setattr(problem, "render_fn", lambda *a, **k: lambda x, seed: image(x))
    monkeypatch.setattr(problem, "renderer", lambda downscale=1: Linear())


def test_gauss_newton_curvature_follows_the_transform(problem, monkeypatch):
    """`gn`'s curvature is rendered in physical values and taken to the solver's space where the
    iterate is: next to a bound the sigmoid's derivative shrinks as the iterate nears it (alpha
    from 0.05 toward 0.0025 by 90x), and a solver-space Jacobian kept from the start made each
    step ~(that factor)^2 too short (the iterate stalled). On an exact linear image with its
    optimum at alpha 0.0025 (bound 0.002), 16 steps reach it within 1 %."""
    truth = {"glaze.pigment": [0.1, 0.22, 0.55], "glaze.roughness": 0.0025, "glaze.ior": 1.52}
    _linear_images(problem, monkeypatch, truth)
    start = {**truth, "glaze.roughness": 0.05}
    result = _gn(problem, problem.unconstrained(start), 16, refresh=4, average=0.0)
    assert result.values["glaze.roughness"] == pytest.approx(0.0025, rel=0.01)
    np.testing.assert_allclose(result.values["glaze.pigment"], truth["glaze.pigment"], atol=1e-3)


@pytest.mark.parametrize("gradient", ["control", "reverse"])
def test_gauss_newton_fixed_point_ignores_the_curvatures_jacobian_error(
    problem, monkeypatch, gradient
):
    """Each step's gradient takes the step image's part of the residual through the
    curvature's Jacobian (`gradient = "control"`), whose error must not move the fixed point:
    on an exact linear image plus a misfit no parameter explains (a target's noise), with the
    curvature's Jacobian 40 % off, `gn` ends at the least-squares optimum, where the Jacobian
    alone (`J^T r`, no reverse pass) would end elsewhere (checked: far from it)."""
    target, sqrt_w = problem.target(1)
    rng = np.random.default_rng(3)
    jac = rng.normal(size=(target.size, 5)).astype(np.float32) * 0.05
    wrong = jac * (1 + 0.4 * rng.normal(size=jac.shape)).astype(np.float32)
    # a misfit along the Jacobian's error (where it matters), plus noise
    misfit = 0.3 * (wrong - jac) @ np.ones(5, np.float32)
    misfit += 0.005 * rng.normal(size=target.size).astype(np.float32)
    x_ref = np.array([0.1, 0.22, 0.55, 0.1, 1.5], np.float32)

    def image(x):
        return jnp.asarray(target + misfit) + jnp.asarray(jac) @ (x - jnp.asarray(x_ref))

    class Wrong:
        def jacobian(self, values, seed, spp):
            return np.asarray(image(jnp.asarray(values))), wrong

    monkeypatch.setattr(problem, "render_fn", lambda *a, **k: lambda x, seed: image(x))
    monkeypatch.setattr(problem, "renderer", lambda downscale=1: Wrong())
    a, w = jac * sqrt_w[:, None], wrong * sqrt_w[:, None]
    optimum = x_ref - np.linalg.solve(a.T @ a, a.T @ (sqrt_w * misfit))
    jacobian_only = x_ref - np.linalg.solve(w.T @ a, w.T @ (sqrt_w * misfit))
    assert np.max(np.abs(jacobian_only - optimum)) > 0.02  # the case: the error matters
    start = {"glaze.pigment": [0.2, 0.3, 0.4], "glaze.roughness": 0.15, "glaze.ior": 1.4}
    result = _gn(problem, problem.unconstrained(start), 40, average=0.0, gradient=gradient)
    fitted = np.array(
        [
            *result.values["glaze.pigment"],
            *[result.values[k] for k in ("glaze.roughness", "glaze.ior")],
        ]
    )
    np.testing.assert_allclose(fitted, optimum, atol=2e-3)


def test_gauss_newton_primal_spp_renders_the_image_apart(problem, monkeypatch):
    """With `primal_spp` each step's image renders at that count and its reverse pass at the
    phase's `spp` (the Jacobians at `jacobian_spp`), and the steps stay finite."""
    renderer = problem.renderer(1)
    calls = {"render": [], "vjp": []}
    for name in calls:
        method = getattr(renderer, name)

        def spy(values, seed, spp, *rest, method=method, name=name):
            calls[name].append(spp)
            return method(values, seed, spp, *rest)

        monkeypatch.setattr(renderer, name, spy)
    start = {"glaze.pigment": [0.3, 0.3, 0.3], "glaze.roughness": 0.12, "glaze.ior": 1.4}
    result = _gn(problem, problem.unconstrained(start), 4, spp=2, primal_spp=12)
    # each of the two Jacobians renders its own image at half of jacobian_spp (16)
    assert calls["render"].count(12) == 4 and set(calls["render"]) <= {8, 12}
    assert calls["vjp"] == [2] * 4
    assert result.reports[0].rejected == 0 and np.all(np.isfinite(result.u))


def test_marquardt_damps_directions_weak_only_jointly():
    """`marquardt` adds a fraction of the curvature's diagonal: a direction weak only jointly
    (two coordinates that trade, each well determined alone) takes a far shorter step; a
    coordinate weak on its own keeps its step (up to 1 + marquardt)."""
    from fit.solvers.gn import GaussNewton, GNOptions

    h = np.array([[1.0, 0.999, 0.0], [0.999, 1.0, 0.0], [0.0, 0.0, 0.001]])
    trade, alone = np.array([1.0, -1.0, 0.0]) / np.sqrt(2), np.array([0.0, 0.0, 1.0])
    plain = GaussNewton._inverse(h, GNOptions())
    damped = GaussNewton._inverse(h, GNOptions(marquardt=0.5))
    assert trade @ plain @ trade == pytest.approx(1000.0, rel=2e-3)
    assert trade @ damped @ trade == pytest.approx(1 / 0.501, rel=2e-3)
    assert alone @ damped @ alone == pytest.approx(1000.0 / 1.5, rel=2e-3)


def test_gauss_newton_curvature_discounts_the_jacobians_noise():
    """Where a Jacobian column is mostly noise (alpha at 0.01-0.02: its plain `J^T J` 15-18x
    the noise-free one at 16 spp), `gn`'s curvature comes down near the noise-free value, not
    below it (steps too long oscillate), a column without noise stays, and it stays positive
    semi-definite."""
    from fit.solvers.gn import _curvature

    rng = np.random.default_rng(3)
    pixels = 4000
    signal = rng.normal(size=(pixels, 3)) * [1.0, 0.05, 0.2]
    noise = [rng.normal(size=(pixels, 3)) * [0.0, 0.3, 0.02] for _ in range(2)]
    exact = signal.T @ signal
    h = _curvature(signal + noise[0], signal + noise[1])
    plain = ((signal + (noise[0] + noise[1]) / 2) ** 2).sum(axis=0)
    assert h[0, 0] == pytest.approx(exact[0, 0], rel=1e-9)
    assert plain[1] > 10 * exact[1, 1]  # the case: noise 18x the signal's energy
    assert exact[1, 1] < h[1, 1] < plain[1] / 4
    assert exact[2, 2] * 0.99 < h[2, 2] <= plain[2] * (1 + 1e-9)
    assert np.linalg.eigvalsh(h).min() >= -1e-9 * np.abs(h).max()


def _against(problem: Problem, image: np.ndarray) -> Problem:
    """`problem` with its one view's photo replaced by `image`."""
    view = dataclasses.replace(problem.capture.views[0], image=image.astype(np.float32))
    capture = dataclasses.replace(problem.capture, views=[view])
    return Problem(capture, problem.material, problem.free)


def test_noise_ratio_is_the_renders_share_of_the_residual(problem):
    """Against a target that is itself a render at the same spp, the rest of the residual is one
    render's noise: a ratio about 1; at 16x the samples about 16, well above `AUTO_RATIO` (one
    pair of 4-spp renders is a heavy-tailed estimate of their noise: over six 64-spp targets and
    three noise seeds each it read 2.7 to infinity, the medians 8-25); against a target three
    times brighter, the difference dominates (30 % brighter is still 7x less than 4-spp noise on
    this small sphere's highlights)."""
    from fit.solvers.gn import AUTO_RATIO
    from fit.solvers.problem import noise_ratio

    u = problem.unconstrained(TRUTH)
    x = to_physical(problem.free, u)
    shape = problem.capture.views[0].image.shape

    def target(spp, seed=4242):
        return problem.renderer(1).render(x, seed, spp).reshape(shape)

    same = [noise_ratio(_against(problem, target(4, 4242 + k)), u, 4, k) for k in range(4)]
    assert 0.6 < np.median(same) < 1.6, same
    clean = [noise_ratio(_against(problem, target(64)), u, 4, k) for k in range(4)]
    assert np.median(clean) > 2 * AUTO_RATIO, clean
    assert noise_ratio(_against(problem, 3.0 * target(64)), u, 4, 0) < 0.5


def test_gauss_newton_auto_split_follows_the_residual(problem, monkeypatch):
    """`primal_spp = "auto"`: against a clean target the image renders at 4x the phase's spp and
    the reverse pass at a quarter, said in the phase's report; against a target three times
    brighter both keep the phase's spp, the image then from the reverse pass's own primal pass
    (`shared_paths`: `Renderer.render_vjp`)."""
    clean = problem.unconstrained(TRUTH)
    for factor, image_spp, reverse_spp in ((1.0, 16, 1), (3.0, 4, 4)):
        p = _against(problem, factor * problem.capture.views[0].image)
        renderer = p.renderer(1)
        calls = {"render": [], "vjp": [], "render_vjp": []}
        for name in calls:
            method = getattr(renderer, name)

            def spy(values, seed, spp, *rest, method=method, seen=calls[name]):
                seen.append(spp)
                return method(values, seed, spp, *rest)

            monkeypatch.setattr(renderer, name, spy)
        result = _gn(p, clean, 2, spp=4, primal_spp="auto", shared_paths=True)
        if image_spp == reverse_spp:
            assert calls["render_vjp"] == [image_spp] * 2 and not calls["vjp"]
        else:
            assert calls["vjp"] == [reverse_spp] * 2 and not calls["render_vjp"]
            assert calls["render"].count(image_spp) >= 2
        assert f"image {image_spp}, reverse pass {reverse_spp}" in result.reports[0].message


def test_gauss_newton_averages_without_bias_next_to_a_bound(problem, monkeypatch):
    """`gn` steps and averages in the solver's space (the sigmoid's logits), where a linear
    image's noise does not average to an upward drift. On an exact linear image with its
    optimum at alpha 0.004 (twice its sigmoid's bound 0.002) plus image noise of a fresh seed
    each step (each iterate's alpha about 30 % off), the mean of 360 steps lands within 6 % of
    the optimum (BENCHMARKS, "Low alpha": at twice the bound the iterates' arithmetic mean in
    alpha was +4 to +9 % off, stepping and averaging in alpha itself -5 to -10 %)."""
    truth = {"glaze.pigment": [0.1, 0.22, 0.55], "glaze.roughness": 0.004, "glaze.ior": 1.52}
    _noisy_linear_images(problem, monkeypatch, truth, 0.3)
    result = _gn(problem, problem.unconstrained(truth), 400, refresh=400, average=0.9, eta=1.0)
    assert result.values["glaze.roughness"] == pytest.approx(0.004, rel=0.06)


def _noisy_linear_images(problem, monkeypatch, truth, share):
    """`_linear_images` plus image noise of a fresh seed each render, sized so that one step's
    alpha is `share` of its value off."""
    _linear_images(problem, monkeypatch, truth)
    target, _ = problem.target(1)
    base = problem.render_fn()
    noise = share * truth["glaze.roughness"] * 0.05 * np.sqrt(target.size)

    def noisy(x, seed):
        key = jax.random.PRNGKey(seed)
        return base(x, seed) + noise * jax.random.normal(key, (target.size,), jnp.float32)

    monkeypatch.setattr(problem, "render_fn", lambda *a, **k: noisy)


@pytest.mark.parametrize("share, ends", [(0.002, "at its steps"), (0.07, "later"), (2.0, "limit")])
def test_a_precise_phase_averages_until_its_noise_is_small(problem, monkeypatch, share, ends):
    """`GNOptions.precision`: the phase goes on past `steps` until its averaged answer's Monte
    Carlo sd is within `precision` of every value. One step's alpha 0.2 % off: 8 steps are
    enough; 7 %: more steps (an average of n steps is about 7 % / sqrt(n) off: 13 for 2 %);
    200 %: every step up to `max_steps`, the message naming what stayed noisy."""
    truth = {"glaze.pigment": [0.1, 0.22, 0.55], "glaze.roughness": 0.1, "glaze.ior": 1.52}
    _noisy_linear_images(problem, monkeypatch, truth, share)
    u0 = problem.unconstrained(truth)
    options = dict(refresh=4, average=1.0, eta=1.0, precision=0.02, max_steps=32)
    result = _gn(problem, u0, 8, **options)
    report = result.reports[-1]
    if ends == "at its steps":
        assert result.steps == 8 and "averaged" not in report.message
    elif ends == "later":
        assert 8 < result.steps < 32 and "averaged" in report.message
        assert "still noisier" not in report.message
        assert result.values["glaze.roughness"] == pytest.approx(0.1, rel=0.04)
    else:
        assert result.steps == 32 and "still noisier at max_steps" in report.message
        assert "glaze.roughness" in report.message


def test_a_precise_phase_resumes_to_the_same_end(problem, monkeypatch):
    """A phase stopped right after the step at which it found itself precise (its state offered,
    then a Ctrl-C) ends there when resumed, at the uninterrupted run's answer; stopped at an
    earlier check it goes on to the same end."""
    truth = {"glaze.pigment": [0.1, 0.22, 0.55], "glaze.roughness": 0.1, "glaze.ior": 1.52}
    _noisy_linear_images(problem, monkeypatch, truth, 0.07)
    u0 = problem.unconstrained(truth)
    options = dict(refresh=4, average=1.0, eta=1.0, precision=0.02, max_steps=32)
    whole = _gn(problem, u0, 8, **options)
    assert 8 < whole.steps < 32
    for stop in (whole.steps, whole.steps - 4):
        saved = {}
        _gn(problem, u0, 8, offer=keep_offered(stop, saved), **options)
        resumed = _gn(problem, u0, 8, resume=saved, **options)
        assert resumed.steps == whole.steps, stop
        np.testing.assert_allclose(resumed.u, whole.u, rtol=1e-5, atol=1e-6)


def _flat_below_images(problem, monkeypatch, truth, share):
    """Images whose alpha column acts only above the truth's alpha (softly, over a tenth of
    it): below it the loss is flat, as a lobe narrower than a pixel and the light's reflection
    leaves it, steep above. Other columns linear; image noise of a fresh seed each render, sized
    so that one step's alpha is about `share` of its value off."""
    target, _ = problem.target(1)
    jac = np.random.default_rng(0).normal(size=(target.size, 5)).astype(np.float32) * 0.05
    x_opt = np.array([*truth["glaze.pigment"], truth["glaze.roughness"], truth["glaze.ior"]])
    alpha, soft = truth["glaze.roughness"], 0.1 * truth["glaze.roughness"]
    noise = share * alpha * 0.05 * np.sqrt(target.size)

    def bent(x):  # alpha through a softplus: flat below the truth, slope 1 above
        ramp = soft * jax.nn.softplus((x[3] - alpha) / soft)
        return x.at[3].set(ramp - soft * np.log(2.0) + alpha)

    def image(x, seed=None):
        clean = jnp.asarray(target) + jnp.asarray(jac) @ (bent(x) - jnp.asarray(x_opt, jnp.float32))
        if seed is None:
            return clean
        return clean + noise * jax.random.normal(jax.random.PRNGKey(seed), (target.size,))

    class Bent:
        def jacobian(self, values, seed, spp):
            x = jnp.asarray(values)
            slope = np.asarray(jax.jacfwd(bent)(x))
            return np.asarray(image(x, seed)), jac @ slope

    monkeypatch.setattr(problem, "render_fn", lambda *a, **k: image)
    monkeypatch.setattr(problem, "renderer", lambda downscale=1: Bent())


@pytest.mark.xfail(
    strict=True,
    reason=(
        "2026-12-05: the default's averaged phase walks down the flat side: over seeds 1-6 alpha "
        "0.0084 on average (-16 %), spread 27 %. Capped at 0.1 a step (`max_step`) it ends "
        "0.0103, spread 9 %, but on the recovery sweep that cap also kept unfinished relaxations "
        "unfinished (the sphere at alpha 0.005: +65 % against -18 %), so the default keeps 1"
    ),
)
def test_the_averaged_phase_does_not_walk_down_a_flat_side(problem, monkeypatch):
    """The default's averaged phase, started at the truth's alpha 0.01 where the loss is flat
    below and steep above (`_flat_below_images`), each step's alpha about 60 % off: over six
    seeds its answers average within 5 % of the truth and spread less than 15 %. Steps of up
    to 1 in the sigmoid's coordinate (a factor e in alpha less its bound) walk it down the flat
    side, where nothing brings it back: the sphere at alpha 0.01 against a clean target ended
    0.0039 (BENCHMARKS, "Recovery over the range")."""
    from fit.solvers import DEFAULT_SCHEDULE

    truth = {"glaze.pigment": [0.1, 0.22, 0.55], "glaze.roughness": 0.01, "glaze.ior": 1.52}
    _flat_below_images(problem, monkeypatch, truth, 0.6)
    last = DEFAULT_SCHEDULE[-1]
    u0 = problem.unconstrained(truth)
    options = last.options.model_dump()
    alphas = [
        _gn(problem, u0, last.steps, seed=s, **options).values["glaze.roughness"]
        for s in range(1, 7)
    ]
    assert np.mean(alphas) == pytest.approx(0.01, rel=0.05), alphas
    assert np.std(alphas) < 0.15 * 0.01, alphas


@pytest.mark.parametrize(
    "key, column, at_bound, inside",
    [
        ("glaze.pigment", 0, [0.0, 0.22, 0.55], [0.3, 0.22, 0.55]),
        ("glaze.roughness", 3, 0.002, 0.1),
    ],
)
@pytest.mark.parametrize("pinned", [True, False])
def test_a_value_at_its_bound_does_not_hold_a_precise_phase(
    problem, key, column, at_bound, inside, pinned
):
    """`imprecise`: a component whose average sits at a bound is not what keeps a precise phase
    going. Where the loss is flat in it (Oren-Nayar's sigma at 0 acts quadratically; here a
    colour's component, or a scalar, with a column of 1e-5), the sd linearised at the average
    is large whatever the iterates do; inside its range the same column still asks for more
    steps."""
    from fit.solvers.gn import imprecise

    truth = {"glaze.pigment": [0.1, 0.22, 0.55], "glaze.roughness": 0.1, "glaze.ior": 1.52}
    truth[key] = at_bound if pinned else inside
    u = np.asarray(problem.unconstrained(truth), np.float64)
    rng = np.random.default_rng(0)
    jac = rng.normal(size=(500, u.size))
    jac[:, column] *= 1e-5
    tail = u + 1e-6 * rng.normal(size=(8, u.size))
    gradients = 1e-4 * rng.normal(size=(8, u.size))
    keys = imprecise(problem, tail, gradients, jac, jac, 0.015)
    assert keys == ([] if pinned else [key])
