"""Near the bounds on a render: a fit started next to a bound (where the transform puts a start
at the bound) moves inward; emitter scales at their bounds render and differentiate."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from fit.bench import sphere_problem
from fit.material import resolve
from fit.solvers import solve
from materials.params import EMITTER_PARAMS, GLAZE

ROOT = Path(__file__).resolve().parents[2]
TRUTH = {"glaze.pigment": [0.1, 0.22, 0.55], "glaze.roughness": 0.0625, "glaze.ior": 1.52}


@pytest.fixture(scope="module")
def problem():
    return sphere_problem(32, ROOT / "configs" / "glazed-sphere.toml")


#: Not alpha from its lower bound: there the gradient has the right sign in expectation but
#: Monte Carlo noise swamps it on this problem (measured at alpha 0.011, 8 x 256 spp: dL/dalpha
#: -348 +- 160; Adam moved it inward for at most 2 of 5 seeds at 4 spp, 40 or 300 steps, and
#: 0 of 3 at 64 spp: README "Bounds").
CASES = [("roughness", "upper"), ("ior", "lower"), ("ior", "upper")]


@pytest.mark.parametrize("key, bound", CASES, ids=[f"{k}-{b}" for k, b in CASES])
def test_fit_from_a_bound_moves_inward(problem, key, bound):
    """One parameter starts at a bound (so BOUND_MARGIN inside it), the others at the truth: 40
    Adam steps (lr 0.1, 4 spp) move it toward the truth in the solver's space by at least five
    steps' worth, to at least twice its start's distance from the bound, all finite. (Measured,
    seeds 0-4: alpha from 1 moved 2.6 to 3.8 units, ior from 1.01 3.9 to 4.3.)"""
    spec = GLAZE.params[key]
    u_truth = problem.unconstrained(TRUTH)
    u0 = problem.unconstrained({**TRUTH, f"glaze.{key}": getattr(spec, bound)})
    (i,) = np.flatnonzero(u0 != u_truth)
    result = solve("adam", problem, u0, steps=40, spp=4, seed=3, lr=0.1)
    assert np.all(np.isfinite(result.u)) and result.reports[0].rejected == 0
    moved = abs(u0[i] - u_truth[i]) - abs(result.u[i] - u_truth[i])
    assert moved > 0.5, f"{key} from its {bound} bound: moved {moved:.2f} toward the truth"
    began = problem.values(u0)[f"glaze.{key}"]
    end = result.values[f"glaze.{key}"]
    side = getattr(spec, bound)
    assert abs(end - side) > 2 * abs(began - side), (began, end)


def test_emitter_scales_at_their_bounds(problem):
    """The declared emitter scales at each bound: the render and its Jacobian are finite, and the
    image is linear in them (every path ends on one emitter), so with the image's own seed
    `sum_k s_k dI/ds_k` equals the image (Euler), a Jacobian that is neither zero nor off.

    Not to the last pixel: a frozen replay of the Jacobian's forward pass can differ from its
    recording at a pixel (measured, 2026-12-05: in most runs one of 3072 values 0.3 % off, the
    environment's column, where the recording, the first level's first column, is exact;
    not explained). At most one value in a thousand may miss, by at most 1 %."""
    from fit.render import Renderer

    free = resolve(problem.material, [f"{name}.scale" for name in EMITTER_PARAMS])
    renderer = Renderer(problem.capture, problem.material, free)
    for level in ("lower", "upper"):
        scales = np.array([getattr(s, level) for s in EMITTER_PARAMS.values()], np.float32)
        image, jac = renderer.jacobian(scales, 5, 4)
        assert np.all(np.isfinite(image)) and np.all(np.isfinite(jac)), level
        assert np.all(np.abs(jac).max(axis=0) > 0), f"{level}: a scale does not act"
        error = np.abs(jac @ scales - image)
        off = error > 1e-3 * np.abs(image) + 1e-4 * image.max()
        assert off.mean() <= 1e-3, f"{level}: {off.sum()} of {off.size} values off"
        assert np.all(error <= 1e-2 * np.abs(image) + 1e-4 * image.max()), level
