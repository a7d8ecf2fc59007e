"""The bundled cup capture (captures/samples/cup): what the main job fits is what its
README promises: 4 to 6 thin-lens views as 16-bit PNG with different exposures, under 1 %
clipped pixels, under 2 MB, and the truth of every parameter the main job frees."""

from __future__ import annotations

import tomllib
from pathlib import Path

import numpy as np
import OpenImageIO as oiio

from captures import open_capture

ROOT = Path(__file__).resolve().parents[2]
SAMPLE = ROOT / "captures" / "samples" / "cup"


def test_bundled_cup_capture_is_what_the_readme_says():
    capture = open_capture(SAMPLE)
    assert 4 <= len(capture.views) <= 6
    assert sum(p.stat().st_size for p in SAMPLE.iterdir()) < 2_000_000
    for view in capture.views:
        assert view.camera.aperture_radius > 0  # thin lens: depth of field
    exposures = [
        v["exposure_ev"] for v in tomllib.loads((SAMPLE / "capture.toml").read_text())["views"]
    ]
    assert len(set(exposures)) == len(exposures)  # an offset per view
    for png in sorted(SAMPLE.glob("*.png")):
        image = oiio.ImageBuf(str(png))
        assert image.spec().format == oiio.UINT16, png.name
        pixels = image.get_pixels(oiio.UINT16)
        assert np.mean(np.any(pixels == 65535, axis=-1)) < 0.01, png.name


def test_the_main_job_frees_only_what_the_capture_knows():
    free = tomllib.loads((ROOT / "configs" / "cup-fit.toml").read_text())["fit"]["free"]
    truth = open_capture(SAMPLE).truth
    assert set(free) <= set(truth), set(free) - set(truth)


def test_the_cup_capture_holds_the_masks_it_was_rendered_with():
    """`[truth_textures]`: the painted masks of configs/cup.toml, which `mask_iou` scores the
    fitted masks against (configs/cup-masks-fit.toml frees them)."""
    truth = open_capture(SAMPLE).truth_textures
    assert set(truth) == {"glaze.mask.texture", "lime.mask.texture", "stain.mask.texture"}
    for key, path in truth.items():
        painted = ROOT / "configs" / "textures" / f"{key.split('.')[0]}.exr"
        read = [oiio.ImageBuf(str(p)).get_pixels(oiio.FLOAT) for p in (path, painted)]
        np.testing.assert_array_equal(*read)
