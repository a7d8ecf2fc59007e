"""The `texels` texture reads a file as Mitsuba's `bitmap` does (layout, bilinear lookup,
wrapping, sRGB decoding of 8-bit files unless raw), and its texels get derivatives."""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np
import OpenImageIO as oiio
import pytest

from captures.images import write_image


def write_png(path, texels: np.ndarray) -> None:
    out = oiio.ImageOutput.create(str(path))
    height, width, channels = texels.shape
    out.open(str(path), oiio.ImageSpec(width, height, channels, oiio.UINT8))
    out.write_image(np.round(texels * 255).astype(np.uint8))
    out.close()


def interactions(uv: np.ndarray):
    si = dr.zeros(mi.SurfaceInteraction3f, len(uv))
    si.uv = mi.Point2f(uv[:, 0], uv[:, 1])
    return si


@pytest.mark.parametrize(("channels", "suffix"), [(1, "exr"), (3, "exr"), (3, "png")])
@pytest.mark.parametrize("raw", [False, True])
def test_texels_read_a_file_as_the_bitmap_does(tmp_path, channels, suffix, raw):
    rng = np.random.default_rng(channels)
    texels = rng.uniform(0, 1, (5, 7, channels)).astype(np.float32)  # not square: no transposes
    path = tmp_path / f"t.{suffix}"
    write_png(path, texels) if suffix == "png" else write_image(path, texels)
    bitmap = mi.load_dict({"type": "bitmap", "filename": str(path), "raw": raw})
    ours = mi.load_dict({"type": "texels", "filename": str(path), "raw": raw})
    si = interactions(rng.uniform(-1.5, 2.5, (2000, 2)))  # wrapping on both sides
    np.testing.assert_allclose(ours.eval(si), bitmap.eval(si), atol=2e-6)
    np.testing.assert_allclose(ours.eval_1(si), bitmap.eval_1(si), atol=2e-6)
    assert mi.traverse(ours)["data"].shape == (5, 7, channels)


def test_texels_get_the_gradient_of_their_bilinear_weights(tmp_path):
    write_image(tmp_path / "t.exr", np.zeros((2, 4, 1), np.float32))
    texture = mi.load_dict({"type": "texels", "filename": str(tmp_path / "t.exr")})
    params = mi.traverse(texture)
    data = params["data"]
    dr.enable_grad(data)
    params.update()
    # u = 0.25 falls halfway between columns 0 and 1 (0.25 * 4 - 0.5), v = 0.25 on row 0's centre
    value = texture.eval_1(interactions(np.array([[0.25, 0.25]])))
    dr.backward(value)
    grad = np.asarray(dr.grad(data)).reshape(2, 4)
    np.testing.assert_allclose(grad, [[0.5, 0.5, 0, 0], [0, 0, 0, 0]], atol=1e-6)
