"""RAW development details with a stand-in for rawpy (no public DNG with a default crop or a
clipping plateau is among the test data): the default crop, its Bayer phase, a plateau below the
white level marked saturated, float32 out. The stand-in has exactly the attributes `read_raw`
reads from rawpy, with LibRaw's conventions (crop origin in full-raw coordinates)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

import captures.raw as raw_module
from captures import CaptureError
from captures.raw import develop, read_raw

WHITE = 65535
# colour index per sensel for an RGGB mosaic, as LibRaw numbers them for "RGBG"
RGGB = np.array([[0, 1], [3, 2]])
LEVEL = {0: 1000.0, 1: 2000.0, 3: 2000.0, 2: 3000.0}  # R, G, B, G2


class FakeRaw:
    """What `rawpy.imread` returns, for a visible mosaic and its sizes."""

    def __init__(self, mosaic: np.ndarray, colors: np.ndarray, sizes: SimpleNamespace):
        self.raw_image_visible = mosaic
        self.raw_colors_visible = colors
        self.raw_pattern = RGGB
        self.color_desc = b"RGBG"
        self.black_level_per_channel = [0, 0, 0, 0]
        self.white_level = WHITE
        self.camera_whitebalance = [2.0, 1.0, 1.5, 0.0]
        self.color_matrix = np.hstack([np.eye(3), np.zeros((3, 1))])
        self.rgb_xyz_matrix = np.zeros((4, 3))
        self.sizes = sizes

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False


def fake_file(tmp_path, monkeypatch, mosaic, colors, **sizes) -> object:
    """A RAW file path whose decoding yields `mosaic` (visible area) with `sizes`."""
    h, w = mosaic.shape
    base = dict(
        raw_height=h + 2,
        raw_width=w + 4,
        top_margin=1,
        left_margin=2,
        crop_top_margin=1,
        crop_left_margin=2,
        crop_height=h,
        crop_width=w,
    )
    fake = FakeRaw(mosaic, colors, SimpleNamespace(**{**base, **sizes}))
    monkeypatch.setattr(raw_module.rawpy, "imread", lambda path: fake)
    path = tmp_path / "x.dng"
    path.write_bytes(b"\0" * (mosaic.size * 2))
    return path


def mosaic_of(colors: np.ndarray) -> np.ndarray:
    return np.vectorize(LEVEL.get)(colors).astype(np.uint16)


def test_default_crop_is_applied_with_its_bayer_phase(tmp_path, monkeypatch):
    colors = np.tile(RGGB, (5, 7))  # 10x14 visible
    mosaic = mosaic_of(colors)
    # crop 6x8 starting one row and two columns into the visible area (full-raw: +1, +2)
    path = fake_file(
        tmp_path,
        monkeypatch,
        mosaic,
        colors,
        crop_top_margin=2,
        crop_left_margin=4,
        crop_height=6,
        crop_width=8,
    )
    image = read_raw(path)
    assert image.camera_rgb.shape == (3, 4, 3)  # the crop, in 2x2 superpixels
    # the crop starts on an odd row (G B / R G): channels still land right
    np.testing.assert_allclose(image.camera_rgb[..., 0], 1000 / WHITE, rtol=1e-6)
    np.testing.assert_allclose(image.camera_rgb[..., 1], 2000 / WHITE, rtol=1e-6)
    np.testing.assert_allclose(image.camera_rgb[..., 2], 3000 / WHITE, rtol=1e-6)
    assert image.camera_rgb.dtype == np.float32 and develop(image).dtype == np.float32


def test_no_crop_when_it_is_the_visible_area(tmp_path, monkeypatch):
    colors = np.tile(RGGB, (5, 7))
    image = read_raw(fake_file(tmp_path, monkeypatch, mosaic_of(colors), colors))
    assert image.camera_rgb.shape == (5, 7, 3)


@pytest.mark.parametrize("clipped, flagged", [(40, True), (1, False)])
def test_a_plateau_below_the_white_level_is_saturated(tmp_path, monkeypatch, clipped, flagged):
    """A camera clipping at 65472 (white level 65535): sensels at that plateau are saturated; a
    single sensel at the peak is not a plateau."""
    colors = np.tile(RGGB, (20, 20))
    mosaic = mosaic_of(colors)
    rows, cols = np.unravel_index(np.arange(clipped) * 7, mosaic.shape)
    mosaic[rows, cols] = 65472
    image = read_raw(fake_file(tmp_path, monkeypatch, mosaic, colors))
    expected = np.zeros((20, 20), bool)
    expected[rows // 2, cols // 2] = flagged
    np.testing.assert_array_equal(image.saturated, expected)


def test_a_file_too_small_for_its_sensels_is_refused(tmp_path, monkeypatch):
    colors = np.tile(RGGB, (5, 7))
    path = fake_file(tmp_path, monkeypatch, mosaic_of(colors), colors, raw_height=4000)
    with pytest.raises(raw_module.CaptureError, match="holds no usable picture"):
        read_raw(path)


def test_a_raw_that_is_not_a_mosaic_is_one_line(tmp_path, monkeypatch):
    """rawpy raises RuntimeError ("RAW image is not flat") for a linear DNG, sRAW or Foveon
    file; it escaped as an internal error."""

    class Linear(FakeRaw):
        @property
        def raw_colors_visible(self):
            raise RuntimeError("RAW image is not flat")

        @raw_colors_visible.setter
        def raw_colors_visible(self, value):
            pass

    colors = np.tile(RGGB, (5, 7))
    path = fake_file(tmp_path, monkeypatch, mosaic_of(colors), colors)
    fake = Linear(mosaic_of(colors), colors, SimpleNamespace(raw_height=10, raw_width=14))
    monkeypatch.setattr(raw_module.rawpy, "imread", lambda path: fake)
    with pytest.raises(raw_module.CaptureError, match=r"x\.dng: not a Bayer mosaic .*linear"):
        read_raw(path)


def test_a_raw_without_as_shot_white_balance_takes_given_multipliers(tmp_path, monkeypatch):
    """A file that records no as-shot white balance was refused outright, though its manifest
    can give multipliers; now only `white_balance = "camera"` is refused, by name."""
    colors = np.tile(RGGB, (5, 7))
    path = fake_file(tmp_path, monkeypatch, mosaic_of(colors), colors)
    raw_module.rawpy.imread(path).camera_whitebalance = [0.0, 0.0, 0.0, 0.0]
    image = read_raw(path)
    assert image.camera_wb is None
    balanced = develop(image, np.array([0.5, 1.0, 2.0]))
    np.testing.assert_allclose(balanced[0, 0], [500 / WHITE, 2000 / WHITE, 6000 / WHITE], rtol=1e-5)
    with pytest.raises(raw_module.CaptureError, match=r"x\.dng: .*no as-shot white balance; set"):
        develop(image, "camera")


def test_the_xyz_fallback_matrix_keeps_saturated_colours():
    """Where a file has no colour matrix, the camera <- XYZ one is turned into white-balanced
    camera RGB -> Rec.709 as LibRaw does (rows of the camera's response scaled, then inverted).
    A camera seeing Rec.709 colours, white balanced, developed: each colour comes back in
    proportion. (Scaling the inverse's rows kept greys but not (0.5, 0.1, 0.1).)"""
    from captures.color import XYZ_TO_REC709

    rgb_xyz = np.array([[0.9, 0.2, -0.1], [-0.3, 1.2, 0.1], [0.0, -0.2, 0.9]])  # a camera's
    response = rgb_xyz @ np.linalg.inv(XYZ_TO_REC709)  # camera RGB of Rec.709 primaries
    wb = 1.0 / (response @ np.ones(3))
    matrix = raw_module.camera_to_rec709(rgb_xyz)
    colours = np.array([[0.5, 0.1, 0.1], [0.1, 0.6, 0.2], [0.3, 0.3, 0.3], [0.05, 0.1, 0.7]])
    developed = (colours @ response.T * wb) @ matrix.T
    np.testing.assert_allclose(developed / developed[2, 1], colours / 0.3, rtol=1e-9)


@pytest.mark.parametrize("flip", [3, 5, 6])
def test_a_raw_the_camera_recorded_turned_is_refused(tmp_path, monkeypatch, flip):
    """A RAW from a camera held upright (LibRaw's flip 3, 5 or 6): its sensels were read as the
    sensor stored them without a word; refused with the fix for either set-up. flip 0 reads."""
    colors = np.tile(RGGB, (5, 7))
    path = fake_file(tmp_path, monkeypatch, mosaic_of(colors), colors, flip=flip)
    with pytest.raises(CaptureError, match="the camera recorded it turned"):
        raw_module.read_raw(path)
    path = fake_file(tmp_path, monkeypatch, mosaic_of(colors), colors, flip=0)
    assert raw_module.read_raw(path) is not None
