"""The scalars' sd with textures free: what refitting the texels beside them takes from their
curvature (the Schur complement, `texel_trade` and `traded_inverse`)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from captures.capture import Capture, View
from fit.config import load_render_config
from fit.material import resolve
from fit.material.textures import with_free_textures
from fit.render import load_scene, render, scene_dict
from fit.solvers import Problem
from fit.solvers.textures import residual_scale, texel_trade
from fit.solvers.uncertainty import MAX_TRADE, finite_rows, linearised, traded_inverse

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize("seed", range(4))
def test_the_traded_inverse_is_the_marginal_covariance_of_a_linear_model(seed):
    """Scalars s beside texels t, each texel seen by its own rows: the scalars' block of
    `(J^T J)^-1` (their covariance with the texels fitted too) equals the held inverse plus
    `traded_inverse` of the Schur term, with H_tt exactly diagonal."""
    rng = np.random.default_rng(seed)
    p, q, rows = 3, 12, 5
    js = rng.normal(size=(q * rows, p))
    jt = np.zeros((q * rows, q))
    for i in range(q):  # texel i: rows of its own
        jt[i * rows : (i + 1) * rows, i] = rng.normal(size=rows)
    j = np.hstack([js, jt])
    marginal = np.linalg.inv(j.T @ j)[:p, :p]
    h = js.T @ js
    a = jt.T @ js
    trade = a.T @ (a / np.diag(jt.T @ jt)[:, None])
    assert np.linalg.eigvalsh(h - trade).min() > 0  # the rows keep every scalar determined
    held = np.linalg.inv(h)
    np.testing.assert_allclose(held + traded_inverse(trade, held), marginal, rtol=1e-8)


def test_a_noisy_trade_is_cut_to_a_positive_bounded_inflation():
    """A trade estimate with a negative direction adds nothing there, and one past the curvature
    inflates the variance by at most `1 / (1 - MAX_TRADE)`."""
    h = np.diag([4.0, 1.0])
    inverse = np.linalg.inv(h)
    extra = traded_inverse(np.diag([-3.0, 5.0]), inverse)
    assert np.linalg.eigvalsh(extra).min() >= -1e-12
    assert extra[0, 0] == pytest.approx(0.0, abs=1e-12)
    assert 1.0 + extra[1, 1] == pytest.approx(1.0 / (1.0 - MAX_TRADE))


def pigment_texture_problem(width: int = 12, height: int = 12):
    """The glazed sphere's first view, small, its pigment a free 4x4 texture beside its ior;
    the solver's vector at the start (the truth)."""
    cfg = load_render_config(ROOT / "configs" / "glazed-sphere.toml")
    camera = dataclasses.replace(cfg.scene.cameras[0], width=width, height=height)
    scene = dataclasses.replace(cfg.scene, cameras=(camera,))
    image = render(load_scene(scene_dict(scene, cfg.material, 0, 64)), 256, seed=5)
    capture = Capture(scene, [View("v", image, np.ones((height, width), np.float32), camera)])
    material = with_free_textures(cfg.material, {"glaze.pigment": (4, 4)})
    problem = Problem(capture, material, resolve(material, ["glaze.pigment", "glaze.ior"]))
    return problem, problem.unconstrained({f.key: f.start for f in problem.free})


def test_a_stop_asked_for_ends_the_trade_before_its_renders():
    """A Ctrl-C during the uncertainty's trade stops it before the next reverse pass."""
    problem, u = pigment_texture_problem(4, 4)
    jac = np.ones((4 * 4 * 3, 1))
    with pytest.raises(KeyboardInterrupt):
        texel_trade(problem, u, (jac, jac), 4, 0, h=np.ones(problem.n_material), stop=lambda: True)


def test_the_trade_matches_the_texels_rendered_jacobian():
    """The glazed sphere's pigment as a 4x4 texture beside the glaze's ior (a higher ior reflects
    more and lets less through to the pigment): the trade from one reverse pass per Jacobian
    column and the curvature's probes against the texels' Jacobian rendered row by row (one
    reverse pass per pixel channel, 432 of them), `a^T diag(J_t^T J_t)^-1 a`."""
    problem, u = pigment_texture_problem()
    held, take, _ = problem.holding_textures(u)
    jac1 = finite_rows(*linearised(held, take(u), 64, 1))[1]
    jac2 = finite_rows(*linearised(held, take(u), 64, 2))[1]
    # one seed's trade is within about 35 % of its mean (0.0082-0.0172 over seeds 3-6 here):
    # their mean against the rendered Jacobian's
    trades = [texel_trade(problem, u, (jac1, jac2), 64, seed) for seed in (3, 4, 5, 6)]
    assert all(t.shape == (1, 1) for t in trades)
    trade = np.mean(trades, axis=0)

    renderer = problem.renderer(1)
    values = np.asarray(problem.values(u)["glaze.pigment"] + [problem.values(u)["glaze.ior"]])
    scale = residual_scale(problem, u)
    rows = []
    for p in range(scale.size):
        cotangent = np.zeros(scale.size, np.float32)
        cotangent[p] = scale[p]
        rows.append(renderer.vjp(values.astype(np.float32), 100 + p, 256, cotangent)[:48])
    jt = np.asarray(rows, np.float64)  # d(weighted residual) / d(texel)
    diagonal = np.sum(jt**2, axis=0)
    seen = diagonal > 0
    a = jt[:, seen].T @ (0.5 * (jac1 + jac2))
    expected = float((a.T @ (a / diagonal[seen, None]))[0, 0])
    assert expected > 0.1 * float(np.sum(jac1 * jac2))  # ior and the pigment do trade
    # measured: the mean 0.0126 against 0.0101 (the Jacobians of seeds 5 and 6: 0.0088 against
    # 0.0072); with the glaze's lobes sampled at their weight estimate alone 0.0090 against 0.0080
    assert trade[0, 0] == pytest.approx(expected, rel=0.35)


def test_texels_on_a_bound_trade_too():
    """A mask's fitted texels reach 0 and 1, and each still trades with the scalars (the data
    hold it there, but would take it a little inside as well): the pigment texture with every
    texel on its lower bound trades with the ior. Held there, as an active bound, the stained
    torus's glaze pigment ended 7-10 sd off."""
    problem, _ = pigment_texture_problem(8, 8)
    u = problem.unconstrained({"glaze.pigment": [0.0] * 48, "glaze.ior": 1.5})
    assert np.all(np.asarray(problem.values(u)["glaze.pigment"]) < 2e-3)  # on the bound
    held, take, _ = problem.holding_textures(u)
    jac1 = finite_rows(*linearised(held, take(u), 32, 1))[1]
    jac2 = finite_rows(*linearised(held, take(u), 32, 2))[1]
    trade = texel_trade(problem, u, (jac1, jac2), 32, 3)
    assert trade.shape == (1, 1) and trade[0, 0] > 0.05 * float(np.sum(jac1 * jac2)), trade
