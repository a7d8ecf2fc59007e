"""Capture manifests and DiLiGenT folders: loading, downscaling, pixel warnings, bad input."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest

from captures import CaptureError
from captures.capture import load_capture, manifest_text
from captures.images import read_linear, write_image
from captures.importers import diligent_capture, fit_sphere_to_mask

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
