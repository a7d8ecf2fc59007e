"""Whole renders: a constant-mask stack renders like `blendbsdf`, and gradients flow through the
stack (its `dr.switch`) inside `prb`'s loops to mask, layer and bump parameters."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from fit.config import load_render_config
from fit.render import MATERIAL_PREFIX, load_scene, render, scene_dict

ROOT = Path(__file__).resolve().parents[2]
CLAY = {
    "type": "oren_nayar",
    "sigma": 0.4,
    "reflectance": {"type": "rgb", "value": [0.6, 0.45, 0.3]},
}
GLAZE = {"type": "glaze", "roughness": 0.1, "pigment": {"type": "rgb", "value": [0.1, 0.2, 0.6]}}


def small_scene(config="glazed-sphere.toml", size=48):
    cfg = load_render_config(ROOT / "configs" / config)
    camera = dataclasses.replace(
        cfg.scene.cameras[0],
        width=size,
        height=size * 3 // 4 if config == "glazed-sphere.toml" else size,
    )
    return cfg, dataclasses.replace(cfg.scene, cameras=(camera,))


def test_constant_mask_stack_renders_like_blendbsdf():
    _, scene = small_scene()
    stack = {
        "type": "layered",
        "layers": "clay,glaze",
        "clay": CLAY,
        "glaze": GLAZE,
        "glaze_mask": 0.3,
    }
    blend = {"type": "blendbsdf", "weight": 0.3, "a": CLAY, "b": GLAZE}
    a = render(load_scene(scene_dict(scene, stack, 0, 64)), 512, seed=1)
    b = render(load_scene(scene_dict(scene, blend, 0, 64)), 512, seed=1000)
    c = render(load_scene(scene_dict(scene, blend, 0, 64)), 512, seed=2000)
    assert a.sum() / b.sum() == pytest.approx(1.0, abs=0.01)
    # the stack differs from blendbsdf no more than blendbsdf differs from itself (noise)
    assert np.abs(a - b).mean() < 1.3 * np.abs(c - b).mean()


def test_cup_gradients_flow_through_the_stack():
    """`dr.backward` through a prb render of the cup reaches every kind of parameter, finite."""
    cfg, scene = small_scene("cup.toml", size=32)
    loaded = load_scene(scene_dict(scene, cfg.material, 0, 8))
    params = mi.traverse(loaded)
    keys = [
        "glaze.mask.threshold",
        "lime.mask.softness",
        "glaze.roughness",
        "glaze.normal_noise",
        "clay.sigma",
        "stain.reflectance.value",
        "bump",
    ]
    for key in keys:
        dr.enable_grad(params[MATERIAL_PREFIX + key])
    params.update()
    image = mi.render(loaded, params, spp=8, seed=3)
    dr.backward(dr.mean(image))
    for key in keys:
        grad = np.asarray(dr.grad(params[MATERIAL_PREFIX + key]))
        assert np.all(np.isfinite(grad)) and np.any(grad != 0), (key, grad)
