"""RAW development: linear camera RGB, white balance, and files LibRaw cannot use named."""

from __future__ import annotations

import numpy as np
import pytest

from captures import CaptureError
from captures.raw import develop, read_raw, white_balance_from_patch

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
