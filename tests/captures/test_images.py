"""Image readers (EXR channels, parts, frames, alpha, masks, orientation, primaries) and weights."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from image_files import _oiio_write

from captures import CaptureError
from captures.images import read_linear, write_image
from captures.weights import downscale, validity


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


def test_a_grey_and_alpha_mask_is_read_by_its_grey(tmp_path):
    """A mask saved as grey and alpha (alpha 1 everywhere) made every pixel the object: its
    alpha was read as a colour channel."""
    from captures.images import read_mask

    stored = np.zeros((6, 8, 2), np.uint8)
    stored[2:4, 3:6, 0] = 255
    stored[..., 1] = 255
    mask = read_mask(_png(tmp_path / "mask.png", stored))
    assert mask.sum() == 6 and mask[2:4, 3:6].all()


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


@pytest.mark.parametrize("factor", [2, 3, 4, 7])
def test_a_downscaled_photo_leaves_out_pixels_partly_over_what_a_render_would_not(factor):
    """A disc whose mask leaves the background out of the weights, with a clipped highlight
    (a bright pixel left out) and a clipped black (a black one left out) on it. Area-averaged,
    an output pixel partly over the background or the highlight gets weight 0 (the photo's
    mean there leaves out what a render's takes in); one partly over the black pixel keeps its
    valid share (its true value is about a render's); pixels wholly on the disc keep their
    mean and weight."""
    from captures.capture import Capture, View
    from captures.scene import Camera, Scene, Sphere

    n = 60
    yy, xx = np.mgrid[0:n, 0:n]
    disc = (xx + 0.5 - n / 2) ** 2 + (yy + 0.5 - n / 2) ** 2 <= (0.4 * n) ** 2
    image = np.where(disc[..., None], 0.6, 0.0).astype(np.float32) * np.ones(3, np.float32)
    weight = disc.astype(np.float32)
    bright, black = (n // 2, n // 2), (n // 2 + 7, n // 2)
    image[bright], weight[bright] = 5.0, 0.0  # saturated
    image[black], weight[black] = 0.0, 0.0  # clipped black
    camera = Camera((0.0, -5.0, 0.0), (0.0, 0.0, 0.0), (0.0, 0.0, 1.0), 30.0, n, n)
    view = dataclasses.replace(View("v", image, weight, camera), mask=disc)
    small = Capture(Scene(Sphere(), (camera,)), [view]).downscaled(factor).views[0]
    plain_image, plain = downscale(image, weight, factor)

    def over(pixels):  # output pixels whose area is partly over these input pixels
        return downscale(pixels[..., None] * np.ones(3), np.ones((n, n)), factor)[0][..., 0] > 0

    on_disc = ~over(~disc)
    partly = (plain > 0) & ~on_disc
    lit = np.zeros((n, n), bool)
    lit[bright] = True
    dark = np.zeros((n, n), bool)
    dark[black] = True
    assert partly.any() and np.all(small.weight[partly] == 0)
    assert np.all(small.weight[over(lit)] == 0)
    kept = on_disc & ~over(lit)
    assert kept.sum() >= 9 and np.all(small.weight[kept] > 0)
    np.testing.assert_array_equal(small.weight[kept], plain[kept])
    np.testing.assert_array_equal(small.image[kept], plain_image[kept])
    np.testing.assert_allclose(small.image[kept], 0.6, rtol=1e-6)
    assert (kept & over(dark)).any() and np.all(small.weight[kept & over(dark)] < 1)


def test_without_a_mask_only_a_clipped_highlight_leaves_out_its_neighbours():
    """A view without a mask, its background black and left out (clipped black) beside a lit
    disc with a clipped highlight: area-averaged, the pixels partly over the highlight get
    weight 0, those over the disc's outline keep their valid share (a black pixel's true value
    is about a render's there)."""
    from captures.capture import Capture, View
    from captures.scene import Camera, Scene, Sphere

    n = 40
    yy, xx = np.mgrid[0:n, 0:n]
    disc = (xx + 0.5 - n / 2) ** 2 + (yy + 0.5 - n / 2) ** 2 <= (0.4 * n) ** 2
    image = np.where(disc[..., None], 0.6, 0.0).astype(np.float32) * np.ones(3, np.float32)
    weight = disc.astype(np.float32)
    image[n // 2, n // 2], weight[n // 2, n // 2] = 5.0, 0.0  # saturated
    camera = Camera((0.0, -5.0, 0.0), (0.0, 0.0, 0.0), (0.0, 0.0, 1.0), 30.0, n, n)
    small = Capture(Scene(Sphere(), (camera,)), [View("v", image, weight, camera)]).downscaled(4)
    _, plain = downscale(image, weight, 4)
    centre = small.views[0].weight[n // 8, n // 8]
    assert plain[n // 8, n // 8] > 0.9 and centre == 0
    outline = (plain > 0) & (plain < 1)
    outline[n // 8, n // 8] = False  # the highlight's
    assert outline.sum() > 8
    np.testing.assert_array_equal(small.views[0].weight[outline], plain[outline])
