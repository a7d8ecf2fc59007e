"""Rendering: Mitsuba scenes from a `captures.Scene` and a material, forward renders in passes,
the `Renderer` of a capture's views (render, VJP, Jacobian) and the one JAX <-> Dr.Jit bridge.
Import after the Mitsuba variant is chosen (`fit.variant.select_variant`)."""

from .bake import bake_texture, seen_texels
from .bridge import make_render
from .image import render
from .renderer import GRAD_SEED_OFFSET, Renderer
from .scene import MATERIAL_PREFIX, coverage_dict, load_scene, material_keys, scene_dict

__all__ = [
    "GRAD_SEED_OFFSET",
    "MATERIAL_PREFIX",
    "Renderer",
    "bake_texture",
    "coverage_dict",
    "load_scene",
    "make_render",
    "material_keys",
    "render",
    "scene_dict",
    "seen_texels",
]
