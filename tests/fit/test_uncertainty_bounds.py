"""The uncertainty near a bound: a coordinate's units (its transform's slope) do not make it
undetermined, and a value that ended at a bound is named."""

from __future__ import annotations

import numpy as np
import pytest

from fit.material import Free, at_bounds, bound_note, to_physical
from fit.solvers.uncertainty import inverse_determined, transform_jacobian, transform_slope
from materials.params import IOR, PIGMENT, ROUGHNESS, SCALE


def _curvature(columns: int = 5, seed: int = 0) -> np.ndarray:
    a = np.random.default_rng(seed).normal(size=(200, columns))
    return a.T @ a


@pytest.mark.parametrize("slope", [1.0, 1e-3, 1e-6])
def test_a_coordinates_units_do_not_make_it_undetermined(slope):
    """A well-conditioned curvature with one coordinate scaled by a transform's slope (ior at
    1.011 of [1.01, 3]: 0.001; its curvature 1e-6 of the others'): every coordinate determined
    and the inverse the exact one. Unscaled, a floor at 1e-9 of the largest eigenvalue cut the
    small one (at slope 1e-6 its eigenvalue is 1e-12 of the largest)."""
    d = np.diag([1.0, 1.0, 1.0, 1.0, slope])
    h = d @ _curvature() @ d
    inverse, undetermined = inverse_determined(h)
    assert not undetermined.any()
    np.testing.assert_allclose(inverse, np.linalg.inv(h), rtol=1e-6)


def test_collinear_or_noise_only_coordinates_stay_undetermined():
    """Two coordinates acting identically (whatever their scale) leave both undetermined and
    the others determined; a coordinate whose own curvature is not positive (a noisy cross
    product) is undetermined though the matrix's other eigenvalues are fine."""
    a = np.random.default_rng(1).normal(size=(200, 4))
    a[:, 3] = 1e-4 * a[:, 2]
    _, undetermined = inverse_determined(a.T @ a)
    assert undetermined.tolist() == [False, False, True, True]
    h = _curvature(3)
    h[2, :] = h[:, 2] = 0.0
    h[2, 2] = -1e-3
    inverse, undetermined = inverse_determined(h)
    assert undetermined.tolist() == [False, False, True]
    assert not inverse[2].any() and not inverse[:, 2].any()
    np.testing.assert_allclose(inverse[:2, :2], np.linalg.inv(h[:2, :2]), rtol=1e-9)


def _free(*specs) -> list[Free]:
    return [Free(f"glaze.{s.key}", s.key, s) for s in specs]


def test_values_at_a_bound_are_named_per_component():
    """ior at 1.011 (lower), one pigment channel at 0.9999 (upper), a light scale at 0.1001 (its
    log-space lower bound); interior values and textures are not named."""
    free = [*_free(PIGMENT, ROUGHNESS, IOR), Free("lights.scale", None, SCALE)]
    free.append(Free("glaze.mask.texture", "mask", PIGMENT, shape=(2, 2, 1)))
    values = {
        "glaze.pigment": [0.3, 0.9999, 0.5],
        "glaze.roughness": 0.05,
        "glaze.ior": 1.011,
        "lights.scale": 0.1001,
        "glaze.mask.texture": [0.0, 1.0, 0.0, 1.0],
    }
    found = at_bounds(free, values)
    assert [(e["parameter"], e["bound"]) for e in found] == [
        ("glaze.pigment[1]", "upper"),
        ("glaze.ior", "lower"),
        ("lights.scale", "lower"),
    ]
    assert found[1]["range"] == [1.01, 3.0] and found[1]["value"] == 1.011
    note = bound_note(found[1])
    assert note.startswith("glaze.ior ended at its lower bound (1.011; range 1.01 to 3)")
    assert "local minimum" in note and "--starts 4" in note
    assert "more starts" in bound_note(found[1], starts=4)
    assert at_bounds(free[:3], {**values, "glaze.pigment": [0.3] * 3, "glaze.ior": 1.5}) == []


def test_transform_derivatives_are_the_transforms_slopes():
    """`transform_jacobian` is diagonal with `transform_slope` on it, both the central
    differences of `to_physical` (a sigmoid, a log-sigmoid, an RGB colour); free parameters
    sized alike but declared otherwise (ior for alpha) get their own slopes, not another's."""
    u = np.asarray([0.3, -1.2, 0.8, 0.4, 1.1, -0.5], np.float32)
    eps = 1e-3
    for free in (
        [*_free(PIGMENT, ROUGHNESS, IOR), Free("lights.scale", None, SCALE)],
        [*_free(PIGMENT, IOR, ROUGHNESS), Free("lights.scale", None, SCALE)],
    ):
        u64 = u.astype(np.float64)
        numeric = np.asarray(
            [
                (to_physical(free, u64 + eps * e) - to_physical(free, u64 - eps * e)) / (2 * eps)
                for e in np.eye(len(u))
            ]
        ).T
        jacobian = transform_jacobian(free, u)
        np.testing.assert_allclose(jacobian, numeric, rtol=1e-3, atol=1e-6)
        np.testing.assert_allclose(transform_slope(free, u), np.diag(numeric), rtol=1e-3)
