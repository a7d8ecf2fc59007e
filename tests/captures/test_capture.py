"""Captures: RAW development, readers, validity weights, resampling, manifests and bad input."""

from __future__ import annotations

import dataclasses
import json
import logging
from pathlib import Path

import numpy as np
import pytest

from captures import CaptureError
from captures.capture import load_capture, manifest_text
from captures.images import read_linear, write_image
from captures.importers import diligent_capture, fit_sphere_to_mask, peer_capture
from captures.raw import develop, read_raw, white_balance_from_patch
from captures.weights import downscale, validity

# Neutral patches of colorchart.dng (../shared/data/README.md), full-resolution coordinates
PATCH_Y, PATCH_X = 928, (704, 820, 936, 1048, 1164, 1276)


def patch(image, x, y=PATCH_Y, half=6):
    """Mean of a 24 px box (12 superpixels) of the half-resolution development."""
    return (
        image[y // 2 - half : y // 2 + half, x // 2 - half : x // 2 + half].reshape(-1, 3).mean(0)
    )


@pytest.fixture(scope="module")
def chart(shared_data):
    return read_raw(shared_data / "raw" / "colorchart.dng")


def test_raw_is_linear_black_removed_in_unit_range(chart):
    cam = chart.camera_rgb
    assert cam.shape == (578, 867, 3)  # 1734x1156 visible, 2x2 superpixels
    assert cam.min() >= 0 and cam.max() <= 1
    # black level removed: the black patch is near 0, the white patch well above it
    assert patch(cam, PATCH_X[-1]).max() < 0.01 < patch(cam, PATCH_X[0]).min()
    # linear: the neutral row's camera ratios are those the data README reports
    white = patch(cam, PATCH_X[0])
    assert white[0] / white[1] == pytest.approx(0.69, abs=0.02)
    assert white[2] / white[1] == pytest.approx(0.44, abs=0.02)


def test_as_shot_white_balance_is_rawpys(chart, shared_data):
    import rawpy

    with rawpy.imread(str(shared_data / "raw" / "colorchart.dng")) as raw:
        reported = np.array(raw.camera_whitebalance[:3])
    np.testing.assert_allclose(chart.camera_wb, reported / reported[1])
    developed = develop(chart, "camera")
    expected = np.clip((chart.camera_rgb * chart.camera_wb) @ chart.color_matrix.T, 0, None)
    np.testing.assert_allclose(developed, expected, rtol=1e-5, atol=1e-7)


def test_white_patch_balance_makes_greys_neutral(chart):
    """White balance from the white patch: the next three greys neutral within 8 % (measured:
    R/G 0.973, 0.953, 0.938; B/G 1.011, 1.000, 0.991) in balanced camera RGB. The colour matrix
    then amplifies the residual (flare in dim light) to 5-13 % in Rec.709."""
    multipliers = white_balance_from_patch(chart, PATCH_X[0] // 2, PATCH_Y // 2)
    balanced = chart.camera_rgb * multipliers
    white = patch(balanced, PATCH_X[0])
    assert white[0] / white[1] == pytest.approx(1.0, abs=1e-4)
    for x in PATCH_X[1:4]:
        grey = patch(balanced, x)
        assert grey[0] / grey[1] == pytest.approx(1.0, abs=0.08), x
        assert grey[2] / grey[1] == pytest.approx(1.0, abs=0.08), x


@pytest.mark.parametrize(
    "name, message",
    [
        ("stub_CanonRaw.cr2", "LibRaw cannot decode"),
        ("stub_CanonRaw.cr3", "LibRaw cannot decode"),
        ("stub_FujiFilm.raf", "LibRaw cannot decode"),
        ("stub_Nikon.nef", "LibRaw cannot decode"),
        ("stub_DNG.dng", "holds no usable picture"),
        ("stub_Panasonic.rw2", "holds no usable picture"),
    ],
)
def test_raw_stubs_are_clear_errors(shared_data, name, message):
    with pytest.raises(CaptureError) as err:
        read_raw(shared_data / "raw" / name)
    assert name in str(err.value) and message in str(err.value)


def test_readers_decode_as_declared(tmp_path):
    linear = np.linspace(0, 1, 64 * 3, dtype=np.float32).reshape(8, 8, 3)
    write_image(tmp_path / "a.exr", linear)
    write_image(tmp_path / "a.png", linear)  # 16-bit sRGB-encoded
    exr, sat_exr, _ = read_linear(tmp_path / "a.exr", "linear")
    png, sat_png, warnings = read_linear(tmp_path / "a.png", "srgb")
    np.testing.assert_array_equal(exr, linear)
    np.testing.assert_allclose(png, linear, atol=1e-4)
    assert not sat_exr.any() and sat_png[-1, -1] and not warnings
    write_image(tmp_path / "b.jpg", linear)
    _, _, warnings = read_linear(tmp_path / "b.jpg", "linear")
    assert "8-bit data declared linear" in warnings[0]


@pytest.mark.parametrize("channels", [2, 4])
def test_alpha_is_dropped_not_multiplied_in(tmp_path, channels):
    """A PNG with a half-transparent alpha channel (grey + alpha or RGBA) reads as the colours
    it stores, not premultiplied by alpha, with a warning that alpha is ignored."""
    import OpenImageIO as oiio

    stored = np.zeros((4, 6, channels), np.uint16)
    stored[..., :-1] = 30000
    stored[..., -1] = 32768  # alpha 0.5
    path = str(tmp_path / "a.png")
    out = oiio.ImageOutput.create(path)
    spec = oiio.ImageSpec(6, 4, channels, oiio.UINT16)
    spec.attribute("oiio:UnassociatedAlpha", 1)  # store these numbers as they are
    out.open(path, spec)
    out.write_image(stored)
    out.close()
    pixels, _, warnings = read_linear(path, "linear")
    assert pixels.shape == (4, 6, 3)
    np.testing.assert_allclose(pixels, 30000 / 65535, rtol=1e-6)
    assert len(warnings) == 1 and "alpha channel is ignored (24 pixels" in warnings[0]


def _exr(path: Path, names: list[str]) -> Path:
    """A 4x3 half-float EXR whose channel k holds k + 1 everywhere, its channels named."""
    import OpenImageIO as oiio

    spec = oiio.ImageSpec(4, 3, len(names), oiio.HALF)
    spec.channelnames = names
    out = oiio.ImageOutput.create(str(path))
    out.open(str(path), spec)
    out.write_image(
        np.broadcast_to(np.arange(1, len(names) + 1, dtype=np.float32), (3, 4, len(names)))
    )
    out.close()
    return path


@pytest.mark.parametrize(
    "names, expected",
    [
        (["R", "G", "B"], [1, 2, 3]),
        (["r", "g", "b", "a"], [1, 2, 3]),
        (["Y"], [1, 1, 1]),
        (["Y", "A"], [1, 1, 1]),
        (["R"], [1, 1, 1]),  # one channel, named as a tool likes: grey
        (["L", "A"], [1, 1, 1]),
        (["R", "G"], [1, 1, 1]),  # OpenImageIO's names for two channels, alpha not marked
        (["Y", "Z"], [1, 1, 1]),  # grey beside a depth
        (["R", "G", "B", "A", "Z"], [1, 2, 3]),  # a depth beside the image
        # Blender's multi-layer EXR: the Combined pass, other passes beside it ignored
        (["ViewLayer.Combined.R", "ViewLayer.Combined.G", "ViewLayer.Combined.B",
          "ViewLayer.Combined.A", "ViewLayer.Depth.Z"], [1, 2, 3]),
        (["ViewLayer.Normal.X", "ViewLayer.Normal.Y", "ViewLayer.Normal.Z",
          "ViewLayer.Combined.R", "ViewLayer.Combined.G", "ViewLayer.Combined.B",
          "ViewLayer.Diffuse.R", "ViewLayer.Diffuse.G", "ViewLayer.Diffuse.B"], [4, 5, 6]),
        (["Beauty.R", "Beauty.G", "Beauty.B", "Z"], [1, 2, 3]),
        # with the compositor on, Blender writes its output beside the render layer's
        (["Composite.Combined.R", "Composite.Combined.G", "Composite.Combined.B",
          "ViewLayer.Combined.R", "ViewLayer.Combined.G", "ViewLayer.Combined.B"], [1, 2, 3]),
        (["ViewLayer.Combined.R", "ViewLayer.Combined.G", "ViewLayer.Combined.B",
          "Composite.Combined.R", "Composite.Combined.G", "Composite.Combined.B"], [4, 5, 6]),
    ],
)  # fmt: skip
def test_an_exrs_colour_is_read_by_channel_name(tmp_path, names, expected):
    """Other renderers' EXRs keep the image beside other passes (depth, normals) or in a named
    layer; five channels or more were refused, and any three taken as RGB in order."""
    pixels, _, _ = read_linear(_exr(tmp_path / "t.exr", names), "linear")
    assert pixels.shape == (3, 4, 3)
    np.testing.assert_array_equal(pixels[1, 2], np.asarray(expected, np.float32))


@pytest.mark.parametrize(
    "names, message",
    [
        (["X", "Y", "Z"], "channels X, Y, Z .* not RGB"),
        (["Y", "RY", "BY"], "a luminance-chroma image"),
        (["a.R", "a.G", "a.B", "b.R", "b.G", "b.B"], "2 layers hold RGB \\('a', 'b'\\)"),
        (["Depth.Z", "Normal.X", "Normal.Y"], "no RGB or grey"),
        (["U", "V"], "no RGB or grey"),
        (
            [
                "a.Combined.R",
                "a.Combined.G",
                "a.Combined.B",
                "b.Combined.R",
                "b.Combined.G",
                "b.Combined.B",
            ],
            "2 layers hold RGB .* and several are main ones",
        ),
    ],
)
def test_an_exr_without_one_rgb_image_is_refused_by_name(tmp_path, names, message):
    """Values that are not RGB (XYZ colour, luminance-chroma, a vector pass) were taken as RGB;
    a file with several RGB layers and no main one has no answer to guess."""
    path = _exr(tmp_path / "t.exr", names)
    with pytest.raises(CaptureError, match=f"t\\.exr: {message}"):
        read_linear(path, "linear")


def _parts(path: Path, parts: list[tuple[str, list[str]]], alpha: float | None = None) -> Path:
    """A multi-part 4x3 EXR: each (name, channels) part's channel k holds 10 x part + k + 1, an
    A channel `alpha` where given."""
    import OpenImageIO as oiio

    specs = []
    for name, names in parts:
        spec = oiio.ImageSpec(4, 3, len(names), oiio.FLOAT)
        spec.channelnames = names
        spec.attribute("name", name)
        specs.append(spec)
    out = oiio.ImageOutput.create(str(path))
    out.open(str(path), specs)
    for i, (spec, (_, names)) in enumerate(zip(specs, parts, strict=True)):
        if i:
            out.open(str(path), spec, "AppendSubimage")
        values = 10 * i + np.arange(1, len(names) + 1, dtype=np.float32)
        if alpha is not None and "A" in names:
            values[names.index("A")] = alpha
        out.write_image(np.ascontiguousarray(np.broadcast_to(values, (3, 4, len(names)))))
    out.close()
    return path


@pytest.mark.parametrize(
    "parts, expected, warned",
    [
        ([("rgba", ["R", "G", "B", "A"]), ("depth", ["Z"])], [1, 2, 3], False),
        ([("depth", ["Z"]), ("rgba", ["R", "G", "B"])], [11, 12, 13], True),
        ([("depth", ["Z"]), ("normal", ["N.X", "N.Y", "N.Z"]), ("beauty", ["R", "G", "B"])],
         [21, 22, 23], True),
    ],
)  # fmt: skip
def test_a_multi_part_exrs_colour_part_is_read(tmp_path, parts, expected, warned):
    """A multi-part EXR (Nuke, Houdini, another exporter) was read from its first part alone:
    a depth part first was the image, grey, without a word. Its first colour part is read, and
    where that is not the first, a warning names it."""
    pixels, _, warnings = read_linear(_parts(tmp_path / "t.exr", parts), "linear")
    np.testing.assert_array_equal(pixels[1, 2], np.asarray(expected, np.float32))
    assert bool(warnings) == warned
    if warned:
        assert "a multi-part file" in warnings[0] and "'depth' (Z)" in warnings[0]


@pytest.mark.parametrize("alpha, refused", [(1.0, False), (0.0, True)])
def test_the_film_check_reads_the_colour_parts_alpha(tmp_path, alpha, refused):
    """The transparent-film check reads the alpha of the part the colour comes from."""
    from captures.importers import _check_opaque_film

    parts = [("depth", ["Z"]), ("rgba", ["R", "G", "B", "A"])]
    path = _parts(tmp_path / "t.exr", parts, alpha)
    if not refused:
        _check_opaque_film(path, "view")
        return
    with pytest.raises(CaptureError, match="alpha 0 on 100% of its pixels"):
        _check_opaque_film(path, "view")


def _windowed(path: Path, data: tuple[int, int, int, int]) -> Path:
    """An 8x6 frame (display window) whose stored pixels are `data` (x, y, width, height), each
    holding its frame coordinates (x, y, 0)."""
    import OpenImageIO as oiio

    x0, y0, w, h = data
    spec = oiio.ImageSpec(w, h, 3, oiio.FLOAT)
    spec.x, spec.y, spec.full_x, spec.full_y, spec.full_width, spec.full_height = x0, y0, 0, 0, 8, 6
    ys, xs = np.mgrid[y0 : y0 + h, x0 : x0 + w].astype(np.float32)
    out = oiio.ImageOutput.create(str(path))
    out.open(str(path), spec)
    out.write_image(np.ascontiguousarray(np.stack([xs, ys, np.zeros_like(xs)], -1)))
    out.close()
    return path


def test_an_overscan_exr_is_read_over_its_frame(tmp_path):
    """Pixels rendered beyond the frame (overscan) were reported as an image of another size;
    the frame is read, each pixel where it is."""
    pixels, _, _ = read_linear(_windowed(tmp_path / "o.exr", (-2, -1, 12, 8)), "linear")
    assert pixels.shape == (6, 8, 3)
    np.testing.assert_array_equal(pixels[4, 5], [5, 4, 0])
    np.testing.assert_array_equal(pixels[0, 0], [0, 0, 0])


@pytest.mark.parametrize("data", [(1, 1, 6, 4), (0, 0, 8, 5), (2, 0, 8, 6)])
def test_an_exr_holding_part_of_its_frame_is_refused(tmp_path, data):
    """A render region or an autocropped EXR stores part of the frame; the rest was not
    rendered (it was reported as an image of another size than the camera's)."""
    with pytest.raises(CaptureError, match=r"o\.exr: holds pixels only in x .* of its 8x6 frame"):
        read_linear(_windowed(tmp_path / "o.exr", data), "linear")


def test_validity_weights():
    image = np.full((20, 20, 3), 0.5, np.float32)
    image[2, 2] = np.nan
    image[15, 15] = 0.0
    saturated = np.zeros((20, 20), bool)
    saturated[10, 10] = True
    mask = np.ones((20, 20), bool)
    mask[:, 18:] = False
    clean, weight = validity(image, saturated, mask, dilate=2)
    assert np.all(np.isfinite(clean)) and clean[2, 2].sum() == 0
    assert weight[2, 2] == 0 and weight[15, 15] == 0 and weight[:, 18:].sum() == 0
    assert weight[10, 8] == 0 and weight[10, 12] == 0 and weight[10, 13] == 1  # dilated by 2
    assert weight[5, 5] == 1


def test_downscale_by_area():
    image = np.arange(16 * 3, dtype=np.float32).reshape(4, 4, 3)
    weight = np.ones((4, 4), np.float32)
    weight[0, 0] = 0
    small, w = downscale(image, weight, 2)
    assert small.shape == (2, 2, 3) and w[0, 0] == 0.75 and w[1, 1] == 1
    np.testing.assert_allclose(small[0, 0], image[[0, 1, 1], [1, 0, 1]].mean(0))
    # any size: 4 / 3 rounds to 1 pixel of 4 x 4 input pixels, centred, all of the image
    one, w1 = downscale(image, weight, 3)
    assert one.shape == (1, 1, 3) and w1[0, 0] == pytest.approx(15 / 16)
    np.testing.assert_allclose(one[0, 0], image.reshape(-1, 3)[1:].mean(0), rtol=1e-6)


def test_downscale_of_odd_sizes_keeps_square_centred_pixels():
    """153 x 128 by 2: 76 x 64 square pixels 153/76 wide, centred; a linear ramp's area
    averages are the ramp at the pixel centres (to the input pixels' steps), and the rows past
    the image lose weight."""
    h, w = 128, 153
    y, x = np.mgrid[0:h, 0:w].astype(np.float32)
    image = np.stack([x + 0.5, y + 0.5, np.ones_like(x)], axis=-1)
    small, weight = downscale(image, np.ones((h, w), np.float32), 2)
    assert small.shape == (64, 76, 3)
    size = w / 76
    centres_x = (np.arange(76) + 0.5) * size
    centres_y = (h - 64 * size) / 2 + (np.arange(64) + 0.5) * size
    inside = weight > 0.999
    # the image is constant per input pixel: area averages differ from the ramp by < 1/100
    ramp_x, ramp_y = np.tile(centres_x, (64, 1)), np.tile(centres_y[:, None], (1, 76))
    np.testing.assert_allclose(small[..., 0][inside], ramp_x[inside], atol=0.01)
    np.testing.assert_allclose(small[..., 1][1:-1], ramp_y[1:-1], atol=0.01)
    assert weight[0].max() < 1 and weight[-1].max() < 1 and inside[1:-1].all()


def test_diligent_loads_with_normalised_lights(shared_data):
    folder = shared_data / "diligent-ball"
    capture = diligent_capture(folder)
    assert len(capture.views) == 16
    intensities = np.loadtxt(folder / "light_intensities.txt")
    first = capture.views[0]
    raw, _, _ = read_linear(folder / "001.png", "linear")
    inside = first.weight > 0
    np.testing.assert_allclose(first.image[inside], (raw / intensities[0])[inside], rtol=1e-5)
    for view in capture.views:
        (light,) = view.lights
        assert np.linalg.norm(light.direction) == pytest.approx(1.0)
        assert light.direction[2] < 0  # light travels away from the camera side, towards the ball
    mask = capture.scene.meta["mask"]
    cx, cy, r = fit_sphere_to_mask(mask)
    ys, xs = np.nonzero(mask)
    assert r == pytest.approx((xs.max() - xs.min() + 1) / 2, abs=1.5)  # a disc: area = extent
    assert r == pytest.approx((ys.max() - ys.min() + 1) / 2, abs=1.5)
    assert cx == pytest.approx((xs.max() + xs.min() + 1) / 2, abs=1.0)
    assert cy == pytest.approx((ys.max() + ys.min() + 1) / 2, abs=1.0)


def test_peer_capture_truth(shared_data):
    capture = peer_capture(shared_data / "peer-cycles" / "sphere-blue" / "scene.json")
    assert capture.truth["glaze.roughness"] == pytest.approx(0.25**2)
    assert len(capture.views) == 3 and all(v.weight.mean() == 1 for v in capture.views)


def test_a_peer_targets_folder_opens_as_its_scene_json(shared_data, tmp_path):
    """`layerfit fit`'s capture may name the peer target's folder, as it may a manifest's; the
    folder was refused as holding "no capture.toml, scene.json" while it held a scene.json."""
    from captures import open_capture

    folder = shared_data / "peer-cycles" / "sphere-blue"
    capture = open_capture(folder)
    assert len(capture.views) == 3 and capture.truth == open_capture(folder / "scene.json").truth
    (tmp_path / "scene.json").mkdir()  # a folder by that name: one line, not a traceback
    with pytest.raises(CaptureError, match=r"scene\.json: cannot read"):
        open_capture(tmp_path / "scene.json")


# Manifests ---------------------------------------------------------------------------------------

SCENE = {"geometry": "sphere", "environment": [0.1, 0.1, 0.1]}
CAMERA = {"origin": [0.0, -5.0, 0.0], "target": [0.0, 0.0, 0.0], "fov_x_deg": 30.0}


def make_capture(tmp_path, views=None, capture=None, truth=None, size=(8, 6)) -> Path:
    image = np.full((size[1], size[0], 3), 0.25, np.float32)
    write_image(tmp_path / "v0.exr", image)
    views = views if views is not None else [{"image": "v0.exr", "camera": dict(CAMERA)}]
    text = manifest_text(capture or {"encoding": "linear"}, SCENE, views, truth or {})
    (tmp_path / "capture.toml").write_text(text)
    return tmp_path / "capture.toml"


def test_manifest_loads(tmp_path):
    path = make_capture(
        tmp_path,
        views=[{"image": "v0.exr", "gain": 2.0, "camera": dict(CAMERA)}],
        truth={"glaze.ior": 1.5},
    )
    capture = load_capture(path.parent)
    (view,) = capture.views
    np.testing.assert_allclose(view.image, 0.125)
    assert view.camera.width == 8 and capture.truth == {"glaze.ior": 1.5}


def test_manifest_downscale_adjusts_cameras(tmp_path):
    views = [{"image": "v0.exr", "camera": dict(CAMERA, width=16, height=12)}]
    capture = {"encoding": "linear", "downscale": 2}
    path = make_capture(tmp_path, views=views, capture=capture, size=(16, 12))
    view = load_capture(path).views[0]
    assert view.image.shape == (6, 8, 3) and (view.camera.width, view.camera.height) == (8, 6)
    # a factor that leaves under 4 pixels a side: refused, naming the manifest's field
    path = make_capture(tmp_path, views=views, capture=capture | {"downscale": 4}, size=(16, 12))
    with pytest.raises(CaptureError, match=r"capture.toml: capture.downscale = 4 leaves .* 4x3"):
        load_capture(path)
    # photos under 4 pixels a side: no factor to make smaller (it said "give a smaller factor")
    views = [{"image": "v0.exr", "camera": dict(CAMERA, width=3, height=2)}]
    path = make_capture(tmp_path, views=views, capture={"encoding": "linear"}, size=(3, 2))
    with pytest.raises(
        CaptureError, match=r"capture.toml: view v0 is 3x2: at least 4 pixels a side; give lar"
    ):
        load_capture(path)


def bad(tmp_path, **kw):
    with pytest.raises(CaptureError) as err:
        load_capture(make_capture(tmp_path, **kw))
    assert "capture.toml" in str(err.value)
    return str(err.value)


def test_float_image_declared_srgb(tmp_path):
    """An EXR's floats are linear: decoding them as sRGB would square the gamma; refused."""
    message = bad(tmp_path, capture={"encoding": "srgb"})
    assert "views[0].image" in message and 'encoding = "linear"' in message


def test_missing_file(tmp_path):
    assert "views[0].image: 'none.exr' does not exist" in bad(
        tmp_path, views=[{"image": "none.exr", "camera": CAMERA}]
    )


def test_corrupt_image(tmp_path):
    (tmp_path / "broken.png").write_bytes(b"not a png at all")
    with pytest.raises(CaptureError, match=r"broken\.png"):
        load_capture(make_capture(tmp_path, views=[{"image": "broken.png", "camera": CAMERA}]))


def test_raw_stub_in_a_manifest(tmp_path, shared_data):
    (tmp_path / "x.nef").write_bytes((shared_data / "raw" / "stub_Nikon.nef").read_bytes())
    path = make_capture(
        tmp_path, capture={"encoding": "raw"}, views=[{"image": "x.nef", "camera": CAMERA}]
    )
    with pytest.raises(CaptureError, match=r"x\.nef: LibRaw cannot decode"):
        load_capture(path)


def test_camera_size_must_match_image(tmp_path):
    assert "views[0].camera is 10x6 but v0.exr is 8x6" in bad(
        tmp_path, views=[{"image": "v0.exr", "camera": {**CAMERA, "width": 10, "height": 6}}]
    )


def test_mask_size_mismatch(tmp_path):
    write_image(tmp_path / "m.png", np.ones((5, 5, 3), np.float32))
    assert "views[0].mask is 5x5 but the image is 8x6" in bad(
        tmp_path, views=[{"image": "v0.exr", "mask": "m.png", "camera": CAMERA}]
    )


def test_nan_pixels_get_zero_weight_and_a_warning(tmp_path, caplog):
    path = make_capture(tmp_path)
    image = np.full((6, 8, 3), 0.25, np.float32)
    image[1, 1] = np.nan
    write_image(tmp_path / "v0.exr", image)
    with caplog.at_level(logging.WARNING):
        capture = load_capture(path)
    assert capture.views[0].weight[1, 1] == 0 and np.isfinite(capture.views[0].image).all()
    assert "1 NaN/Inf pixels get weight 0" in caplog.text


def test_an_inf_pixel_is_counted_once_as_not_finite(tmp_path, caplog):
    """+inf in a float32 EXR is not finite, not a half float at its maximum: one warning (it was
    counted in both)."""
    path = make_capture(tmp_path)
    image = np.full((6, 8, 3), 0.25, np.float32)
    image[1, 1], image[2, 2] = np.inf, 65504.0
    write_image(tmp_path / "v0.exr", image)
    with caplog.at_level(logging.WARNING):
        capture = load_capture(path)
    assert capture.views[0].weight[1, 1] == 0
    assert "1 NaN/Inf pixels get weight 0" in caplog.text
    assert "1 pixels at the half-float maximum" in caplog.text


def test_8bit_declared_linear_warns(tmp_path):
    write_image(tmp_path / "v.jpg", np.full((6, 8, 3), 0.25, np.float32))
    capture = load_capture(make_capture(tmp_path, views=[{"image": "v.jpg", "camera": CAMERA}]))
    assert any("8-bit data declared linear" in w for w in capture.warnings)


@pytest.mark.parametrize(
    "exposure, message",
    [
        ({"gain": 0.0}, "views[0].gain: got 0.0; should be greater than 0"),
        ({"gain": -1.0}, "views[0].gain: got -1.0; should be greater than 0"),
        ({"gain": 1.0, "exposure_ev": 1.0}, "and exposure_ev both given"),
    ],
)
def test_bad_exposure(tmp_path, exposure, message):
    assert message in bad(tmp_path, views=[{"image": "v0.exr", **exposure, "camera": CAMERA}])


def test_camera_that_does_not_see_the_object(tmp_path):
    away = {**CAMERA, "target": [0.0, -10.0, 0.0]}
    assert "views[0].camera does not see the object" in bad(
        tmp_path, views=[{"image": "v0.exr", "camera": away}]
    )


def test_empty_photo_set(tmp_path):
    assert "the photo set is empty" in bad(tmp_path, views=[])


def test_path_escaping_the_folder(tmp_path):
    sub = tmp_path / "cap"
    sub.mkdir()
    write_image(tmp_path / "outside.exr", np.ones((6, 8, 3), np.float32))
    assert "points outside the capture folder" in bad(
        sub, views=[{"image": "../outside.exr", "camera": CAMERA}]
    )


def test_unknown_key(tmp_path):
    assert "views[0].exposure: unknown key; known: image, mask, exposure_ev, gain, camera" in bad(
        tmp_path, views=[{"image": "v0.exr", "exposure": 1.0, "camera": CAMERA}]
    )


def _peer_folder(folder: Path, image_name: str, material: dict) -> Path:
    """A one-view peer target: scene.json, a tetrahedron mesh and the view's file name."""
    import json

    folder.mkdir()
    (folder / "mesh.obj").write_text(
        "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n"
    )
    doc = {
        "mesh": "mesh.obj",
        "views": [
            {
                "image": image_name,
                "origin": [3, -3, 2],
                "target": [0, 0, 0],
                "up": [0, 0, 1],
                "fov_x_deg": 40,
                "width": 8,
                "height": 6,
            }
        ],
        "lights": [],
        "environment_radiance_rgb": [0.05, 0.05, 0.05],
        "material": material,
    }
    path = folder / "scene.json"
    path.write_text(json.dumps(doc))
    return path


def test_a_peer_target_in_png_is_decoded_as_srgb(tmp_path):
    """A peer's views given as 16-bit PNG (a display output) are sRGB-decoded, with a warning;
    read as stored they were 2x too bright in the mid-tones."""
    from captures.images import srgb_decode

    path = _peer_folder(tmp_path / "peer", "view_00.png", {"base_color": [0.5, 0.4, 0.3]})
    write_image(tmp_path / "peer" / "view_00.png", np.full((6, 8, 3), 0.2, np.float32))
    encoded = read_linear(tmp_path / "peer" / "view_00.png", "linear")[0]  # the file's codes
    capture = peer_capture(path)
    np.testing.assert_allclose(capture.views[0].image, srgb_decode(encoded), rtol=1e-5)
    assert any("read as sRGB-encoded" in w for w in capture.warnings)


def test_a_peer_material_table_may_lack_keys(tmp_path):
    path = _peer_folder(tmp_path / "peer", "view_00.exr", {"base_color": [0.5, 0.4, 0.3]})
    write_image(tmp_path / "peer" / "view_00.exr", np.full((6, 8, 3), 0.2, np.float32))
    capture = peer_capture(path)
    assert capture.truth == {"glaze.pigment": [0.5, 0.4, 0.3]}
    (warning,) = capture.warnings
    assert "no specular_roughness, ior, diffuse_roughness" in warning
    np.testing.assert_allclose(capture.views[0].image, 0.2, rtol=1e-3)  # EXR: linear as stored


def test_a_peer_diffuse_roughness_is_the_eon_sigma(tmp_path):
    """Cycles' diffuse roughness is EON's r in [0, 1]: the truth of the glaze's sigma with
    `diffuse = "eon"` (recorded in `truth_options`); 0 (Lambert) is sigma 0 in either lobe."""
    material = {"base_color": [0.5, 0.4, 0.3], "specular_roughness": 0.2, "ior": 1.5}
    lambert = _peer_folder(tmp_path / "a", "view_00.exr", {**material, "diffuse_roughness": 0.0})
    rough = _peer_folder(tmp_path / "b", "view_00.exr", {**material, "diffuse_roughness": 0.5})
    for folder in ("a", "b"):
        write_image(tmp_path / folder / "view_00.exr", np.full((6, 8, 3), 0.2, np.float32))
    capture = peer_capture(lambert)
    assert capture.truth["glaze.sigma"] == 0.0 and capture.truth_options == {}
    capture = peer_capture(rough)
    assert capture.truth["glaze.sigma"] == 0.5 and capture.truth["glaze.ior"] == 1.5
    assert capture.truth_options == {"glaze.diffuse": "eon"}


def test_an_8_bit_peer_view_masks_only_the_object(tmp_path):
    """In an 8-bit view the constant background varies by its rounding: the object's mask must
    not take it for the object (IoU 0.30-0.34 on a peer sphere before)."""
    path = _peer_folder(tmp_path / "peer", "view_00.png", {"base_color": [0.5, 0.4, 0.3]})
    image = np.full((6, 8, 3), 0.05, np.float32)  # the environment below, as rounded to 8 bits
    image[2:4, 3:5] = 0.4  # the object
    import json

    doc = json.loads(path.read_text())
    doc["environment_radiance_rgb"] = [0.0503, 0.0497, 0.05]  # not exactly a code value
    path.write_text(json.dumps(doc))
    import OpenImageIO as oiio

    from captures.images import srgb_encode

    out = oiio.ImageOutput.create(str(tmp_path / "peer" / "view_00.png"))
    out.open(str(tmp_path / "peer" / "view_00.png"), oiio.ImageSpec(8, 6, 3, "uint8"))
    out.write_image(np.round(srgb_encode(image) * 255).astype(np.uint8))
    out.close()
    mask = peer_capture(path).views[0].mask
    assert mask.sum() == 4 and mask[2:4, 3:5].all()


@pytest.mark.parametrize(
    "material, message",
    [
        ({"base_color": 0.3}, r"material.base_color = 0.3; give 3 numbers in \[0, 1\]"),
        ({"base_color": "blue"}, r"material.base_color = 'blue'; give 3 numbers"),
        ({"ior": True}, r"material.ior = True; give a number in \[1, 10\]"),
        ({"diffuse_roughness": -0.2}, r"material.diffuse_roughness = -0.2; give a number"),
        ([1, 2], r"material is list; give a table of its values"),
    ],
)
def test_a_peer_material_table_with_bad_values_is_named(tmp_path, material, message):
    path = _peer_folder(tmp_path / "peer", "view_00.exr", material)
    write_image(tmp_path / "peer" / "view_00.exr", np.full((6, 8, 3), 0.2, np.float32))
    with pytest.raises(CaptureError, match=message):
        peer_capture(path)


def _view(doc):
    return doc["views"][0]


def _light(doc):
    doc["lights"] = [
        {
            "type": "rectangle",
            "center": [3.0, -2.0, 3.0],
            "u_axis": [1.0, 0.0, 0.0],
            "v_axis": [0.0, 1.0, 0.0],
            "emit_direction": [0.0, 0.0, -1.0],
            "size": [1.0, 1.0],
            "radiance_rgb": [10.0, 10.0, 10.0],
        }
    ]
    return doc["lights"][0]


@pytest.mark.parametrize(
    "part, change, message",
    [
        ("view", {"fov_x_deg": 200}, r"views\[0\]\.fov_x_deg: got 200; should be less"),
        ("view", {"origin": [0, 0, 0]}, r"views\[0\]\.target: equals origin"),
        ("view", {"origin": [float("nan"), 0, 0]}, r"views\[0\]\.origin\[0\]: got nan"),
        ("view", {"up": [3, -3, 2]}, r"views\[0\]\.up: .* along the viewing"),
        ("view", {"width": 0}, r"views\[0\]\.width: got 0"),
        ("view", {"image": 5}, r"views\[0\]\.image is 5; give the view's image"),
        ("view", {"type": "ORTHO"}, r'views\[0\]\.type = "ORTHO" changes the picture'),
        ("view", {"shift_x": 0.1}, r"views\[0\]\.shift_x = 0.1 changes the picture"),
        ("light", {"shape": "DISK"}, r'lights\[0\]\.shape = "DISK" changes the picture'),
        ("light", {"type": "point"}, r"lights\[0\]\.type = 'point'; .* capture.toml"),
        ("doc", {"environment_map": "env.exr"}, r'environment_map = "env.exr" changes the'),
        ("view", {"image": ""}, r'views\[0\]\.image is ""; give'),
        ("view", {"origin": [0.1, 0.1, 0.1]}, r"views\[0\]\.origin .* inside the object"),
        ("light", {"radiance_rgb": [-1, 1, 1]}, r"lights\[0\]\.radiance_rgb\[0\]: got -1"),
        ("light", {"size": [0, 1]}, r"lights\[0\]\.size\[0\]: got 0"),
        ("light", {"radiance_rgb": None}, r"lights\[0\] has no field 'radiance_rgb'"),
        ("doc", {"environment_radiance_rgb": [-1, 0, 0]}, r"environment_radiance_rgb\[0\]: got -1"),
        ("doc", {"views": []}, r"views must be a list of one or more"),
        ("doc", {"environment_radiance_rgb": "bright"}, r"environment_radiance_rgb: expected 3"),
        ("doc", {"environment_radiance_rgb": [0, 0, 0]}, r"the scene has no light; add lights"),
    ],
)
def test_a_peer_scene_passes_a_manifests_checks_named_by_its_fields(
    tmp_path, part, change, message
):
    """A peer scene.json's cameras, lights and environment were read without a manifest's checks:
    a field of view outside (0, 180) or a camera on its target was an internal error from the
    renderer, a NaN origin or a camera inside the object rendered nothing, a negative radiance
    or a light of no size was taken. Now each is one line naming the JSON's field."""
    path = _peer_folder(tmp_path / "peer", "view_00.exr", {"base_color": [0.5, 0.4, 0.3]})
    write_image(tmp_path / "peer" / "view_00.exr", np.full((6, 8, 3), 0.2, np.float32))
    doc = json.loads(path.read_text())
    table = {"view": _view, "light": _light, "doc": lambda d: d}[part](doc)
    table.update(change)
    for key in [k for k, v in change.items() if v is None]:  # a field left out
        del table[key]
    path.write_text(json.dumps(doc))
    with pytest.raises(CaptureError, match=r"peer/scene\.json: " + message):
        peer_capture(path)


def test_a_peer_views_size_may_be_a_whole_float(tmp_path):
    """A script's computed resolution (160.0) is a whole number of pixels; 160.5 is not."""
    path = _peer_folder(tmp_path / "peer", "view_00.exr", {"base_color": [0.5, 0.4, 0.3]})
    write_image(tmp_path / "peer" / "view_00.exr", np.full((6, 8, 3), 0.2, np.float32))
    doc = json.loads(path.read_text())
    _view(doc).update(width=8.0, height=6.0)
    path.write_text(json.dumps(doc))
    assert peer_capture(path).views[0].image.shape == (6, 8, 3)
    _view(doc).update(width=8.5)
    path.write_text(json.dumps(doc))
    with pytest.raises(CaptureError, match=r"views\[0\]\.width: got 8\.5"):
        peer_capture(path)


def _png(path: Path, stored: np.ndarray) -> Path:
    """An 8-bit PNG of `stored` (H, W, C) codes, as they are."""
    import OpenImageIO as oiio

    out = oiio.ImageOutput.create(str(path))
    out.open(str(path), oiio.ImageSpec(stored.shape[1], stored.shape[0], stored.shape[2], "uint8"))
    out.write_image(stored)
    out.close()
    return path


def test_a_mask_stored_as_codes_0_and_1_reads_as_a_mask(tmp_path):
    """Some tools write masks as 8-bit codes 0 and 1 (not 255): read as the object's pixels."""
    from captures.images import read_mask

    codes = np.zeros((6, 8, 1), np.uint8)
    codes[2:4, 3:6] = 1
    mask = read_mask(_png(tmp_path / "mask.png", codes))
    assert mask.sum() == 6 and mask[2:4, 3:6].all()


def test_a_peer_model_other_than_the_glaze_is_a_warning(tmp_path, shared_data):
    """The shared targets' `material.model` is the glaze (no warning, whatever the spacing); a
    target made with another BSDF (GGX here) says that its scores compare two models."""
    from captures.importers import PEER_MODEL

    shared = json.loads((shared_data / "peer-cycles" / "torus-amber" / "scene.json").read_text())
    assert "".join(shared["material"]["model"].split()) == "".join(PEER_MODEL.split())
    material = {"base_color": [0.5, 0.4, 0.3], "specular_roughness": 0.2, "ior": 1.5}
    material["diffuse_roughness"] = 0.0
    for name, model, warned in (
        ("same", PEER_MODEL.replace(", ", ","), False),
        ("ggx", PEER_MODEL.replace("beckmann", "ggx"), True),
    ):
        path = _peer_folder(tmp_path / name, "view_00.exr", {**material, "model": model})
        write_image(tmp_path / name / "view_00.exr", np.full((6, 8, 3), 0.2, np.float32))
        warnings = peer_capture(path).warnings
        assert any("is not the glaze's model" in w for w in warnings) == warned, warnings


def test_negative_pixels_are_counted_in_a_warning(tmp_path, caplog):
    """A linear image with values below 0: pixels with no channel above 0 get weight 0 (clipped
    black), the others keep theirs; the warning counts both (it was silent)."""
    path = make_capture(tmp_path)
    image = np.full((6, 8, 3), 0.25, np.float32)
    image[1, 1] = -0.01  # every channel: dropped
    image[2, 2, 0] = -0.5  # one channel: kept
    image[3, 3] = np.nan  # not counted as negative
    image[4, 4] = 0.0  # black, not negative: dropped but not counted
    image[5, 5] = (-np.inf, 0.2, 0.2)  # not finite: the NaN/Inf warning's
    write_image(tmp_path / "v0.exr", image)
    with caplog.at_level(logging.WARNING):
        capture = load_capture(path)
    weight = capture.views[0].weight
    assert weight[1, 1] == 0 and weight[2, 2] == 1 and weight[3, 3] == 0 and weight[4, 4] == 0
    assert (
        "2 pixels have negative values (the lowest -0.5): 1 of them with no channel" in caplog.text
    )
    assert capture.warnings and "negative" in " ".join(capture.warnings)
    caplog.clear()
    write_image(tmp_path / "v0.exr", np.full((6, 8, 3), 0.25, np.float32))
    with caplog.at_level(logging.WARNING):
        load_capture(path)
    assert "negative" not in caplog.text


def test_a_grey_and_alpha_mask_is_read_by_its_grey(tmp_path):
    """A mask saved as grey and alpha (alpha 1 everywhere) made every pixel the object: its
    alpha was read as a colour channel."""
    from captures.images import read_mask

    stored = np.zeros((6, 8, 2), np.uint8)
    stored[2:4, 3:6, 0] = 255
    stored[..., 1] = 255
    mask = read_mask(_png(tmp_path / "mask.png", stored))
    assert mask.sum() == 6 and mask[2:4, 3:6].all()


@pytest.mark.parametrize("coverage, expected", [(0.5, 0), (0.0, 1)])
def test_a_downscaled_mask_keeps_its_coverage_meaning(coverage, expected):
    """A peer's mask marks any coverage (`mask_coverage` 0); downscaled, it was cut at half,
    so a perfect render of a disc scored IoU 0.91 at downscale 4."""
    from captures.capture import Capture, View
    from captures.scene import Camera, Scene, Sphere

    camera = Camera((0.0, -5.0, 0.0), (0.0, 0.0, 0.0), (0.0, 0.0, 1.0), 30.0, 8, 8)
    mask = np.zeros((8, 8), bool)
    mask[1, 1] = True  # one pixel of a 4x4 block
    view = View("v", np.zeros((8, 8, 3), np.float32), np.ones((8, 8), np.float32), camera)
    view = dataclasses.replace(view, mask=mask, mask_coverage=coverage)
    capture = Capture(Scene(Sphere(), (camera,)), [view])
    small = capture.downscaled(4).views[0].mask
    assert small.shape == (2, 2) and int(small.sum()) == expected and small[0, 0] == bool(expected)


def test_a_peer_target_is_checked_as_a_manifest_is(tmp_path):
    """What a manifest refuses or warns of, a peer target does too: two views named alike
    (their gains collided: an internal error after the whole fit), a view with no valid pixel
    (fitted as a perfect match, relative RMSE 0), NaN pixels; a light that is not one-sided is
    refused; fields this version does not read, and no environment, are warned."""
    import json

    path = _peer_folder(tmp_path / "peer", "a/view.exr", {"base_color": [0.5, 0.4, 0.3]})
    doc = json.loads(path.read_text())
    doc["views"].append({**doc["views"][0], "image": "b/view.exr"})
    for name in ("a", "b"):
        (tmp_path / "peer" / name).mkdir()
        write_image(tmp_path / "peer" / name / "view.exr", np.full((6, 8, 3), 0.2, np.float32))
    path.write_text(json.dumps(doc))
    with pytest.raises(CaptureError, match=r"views\[1\]\.image: view.exr has the name of views\["):
        peer_capture(path)

    doc["views"] = doc["views"][:1]
    doc["views"][0]["image"] = "black.exr"
    path.write_text(json.dumps(doc))
    write_image(tmp_path / "peer" / "black.exr", np.zeros((6, 8, 3), np.float32))
    with pytest.raises(CaptureError, match=r"views\[0\]\.image: black.exr has no valid pixel"):
        peer_capture(path)

    nan = np.full((6, 8, 3), 0.2, np.float32)
    nan[0, 0] = np.nan
    write_image(tmp_path / "peer" / "black.exr", nan)
    doc["views"][0]["exposure"] = 1.0  # another exporter's field
    doc["lights"] = [
        {
            "type": "rectangle",
            "center": [0, 0, 3],
            "emit_direction": [0, 0, -1],
            "u_axis": [1, 0, 0],
            "v_axis": [0, -1, 0],
            "size": [1, 1],
            "radiance_rgb": [5, 5, 5],
            "one_sided": False,
        }
    ]
    del doc["environment_radiance_rgb"]
    path.write_text(json.dumps(doc))
    with pytest.raises(CaptureError, match=r"lights\[0\]\.one_sided = False: layerfit's rect"):
        peer_capture(path)
    doc["lights"][0]["one_sided"] = True
    path.write_text(json.dumps(doc))
    warnings = peer_capture(path).warnings
    assert any("black.exr: 1 NaN/Inf pixels get weight 0" in w for w in warnings)
    assert any("views[0] has field(s) 'exposure' this version does not read" in w for w in warnings)
    assert any(
        "no environment_radiance_rgb: the environment is taken as black" in w for w in warnings
    )


def test_a_peer_truth_outside_the_bounds_is_fitted_not_scored(tmp_path, caplog):
    """A Cycles glaze of roughness 0.08 (alpha 0.0064, below the glaze's 0.01) could not be
    fitted at all: its truth was refused as a manifest's is ("choose a value inside them",
    which a peer's user cannot). The fit runs; that key is warned and not scored."""
    import logging

    from fit.commands.prepare import check_truth
    from fit.material import build_material, resolve

    material = {"base_color": [0.5, 0.4, 0.3], "specular_roughness": 0.08, "ior": 1.5}
    path = _peer_folder(tmp_path / "peer", "view_00.exr", material)
    write_image(tmp_path / "peer" / "view_00.exr", np.full((6, 8, 3), 0.2, np.float32))
    capture = peer_capture(path)
    glaze = build_material({"type": "glaze"})
    free = resolve(glaze, ["glaze.roughness", "glaze.ior"])
    with caplog.at_level(logging.WARNING):
        check_truth(capture, free, path, glaze)
    assert "truth.glaze.roughness = 0.0064" in caplog.text and "not scored" in caplog.text
    assert "glaze.roughness" not in capture.truth and capture.truth["glaze.ior"] == 1.5


def _oiio_write(path: Path, pixels: np.ndarray, fmt, **attributes) -> Path:
    import OpenImageIO as oiio

    spec = oiio.ImageSpec(pixels.shape[1], pixels.shape[0], pixels.shape[2], fmt)
    for name, value in attributes.items():
        spec.attribute(name, value)
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), spec) and out.write_image(pixels)
    out.close()
    return path


@pytest.mark.parametrize("suffix", [".jpg", ".png", ".tif"])
@pytest.mark.parametrize("orientation", [3, 6, 8])
def test_a_photo_viewers_show_turned_is_refused_with_both_fixes(tmp_path, suffix, orientation):
    """A photo stored sideways with an EXIF Orientation (phones do this): its pixels were read
    as stored without a word, though viewers, and the user setting up its camera, see it turned;
    now refused, naming the tag and the fix for either case. Orientation 1 reads."""
    import OpenImageIO as oiio

    pixels = np.full((30, 40, 3), 128, np.uint8)
    path = _oiio_write(tmp_path / f"v{suffix}", pixels, oiio.UINT8, Orientation=orientation)
    with pytest.raises(CaptureError, match=rf"EXIF Orientation is {orientation}: .*40x30"):
        read_linear(path, "srgb")
    upright = _oiio_write(tmp_path / f"u{suffix}", pixels, oiio.UINT8, Orientation=1)
    assert read_linear(upright, "srgb")[0].shape == (30, 40, 3)


def test_a_cut_out_mask_is_read_from_its_alpha(tmp_path):
    """An RGBA mask with the object in its alpha (segmentation tools write these): its flat
    colour made the whole frame the object (white) or none of it (black); now its alpha is the
    mask. Colour and alpha that draw different objects are refused; agreeing ones read."""
    import OpenImageIO as oiio

    from captures.images import read_mask

    y, x = np.mgrid[:30, :40]
    disc = (x - 20) ** 2 + (y - 15) ** 2 < 100
    for grey in (0.0, 1.0):
        rgba = np.dstack([np.full((30, 40, 3), grey), disc]).astype(np.float32)
        path = _oiio_write(tmp_path / f"m{grey}.png", rgba, oiio.UINT8)
        assert np.array_equal(read_mask(path), disc)
    agree = np.dstack([np.repeat(disc[..., None], 3, 2), disc]).astype(np.float32)
    assert np.array_equal(read_mask(_oiio_write(tmp_path / "a.png", agree, oiio.UINT8)), disc)
    other = np.dstack([np.repeat(~disc[..., None], 3, 2), disc]).astype(np.float32)
    with pytest.raises(CaptureError, match="colour and its alpha channel draw different"):
        read_mask(_oiio_write(tmp_path / "o.png", other, oiio.UINT8))


def test_another_exporters_peer_scene_is_read_or_named(tmp_path):
    """What another exporter writes: a Windows path (`renders\\view.exr`,
    refused as "no such image file"), a material with inputs this version does not read (a
    coat: silently scored as if absent; now a warning), a vertical field of view only, a render
    at another size (the error named neither the field nor the fix), UTF-16 text (a decode
    error)."""
    from captures.peer import load_peer_scene

    path = _peer_folder(tmp_path / "peer", "renders\\view_00.exr", {"base_color": [0.5] * 3})
    (tmp_path / "peer" / "renders").mkdir()
    write_image(tmp_path / "peer" / "renders" / "view_00.exr", np.full((6, 8, 3), 0.2, np.float32))
    doc = json.loads(path.read_text())
    doc["material"]["coat_weight"] = 0.5
    path.write_text(json.dumps(doc))
    capture = peer_capture(path)
    assert capture.views[0].image.shape == (6, 8, 3)
    assert any("material has field(s) 'coat_weight'" in w for w in capture.warnings)
    _view(doc).update(width=16, height=12)
    path.write_text(json.dumps(doc))
    with pytest.raises(CaptureError, match=r"views\[0\]: view_00.exr is 8x6 but width and height"):
        peer_capture(path)
    _view(doc).update(width=8, height=6, fov_y_deg=30)
    del _view(doc)["fov_x_deg"]
    path.write_text(json.dumps(doc))
    with pytest.raises(CaptureError, match=r"views\[0\] has fov_y_deg but no fov_x_deg"):
        load_peer_scene(path)
    path.write_text(json.dumps(doc), encoding="utf-16")
    with pytest.raises(CaptureError, match="is UTF-16 text; save it as UTF-8"):
        load_peer_scene(path)


@pytest.mark.parametrize(
    "attribute, value",
    [
        ("colorInteropID", "lin_ap1_scene"),
        ("chromaticities", (0.713, 0.293, 0.165, 0.830, 0.128, 0.044, 0.32168, 0.33767)),
    ],
)
def test_an_image_in_other_primaries_is_refused(tmp_path, attribute, value):
    """An EXR declaring ACEScg's primaries (Blender 5 from an ACEScg working space) was read as
    Rec.709 without a word; now refused with the conversion. Rec.709's own declaration reads."""
    import OpenImageIO as oiio

    pixels = np.full((6, 8, 3), 0.2, np.float32)
    if attribute == "chromaticities":
        spec_value = oiio.TypeDesc("float[8]"), value
    else:
        spec_value = (value,)
    path = tmp_path / "v.exr"
    spec = oiio.ImageSpec(8, 6, 3, oiio.FLOAT)
    spec.attribute(attribute, *spec_value)
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), spec) and out.write_image(pixels)
    out.close()
    with pytest.raises(CaptureError, match=r"not Rec\.709"):
        read_linear(path, "linear")
    rec709 = _oiio_write(tmp_path / "r.exr", pixels, oiio.FLOAT, colorInteropID="lin_rec709_scene")
    assert read_linear(rec709, "linear")[0].shape == (6, 8, 3)


def test_a_peer_view_on_a_transparent_film_is_refused(tmp_path):
    """A Cycles render with Film > Transparent (background RGB 0, alpha 0): its background is
    not the declared environment; it was read with an "alpha ignored" warning and then a poor
    silhouette overlap blamed on the mesh's axes. Opaque RGBA reads."""
    import OpenImageIO as oiio

    path = _peer_folder(tmp_path / "peer", "view_00.exr", {"base_color": [0.5] * 3})
    rgba = np.zeros((6, 8, 4), np.float32)
    rgba[2:4, 3:5] = 0.2, 0.2, 0.2, 1.0
    _oiio_write(tmp_path / "peer" / "view_00.exr", rgba, oiio.FLOAT)
    with pytest.raises(CaptureError, match=r"views\[0\]: view_00.exr has alpha 0 on 92%"):
        peer_capture(path)
    rgba[..., 3], rgba[..., :3] = 1.0, np.maximum(rgba[..., :3], 0.05)
    _oiio_write(tmp_path / "peer" / "view_00.exr", rgba, oiio.FLOAT)
    assert peer_capture(path).views[0].image.shape == (6, 8, 3)


def test_a_batchs_capture_check_reads_a_peer_scene_as_its_loader_does(tmp_path):
    """`check_capture` (a batch's check before Ray) read scene.json itself as plain UTF-8: a
    file with a byte-order mark, which the loader reads, was refused. It now calls the loader
    (no image read); a broken one is refused with its reason."""
    from captures.open import check_capture

    path = _peer_folder(tmp_path / "peer", "view_00.exr", {"base_color": [0.5] * 3})
    path.write_bytes(b"\xef\xbb\xbf" + path.read_bytes())
    check_capture(tmp_path / "peer")  # no image on disk: not read
    path.write_text("{", encoding="utf-8")
    with pytest.raises(CaptureError, match="not valid JSON"):
        check_capture(path)


def _look_at_matrix(origin, target, up) -> list[list[float]]:
    """Blender's `matrix_world` of a camera at `origin` looking at `target`: columns x, y (up),
    z (backward) and the position."""
    back = np.subtract(origin, target, dtype=float)
    back /= np.linalg.norm(back)
    x = np.cross(up, back)
    x /= np.linalg.norm(x)
    matrix = np.eye(4)
    matrix[:3, 0], matrix[:3, 1], matrix[:3, 2], matrix[:3, 3] = x, np.cross(back, x), back, origin
    return matrix.tolist()


@pytest.mark.parametrize(
    "change, message",
    [
        (None, None),
        ({"origin": [3, -3, 2.5]}, r"puts the camera at \[3, -3, 2.5\], not at origin"),
        ({"target": [0.5, 0, 0]}, r"looks 5\.03 degrees away from target"),
        ({"up": [0.3, 0, 1]}, r"turns the camera \d+\.\d\d degrees about its view"),
        ("rows", r"= \[\[1, 0\], \[0, 1\]\]: expected a 4x4 matrix"),
    ],
)
def test_a_peer_views_camera_matrix_must_agree_with_its_look_at(tmp_path, change, message):
    """`blender_matrix_world` was listed as read but not read: a matrix of another camera (a
    stale export) beside the look-at values was silent. A disagreeing one is refused by what
    differs; an agreeing one reads."""
    from captures.peer import load_peer_scene

    path = _peer_folder(tmp_path / "peer", "view_00.exr", {"base_color": [0.5] * 3})
    doc = json.loads(path.read_text())
    view = _view(doc)
    moved = {**view, **change} if isinstance(change, dict) else view
    matrix = _look_at_matrix(moved["origin"], moved["target"], moved["up"])
    view["blender_matrix_world"] = [[1, 0], [0, 1]] if change == "rows" else matrix
    path.write_text(json.dumps(doc))
    if message is None:
        load_peer_scene(path)
        return
    with pytest.raises(CaptureError, match=r"views\[0\]\.blender_matrix_world " + message):
        load_peer_scene(path)


@pytest.mark.parametrize("fov, warned", [(40, False), (0.698, True), (2.0, True)])
def test_a_field_of_view_in_radians_is_warned(tmp_path, caplog, fov, warned):
    """A field of view given in radians (Blender's `camera.data.angle`) was taken as degrees:
    0.698 saw a sliver of the object and only the silhouette's overlap warned. Where the object
    spans three times the value or more, the warning gives the value in degrees."""
    from captures.peer import load_peer_scene

    path = _peer_folder(tmp_path / "peer", "view_00.exr", {"base_color": [0.5] * 3})
    doc = json.loads(path.read_text())
    _view(doc)["fov_x_deg"] = fov
    path.write_text(json.dumps(doc))
    with caplog.at_level(logging.WARNING):
        load_peer_scene(path)
    notes = [r.getMessage() for r in caplog.records if "in radians" in r.getMessage()]
    assert bool(notes) == warned
    if warned:
        assert f"views[0].fov_x_deg = {fov:g}" in notes[0]
        assert f"give {np.degrees(fov):.4g} (degrees)" in notes[0]


def test_a_telephoto_view_of_a_far_object_is_not_warned(tmp_path, caplog):
    """A narrow field of view that frames the object (a long lens far away) is not radians."""
    from captures.peer import load_peer_scene

    path = _peer_folder(tmp_path / "peer", "view_00.exr", {"base_color": [0.5] * 3})
    doc = json.loads(path.read_text())
    _view(doc).update(origin=[300, -300, 200], fov_x_deg=0.5)
    path.write_text(json.dumps(doc))
    with caplog.at_level(logging.WARNING):
        load_peer_scene(path)
    assert not [r for r in caplog.records if "in radians" in r.getMessage()]
