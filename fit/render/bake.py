"""Bake a texture (an fbm mask, a bitmap) to an image in UV space, for reports and exports."""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

#: Texels evaluated at once: a band of rows this large, then the next (a 16384-texel square in
#: one go held a surface interaction per texel, tens of GB).
BAND_TEXELS = 1 << 20


def uv_bands(width: int, height: int):
    """(first row, surface interactions at the texel centres of rows from it) of a width x
    height UV grid in bands of at most `BAND_TEXELS`, laid out as Mitsuba's `bitmap` reads an
    image (row r at v = (r + 0.5) / height)."""
    rows = max(1, BAND_TEXELS // max(width, 1))
    u = ((np.arange(width) + 0.5) / width).astype(np.float32)
    for first in range(0, height, rows):
        v = ((np.arange(first, min(first + rows, height)) + 0.5) / height).astype(np.float32)
        uu, vv = np.meshgrid(u, v)
        si = dr.zeros(mi.SurfaceInteraction3f, uu.size)
        si.uv = mi.Point2f(uu.ravel(), vv.ravel())
        si.wi = mi.Vector3f(0, 0, 1)
        yield first, si


def bake_texture(texture: dict, width: int = 256, height: int = 256) -> np.ndarray:
    """The (height, width) values of a scalar texture dict (e.g. a layer's `fbm` mask) at the
    texel centres of a UV grid, laid out as Mitsuba's `bitmap` reads an image (row r at
    v = (r + 0.5) / height): written as a bitmap, the baked image is the texture again."""
    loaded = mi.load_dict(texture)
    out = np.empty((height, width), np.float32)
    for first, si in uv_bands(width, height):
        values = np.asarray(loaded.eval_1(si), np.float32).reshape(-1, width)
        out[first : first + len(values)] = values
    return out


def texel_index(u: np.ndarray, v: np.ndarray, width: int, height: int) -> tuple:
    """(rows, columns) of the texels of a width x height UV grid laid out as `bake_texture`'s
    (and as Mitsuba's `bitmap` reads an image) that UV points fall in, wrapped into [0, 1)."""
    cols = np.minimum(((np.asarray(u) % 1.0) * width).astype(int), width - 1)
    rows = np.minimum(((np.asarray(v) % 1.0) * height).astype(int), height - 1)
    return rows, cols


def seen_texels(scene, width: int, height: int, supersample: int = 2) -> np.ndarray:
    """Which texels of a width x height UV grid (laid out as `bake_texture`'s) the scene's
    cameras see: (height, width) booleans, a texel seen where a ray through a pixel (on a
    `supersample` x `supersample` grid in each) first meets the object from its front, through
    one bare scene of the object (lights left out, `bare_scene`)."""
    from .scene import bare_scene

    loaded = bare_scene(scene, scene.cameras)
    seen = np.zeros((height, width), bool)
    for camera, sensor in zip(scene.cameras, loaded.sensors(), strict=True):
        nx, ny = camera.width * supersample, camera.height * supersample
        x, y = np.meshgrid((np.arange(nx) + 0.5) / nx, (np.arange(ny) + 0.5) / ny)
        position = mi.Point2f(x.ravel().astype(np.float32), y.ravel().astype(np.float32))
        ray, _ = sensor.sample_ray(0.0, 0.5, position, mi.Point2f(0.5))
        si = loaded.ray_intersect(ray)
        front = np.asarray(si.is_valid()) & (np.asarray(si.wi.z) > 0)
        uv = np.asarray(si.uv)
        seen[texel_index(uv[0][front], uv[1][front], width, height)] = True
    return seen
