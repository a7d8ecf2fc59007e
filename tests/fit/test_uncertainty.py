"""The fit's uncertainty: cross curvature, the sandwich's meat, averaging, undetermined values."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from sphere_problems import TRUTH

from fit.solvers import uncertainty


def test_cross_curvature_is_unbiased_where_one_jacobians_is_not():
    """Two noisy Jacobians' symmetrised cross product averages to the noise-free `J^T J`; one
    Jacobian's own product adds its noise (the bias that hid alpha's uncertainty); a column of
    pure noise comes out undetermined."""
    from fit.solvers.uncertainty import cross_product, inverse_determined

    rng = np.random.default_rng(0)
    mean = rng.normal(size=(400, 3))
    mean[:, 2] *= 0.02  # a parameter the image barely depends on
    draws = [mean + rng.normal(size=mean.shape) for _ in range(400)]
    cross = np.mean([cross_product(draws[2 * k], draws[2 * k + 1]) for k in range(200)], axis=0)
    own = np.mean([d.T @ d for d in draws], axis=0)
    truth = mean.T @ mean
    assert abs(cross[2, 2] - truth[2, 2]) < 0.2 * truth[2, 2] + 2.0
    assert own[2, 2] > 50 * truth[2, 2]
    keep = np.diag([1.0, 1.0, 0.0])  # the third parameter does not act at all
    _, undetermined = inverse_determined(keep @ cross_product(mean, mean) @ keep)
    assert undetermined.tolist() == [False, False, True]


def test_averaging_covariance_matches_the_averaged_answers_scatter():
    """Preconditioned noisy steps on a quadratic, the last 40 of 80 averaged, 400 seeds: the
    covariance estimated from one run's gradients, `H^-1 S H^-1 / n`, matches the scatter of
    the averaged answers. Where the steps relax slowly (a curvature inflated 15x, as a noisy
    Jacobian's) the iterates' own scatter under-reports it several-fold; this estimate does not
    depend on the steps taken."""
    from fit.solvers.base import tail_variance
    from fit.solvers.uncertainty import averaging_covariance

    rng = np.random.default_rng(1)
    h = np.array([[1.0, 0.3], [0.3, 0.2]])
    noise = np.array([[0.5, 0.0], [0.2, 0.6]])
    truth = np.diag(np.linalg.inv(h) @ noise @ noise.T @ np.linalg.inv(h)) / 40

    def runs(inflation):
        step = 0.5 * np.linalg.inv(h + np.diag([0.0, inflation]))
        answers, estimates, scatter = [], [], []
        for _ in range(400):
            u, iterates, gradients = np.zeros(2), [], []
            for i in range(80):
                g = h @ u + noise @ rng.normal(size=2)
                if i >= 40:
                    iterates.append(u.copy())
                    gradients.append(g)
                u = u - step @ g
            answer = np.mean(iterates, axis=0)
            answers.append(answer)
            cov = averaging_covariance(iterates, gradients, answer, h, np.linalg.inv(h))
            estimates.append(np.diag(cov))
            scatter.append(tail_variance(iterates))
        return np.var(answers, axis=0), np.mean(estimates, axis=0), np.mean(scatter, axis=0)

    spread, estimate, _ = runs(0.0)
    np.testing.assert_allclose(estimate, spread, rtol=0.2)
    np.testing.assert_allclose(estimate, truth, rtol=0.1)
    _, slow_estimate, slow_scatter = runs(3.0)
    np.testing.assert_allclose(slow_estimate, truth, rtol=0.1)
    assert slow_scatter[1] < 0.2 * truth[1]


def test_meat_discounts_the_renders_own_noise():
    """The sandwich's meat from two independent renders' residuals (`r1 r2` per pixel) averages
    to the noise-free one, where their mean's square counts the renders' noise as the target's."""
    from fit.solvers.uncertainty import _meat

    rng = np.random.default_rng(2)
    jac = rng.normal(size=(2001, 3))
    target = 0.1 * rng.normal(size=2001)  # the residual of a noise-free render
    per_pixel = (jac * target[:, None]).reshape(-1, 3, 3).sum(axis=1)
    truth = per_pixel.T @ per_pixel
    meats, squares = [], []
    for _ in range(50):
        r1, r2 = (target + 0.3 * rng.normal(size=2001) for _ in range(2))
        meats.append(_meat(jac, jac, r1, r2))
        squares.append(jac.T @ (jac * (0.5 * (r1 + r2))[:, None] ** 2))
    np.testing.assert_allclose(np.diag(np.mean(meats, axis=0)), np.diag(truth), rtol=0.1)
    assert np.all(np.diag(np.mean(squares, axis=0)) > 4 * np.diag(truth))
    assert np.all(np.linalg.eigvalsh(meats[0]) >= -1e-9)


def test_meat_keeps_the_channels_shared_noise():
    """A pixel's channels share its light paths: with noise common to a pixel's three channels
    and derivatives alike in them (a white highlight's width), the spread of `J^T t` over
    targets is what the per-pixel meat says, three times the per-channel one's."""
    from fit.solvers.uncertainty import _meat

    rng = np.random.default_rng(5)
    pixels = 3000
    jac = np.repeat(rng.normal(size=(pixels, 2)), 3, axis=0)
    sigma = np.repeat(0.1 * rng.uniform(0.5, 2.0, size=pixels), 3)
    draws = [sigma * np.repeat(rng.normal(size=pixels), 3) for _ in range(400)]
    spread = np.var([jac.T @ t for t in draws], axis=0)
    meat = np.mean([np.diag(_meat(jac, jac, t, t)) for t in draws[:50]], axis=0)
    per_channel = np.mean([np.diag(_meat(jac, jac, t, t, channels=1)) for t in draws[:50]], axis=0)
    np.testing.assert_allclose(meat, spread, rtol=0.2)
    np.testing.assert_allclose(meat / per_channel, 3.0, rtol=0.05)


def test_an_undetermined_direction_gets_more_samples_before_it_is_reported(problem, monkeypatch):
    """Where the uncertainty's two Jacobians leave a direction undetermined (their cross product
    not positive: noise), each is averaged with one more render of its own before an infinite sd
    is reported; a determined fit renders the two only. Spoiled: the renders' alpha columns are
    t, -t (a negative cross curvature), then 3t and 3t (the means 2t and t: positive)."""
    import importlib

    module = importlib.import_module("fit.solvers.uncertainty")  # the package exports its function
    real = module.linearised
    calls, first = [], {}

    def spoiled(problem, u, spp, seed, downscale=1):
        r, jac = real(problem, u, spp, seed, downscale)
        calls.append(seed)
        if spoil:  # alpha's columns t, -t (cross curvature negative), then 3t, 3t
            first.setdefault("alpha", jac[:, 3].copy())
            jac = jac.copy()
            jac[:, 3] = first["alpha"] * (1, -1, 3, 3)[len(calls) - 1]
        return r, jac

    monkeypatch.setattr(module, "linearised", spoiled)
    u = problem.unconstrained(TRUTH)
    spoil = False
    std, _, _ = uncertainty(problem, u, spp=128, seed=5)
    assert len(calls) == 2 and np.isfinite(std["glaze.roughness"])
    calls.clear()
    spoil = True
    monkeypatch.setattr(module, "UNDETERMINED_RETRIES", 0)
    std, _, flagged = uncertainty(problem, u, spp=128, seed=5)
    assert len(calls) == 2 and std["glaze.roughness"] == np.inf and "glaze.roughness" in flagged
    calls.clear()
    monkeypatch.setattr(module, "UNDETERMINED_RETRIES", 1)
    more, _, _ = uncertainty(problem, u, spp=128, seed=5)
    assert len(calls) == 4 and len(set(calls)) == 4
    assert np.isfinite(more["glaze.roughness"]) and more["glaze.roughness"] > 0


def test_a_value_pinned_at_its_bound_is_undetermined_not_certain(problem):
    """A diverged fit's coordinates far past the transforms' range (alpha's at +100: at its upper
    bound, ior's at -100: at its lower): their renders' derivatives in the solver's space are
    zero, so both are undetermined, reported infinite; alpha's came out 0 (its transform's
    derivative zero), and ior's derivative NaN (`exp(100)` overflowing) spoiled every row, the
    pigment's too. The transforms' derivatives stay finite there."""
    from fit.material import to_physical

    u = np.asarray(problem.unconstrained(TRUTH), np.float32)
    u[3:5] = 100.0, -100.0
    slopes = jax.jacfwd(lambda v: to_physical(problem.free, v, jnp))(jnp.asarray(u))
    assert np.all(np.isfinite(np.asarray(slopes)))
    values = problem.values(u)
    assert values["glaze.roughness"] == 1.0 and values["glaze.ior"] == pytest.approx(1.01)
    std, corr, flagged = uncertainty(problem, u, spp=32, seed=1)
    assert std["glaze.roughness"] == np.inf and std["glaze.ior"] == np.inf
    assert {"glaze.roughness", "glaze.ior"} <= set(flagged)
    assert all(0 < s < 0.05 for s in std["glaze.pigment"]), std
    # their correlations are unknown (NaN: null in the summary, grey in the report), not 0
    # ("uncorrelated", as the report's heat map drew them); the pigment's among themselves known
    off = ~np.eye(5, dtype=bool)
    assert np.all(np.isnan(corr[3:5][off[3:5]])) and np.all(np.isfinite(corr[:3, :3]))


def test_a_phases_jacobians_are_topped_up_to_the_uncertaintys_samples(problem, monkeypatch):
    """The last `gn` phase's two series of Jacobians (`Result.linearisation`) stand for the
    uncertainty's where they hold its samples, nothing rendered; where they hold fewer, each
    series gets one render of the rest, and the curvature is taken from the mean of all the
    samples (the series weighted by what they hold)."""
    import importlib

    from fit.material import to_physical

    module = importlib.import_module("fit.solvers.uncertainty")  # the package exports its function
    real, crossed = module.linearised, module.cross_product
    calls, seen, crosses = [], [], []

    def counted(problem, u, spp, seed, downscale=1):
        calls.append(spp)
        out = real(problem, u, spp, seed, downscale)
        seen.append(out)
        return out

    monkeypatch.setattr(module, "linearised", counted)
    monkeypatch.setattr(
        module, "cross_product", lambda a, b, *w: crosses.append((a, b)) or crossed(a, b, *w)
    )
    u = problem.unconstrained(TRUTH)
    x0 = np.asarray(to_physical(problem.free, u[: problem.n_material], jnp))
    renderer = problem.renderer(1)
    (i1, j1), (i2, j2) = (renderer.jacobian(x0, seed, 16) for seed in (11, 12))
    model = module.linear_model(problem)
    mine = [
        tuple(np.asarray(a, np.float64) for a in model(u, i, j, x0))
        for i, j in ((i1, j1), (i2, j2))
    ]

    std, _, _ = uncertainty(problem, u, spp=32, seed=5, linearisation=(i1, i2, j1, j2, x0, 16))
    assert calls == [] and np.all(np.isfinite(std["glaze.roughness"]))
    np.testing.assert_allclose(crosses[0][0], module.finite_rows(*mine[0])[1])

    crosses.clear()
    std, _, _ = uncertainty(problem, u, spp=64, seed=5, linearisation=(i1, i2, j1, j2, x0, 16))
    assert calls == [16, 16]
    (_, more1), (_, more2), (jac1, jac2) = seen[0], seen[1], crosses[0]
    np.testing.assert_allclose(jac1, module.finite_rows(mine[0][0], (mine[0][1] + more1) / 2)[1])
    np.testing.assert_allclose(jac2, module.finite_rows(mine[1][0], (mine[1][1] + more2) / 2)[1])
