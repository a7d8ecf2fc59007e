"""The renders' sampler: stratified per pixel, exact sample counts, unbiased, independent seeds."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import mitsuba as mi
import numpy as np
import pytest

from fit.config import load_render_config
from fit.render import load_scene, render, scene_dict
from fit.render.scene import SAMPLER, sample_count

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize("spp", [*range(1, 70), 127, 128, 255, 256, 1000, 16384])
def test_sample_count_is_what_the_sampler_renders(spp):
    n = sample_count(spp)
    sampler = mi.load_dict({"type": SAMPLER, "sample_count": n})
    assert sampler.sample_count() == n
    assert spp <= n < spp + max(1, math.isqrt(spp))


def sphere_scene(sampler: str, width: int = 64, height: int = 48):
    cfg = load_render_config(ROOT / "configs" / "glazed-sphere.toml")
    camera = dataclasses.replace(cfg.scene.cameras[0], width=width, height=height)
    scene = scene_dict(dataclasses.replace(cfg.scene, cameras=(camera,)), cfg.material, 0, 16)
    scene["sensor"]["sampler"]["type"] = sampler
    return load_scene(scene)


def test_the_sampler_is_unbiased_and_quieter_than_independent_with_independent_seeds():
    reference = render(sphere_scene("independent"), 4096, seed=10_000)
    seeds = range(8)
    strata = np.stack([render(sphere_scene(SAMPLER), 16, seed=s) for s in seeds])
    plain = np.stack([render(sphere_scene("independent"), 16, seed=s) for s in seeds])
    # unbiased: the image sum of 8 x 16 spp sits on the reference's within the two's noise
    error = strata.mean(0) - reference
    noise = strata.var(0, ddof=1) / len(seeds) + plain.var(0, ddof=1) * 16 / 4096
    assert abs(error.sum()) < 4 * np.sqrt(noise.sum())
    # quieter: the summed per-pixel variance at 16 spp (measured 5.9-6.5x lower on this sphere)
    assert strata.var(0, ddof=1).sum() < plain.var(0, ddof=1).sum() / 3
    # seeds independent: two renders' noise is uncorrelated
    a, b = (strata[0] - reference).ravel(), (strata[1] - reference).ravel()
    assert abs(np.corrcoef(a, b)[0, 1]) < 0.1
