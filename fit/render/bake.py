"""Bake a texture (an fbm mask, a bitmap) to an image in UV space, for reports and exports."""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np


def bake_texture(texture: dict, width: int = 256, height: int = 256) -> np.ndarray:
    """The (height, width) values of a scalar texture dict (e.g. a layer's `fbm` mask) at the
    texel centres of a UV grid, laid out as Mitsuba's `bitmap` reads an image (row r at
    v = (r + 0.5) / height): written as a bitmap, the baked image is the texture again."""
    loaded = mi.load_dict(texture)
    u = (np.arange(width) + 0.5) / width
    v = (np.arange(height) + 0.5) / height
    uu, vv = np.meshgrid(u, v)
    si = dr.zeros(mi.SurfaceInteraction3f, uu.size)
    si.uv = mi.Point2f(uu.ravel().astype(np.float32), vv.ravel().astype(np.float32))
    values = loaded.eval_1(si)
    return np.asarray(values, np.float32).reshape(height, width)
