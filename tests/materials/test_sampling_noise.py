"""A narrow glaze lobe gets its share of BSDF samples: the noise of a glossy highlight."""

from __future__ import annotations

import mitsuba as mi
import numpy as np
import pytest

import materials.glaze as glaze


def sphere_under_a_small_light(alpha: float, ior: float = 1.5) -> mi.Scene:
    """A grey-glazed sphere seen from the front, lit by a 1.2 x 0.8 rectangle above to the right
    and a dim constant environment (the Cycles sphere's studio), 48x36 pixels."""
    light = mi.ScalarTransform4f().look_at(origin=[3, -2.5, 3], target=[0, 0, 0], up=[0, 0, 1])
    return mi.load_dict(
        {
            "type": "scene",
            "integrator": {"type": "path", "max_depth": 3},
            "sensor": {
                "type": "perspective",
                "fov": 30,
                "to_world": mi.ScalarTransform4f().look_at(
                    origin=[0, -5, 1.2], target=[0, 0, 0], up=[0, 0, 1]
                ),
                "film": {"type": "hdrfilm", "width": 48, "height": 36, "rfilter": {"type": "box"}},
            },
            "ball": {
                "type": "sphere",
                "bsdf": {
                    "type": "glaze",
                    "roughness": alpha,
                    "ior": ior,
                    "pigment": {"type": "rgb", "value": [0.3, 0.3, 0.3]},
                },
            },
            "light": {
                "type": "rectangle",
                "to_world": light @ mi.ScalarTransform4f().scale([0.6, 0.4, 1]),
                "emitter": {"type": "area", "radiance": {"type": "rgb", "value": 200.0}},
            },
            "sky": {"type": "constant", "radiance": {"type": "rgb", "value": 0.06}},
        }
    )


def relative_variance(scene: mi.Scene, spp: int = 16, renders: int = 12) -> float:
    """The renders' summed per-pixel variance over their mean's summed squares."""
    images = np.stack([np.asarray(mi.render(scene, spp=spp, seed=s)) for s in range(renders)])
    return float(images.var(axis=0, ddof=1).sum() / (images.mean(axis=0) ** 2).sum())


@pytest.mark.parametrize(("alpha", "ratio"), [(0.01, 2.5), (0.02, 2.0), (0.05, 1.3)])
def test_a_narrow_lobe_s_highlight_is_sampled_through_the_bsdf(alpha, ratio, monkeypatch):
    """Sampled at the lobes' weight estimate alone (Fresnel against the pigment: 0.12 here), a
    narrow lobe's highlight got a few BSDF samples a pixel, and emitter sampling cannot find a
    lobe narrower than the light: its noise made a 16-spp gradient's Newton step swing by more
    than alpha itself. With the narrow lobe's share the image's relative variance is lower by
    `ratio` or more (measured here 4.4x at alpha 0.01, 3.4x at 0.02, 1.9x at 0.05, 1.1x at
    0.1; 2.7x at 0.02 on the recovery sweep's sphere)."""
    scene = sphere_under_a_small_light(alpha)
    shared = relative_variance(scene)
    monkeypatch.setattr(glaze, "_NARROW_LOBE_PROB", 0.0)
    weight_only = relative_variance(sphere_under_a_small_light(alpha))
    assert weight_only > ratio * shared, (weight_only, shared)


def test_a_rough_lobe_keeps_the_weight_estimate(monkeypatch):
    """At alpha 0.3, past `_WIDE_ALPHA`, the share is none: the same renders either way."""
    scene = sphere_under_a_small_light(0.3)
    image = np.asarray(mi.render(scene, spp=4, seed=1))
    monkeypatch.setattr(glaze, "_NARROW_LOBE_PROB", 0.0)
    again = np.asarray(mi.render(sphere_under_a_small_light(0.3), spp=4, seed=1))
    np.testing.assert_array_equal(image, again)
