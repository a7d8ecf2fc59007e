"""The fit problems the benchmarks time: a one-view sphere against its own render, and the
recovery sweep's cases from its common start."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .common import DEFAULT_SCENE

#: The free keys of `sphere_problem`.
LONG_KEYS = ("glaze.pigment", "glaze.roughness", "glaze.ior")


def sphere_problem(size: int, config: Path = DEFAULT_SCENE, target_spp: int = 64):
    """A one-view `size`^2 fit of `config`'s material (pigment, roughness, ior free) against its
    own render at `target_spp`."""
    import dataclasses

    from captures.capture import Capture, View

    from ..config import load_render_config
    from ..material import resolve
    from ..render import load_scene, render, scene_dict
    from ..solvers import Problem

    cfg = load_render_config(config)
    camera = dataclasses.replace(cfg.scene.cameras[0], width=size, height=size)
    scene = dataclasses.replace(cfg.scene, cameras=(camera,))
    target = render(load_scene(scene_dict(scene, cfg.material, 0, target_spp)), target_spp, 99)
    capture = Capture(scene, [View("v", target, np.ones((size, size), np.float32), camera)])
    return Problem(capture, cfg.material, resolve(cfg.material, list(LONG_KEYS)))


def recovery_problem(capture):
    """A fit of `capture` (a `fit.recovery` capture) from the recovery sweep's start, its
    renderers at full and half resolution already built (their scenes loaded)."""
    from .. import recovery
    from ..material import resolve
    from ..solvers import Problem

    material = recovery.glaze(recovery.START)
    problem = Problem(capture, material, resolve(material, list(recovery.KEYS)))
    for downscale in (1, 2):
        problem.renderer(downscale)
    return problem


def relative_errors(values: dict, truth: dict) -> dict[str, float]:
    """Each recovery key's largest relative error (over its channels) of `values` to `truth`."""
    from .. import recovery

    return {
        k: float(np.max(np.abs(np.subtract(values[k], truth[k])) / np.abs(truth[k])))
        for k in recovery.KEYS
    }
