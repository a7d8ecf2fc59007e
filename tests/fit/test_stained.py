"""A glazed sphere and a torus with a painted stain, rendered by layerfit and fitted back with
the stain's mask free as a texture from a flat start: the stain's place and colour and the
glaze under it. Slow (35-50 s a shape on 2 cores)."""

from __future__ import annotations

import json
import tomllib

import numpy as np
import pytest

from captures.images import write_image
from fit import recovery
from fit.entry import run as main
from fit.material import build_material

TRUTH = {
    "glaze.pigment": [0.1, 0.22, 0.55],
    "glaze.roughness": 0.1,
    "glaze.ior": 1.5,
    "stain.reflectance": [0.45, 0.25, 0.1],
}
#: The fitted texture's size (width, height); the truth's stain is painted at it.
SIZE = (32, 16)


def stain_texture() -> np.ndarray:
    """Diagonal bands over the UV square, 30 % of it, their edges soft over about 3 texels."""
    width, height = SIZE
    v, u = (np.mgrid[0:height, 0:width] + 0.5) / np.array([height, width])[:, None, None]
    phase = (3 * u + 2 * v) % 1.0
    return np.clip((0.15 - np.abs(phase - 0.5)) / 0.1, 0, 1)[..., None].astype(np.float32)


def material(glaze: dict, stain: list, mask: str = "") -> str:
    return f"""[material]
type = "layered"
[[material.layers]]
name = "glaze"
type = "glaze"
pigment = {glaze["glaze.pigment"]}
roughness = {glaze["glaze.roughness"]}
ior = {glaze["glaze.ior"]}
[[material.layers]]
name = "stain"
type = "oren_nayar"
reflectance = {stain}
sigma = 0.3
[material.layers.mask]
{mask}threshold = 0.0
softness = 0.005
"""


#: Per shape: the least stain IoU, the glaze pigment's and the stain colour's largest errors.
#: Measured (fit seed 0, the test's): the sphere IoU 0.978, pigment 0.0015, stain 0.0028; the
#: torus, smaller in the views, IoU 0.961, pigment 0.0012, stain 0.0103 (over seeds 0-2 IoU
#: 0.96-0.97, the stain colour 0.002-0.010; 0.010-0.020, over this bound on seed 0, with the
#: last Adam phase at lr 0.03: `TEXTURE_LR`). With the masks' plain sigmoid (their texels
#: never on the bounds: `materials.params.OVERSHOOT`) and 60 full-resolution Adam steps the
#: torus's colours were 0.024 off, its IoU 0.90; from a mask of ones it lost its layers apart
#: (IoU 0.36, ior +0.28). Both: ior within 0.03, alpha within 5 % (measured 0.0015 and 0.0055;
#: 2.6 and 1.2 %).
BOUNDS = {"sphere": (0.9, 0.02, 0.02), "torus": (0.9, 0.02, 0.02)}
#: The largest error in reported sd of any scalar (measured 2.3 on the sphere, 1.7 on the torus;
#: over seeds 0-2 of both at most 2.3).
SD_BOUND = 3.0


@pytest.mark.slow
@pytest.mark.parametrize("shape", list(BOUNDS))
def test_a_stained_object_is_recovered_with_its_stain(tmp_path, shape):
    """The stain's mask (its share above one half where the views see) against the truth's by
    IoU, the glaze's pigment, ior and alpha, and the stain's colour (`BOUNDS`)."""
    from fit.commands.synth import synthesize

    write_image(tmp_path / "stain.exr", stain_texture())
    scene = recovery.studio(shape, 160, 120)
    table = tomllib.loads(material(TRUTH, TRUTH["stain.reflectance"], 'texture = "stain.exr"\n'))
    truth = build_material(table["material"], tmp_path / "truth.toml")
    synthesize(scene, truth, tmp_path / "capture", spp=256)
    start = {"glaze.pigment": [0.5] * 3, "glaze.roughness": 0.2, "glaze.ior": 1.3}
    width, height = SIZE
    (tmp_path / "fit.toml").write_text(
        f"""capture = "capture"
[fit]
free = ["glaze.pigment", "glaze.roughness", "glaze.ior", "stain.reflectance", "stain.mask.texture"]
[fit.textures]
"stain.mask.texture" = [{width}, {height}]
"""
        + material(start, [0.5] * 3)
    )
    with pytest.raises(SystemExit) as exit_:
        main(["fit", str(tmp_path / "fit.toml"), "--out", str(tmp_path / "run")])
    assert exit_.value.code == 0
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    iou, pigment, colour = BOUNDS[shape]
    assert summary["mask_iou"]["stain"] >= iou, summary["mask_iou"]
    # the share's root mean square error where seen (measured on fit seed 2: sphere 0.018, torus
    # 0.023; the painted bands are 0 or 1, so it is their edges')
    assert summary["mask_rmse"]["stain"] <= 0.05, summary["mask_rmse"]
    # the fitted texels can hold the painted bands: else this measures the size, not the fit
    assert summary["mask_iou_resampled"] == {"stain": pytest.approx(1.0, abs=1.0 - iou)}, summary
    values = summary["values"]
    error = np.subtract(values["glaze.pigment"], TRUTH["glaze.pigment"])
    assert np.max(np.abs(error)) <= pigment, values["glaze.pigment"]
    assert abs(values["glaze.ior"] - TRUTH["glaze.ior"]) <= 0.03
    assert abs(values["glaze.roughness"] / TRUTH["glaze.roughness"] - 1) <= 0.05
    stain = np.subtract(values["stain.reflectance"], TRUTH["stain.reflectance"])
    assert np.max(np.abs(stain)) <= colour, values["stain.reflectance"]
    # the scalars' sd with the mask's texels refitted beside them (`texel_trade`): the colours'
    # errors were 8-22 sd with the texels held; with the trade every error within 2.3 sd (seeds
    # 0-2 of both shapes)
    over = {k: np.max(np.abs(v)) for k, v in summary["error_over_std"].items()}
    assert max(over.values()) <= SD_BOUND, over
