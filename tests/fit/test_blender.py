"""The USD export where artists open it: Blender (bpy, Cycles) renders the exported material in a
peer scene, and the `--with-scene` stage alone, against layerfit's own render of the same preset
in the same scene."""

from __future__ import annotations

import subprocess
from pathlib import Path

import numpy as np
import pytest

from captures import open_capture
from captures.images import read_image
from fit.commands.export import export
from fit.material import build_material, save_preset
from fit.render import coverage_dict, load_scene, render, scene_dict

ROOT = Path(__file__).resolve().parents[2]
BLENDER = ROOT / ".venv-blender" / "bin" / "python"
SCRIPT = Path(__file__).with_name("blender_render.py")
STAGE_SCRIPT = Path(__file__).with_name("blender_stage_render.py")
#: Samples per pixel of both renders: at 256 the brightest 1 % of a Lambertian sphere differed
#: by 9 % (their noise), at 2048 by 2.5 % (mean within 0.05 %, relative RMSE 0.03).
SPP = 2048

#: name: (peer scene, glaze, views). A glazed ivory sphere, and a glossy amber torus (view 4 of
#: the torus looks from behind a light: a black card in Mitsuba, nothing in Cycles).
CASES = {
    "sphere": (
        "peer-cycles/sphere-blue",
        {"pigment": [0.8, 0.75, 0.62], "roughness": 0.2, "ior": 1.45},
        (0, 1),
    ),
    "torus": (
        "peer-cycles/torus-amber",
        {"pigment": [0.55, 0.33, 0.12], "roughness": 0.0144, "ior": 1.6},
        (0, 2),
    ),
}


@pytest.fixture(scope="module")
def blender() -> Path:
    if not BLENDER.is_file():
        pytest.skip(
            f"no Blender Python at {BLENDER}: `bash scripts/setup.sh --with-blender` makes it "
            "(bpy needs Python 3.11)"
        )
    return BLENDER


def compare(blender_image: np.ndarray, native: np.ndarray, mask: np.ndarray) -> dict:
    """Blender's render against layerfit's over the object's pixels: the ratio of their means,
    of their brightest 1 % (each image's own, by luminance), and the relative RMSE."""
    b, n = blender_image[mask], native[mask]

    def top(image):
        luminance = image @ np.array([0.2126, 0.7152, 0.0722])
        return float(np.sort(luminance)[-max(1, len(luminance) // 100) :].mean())

    return {
        "mean": float(b.mean() / n.mean()),
        "highlight": top(b) / top(n),
        "rmse": float(np.sqrt(np.sum((b - n) ** 2) / np.sum(n**2))),
    }


def blender_render(blender: Path, scene_json: Path, view: int, usda: Path, out: Path) -> np.ndarray:
    args = [blender, SCRIPT, scene_json, view, usda, out, SPP]
    done = subprocess.run(
        [str(a) for a in args], capture_output=True, text=True, check=False, timeout=900
    )
    assert done.returncode == 0 and out.is_file(), done.stderr[-3000:]
    return read_image(out)[..., :3]


@pytest.mark.slow
@pytest.mark.parametrize(
    "name",
    [
        pytest.param(
            "sphere",
            marks=pytest.mark.xfail(
                strict=True,
                reason="2026-12-05: the brightest 1 % of view 1 is 0.88 of layerfit's (view 0: "
                "0.99), relative RMSE 0.057 and 0.092: Blender's GGX of the mapped roughness "
                "against the Beckmann lobe at alpha 0.2 (the torus at 0.0144: 6 %)",
            ),
        ),
        "torus",
    ],
)
def test_the_usd_export_renders_in_blender_as_layerfit_does(name, blender, shared_data, tmp_path):
    """Mean within 3 %, the brightest 1 % within 8 % on both shapes; relative RMSE <= 0.05 on
    the sphere (the glossy torus's few highlight pixels are left to the highlight's check).
    Blender's GGX of the mapped roughness is not the Beckmann lobe: the torus's view 0 has its
    brightest 1 % 6.4 % above layerfit's 2048-spp render, 6.2 % above its 16384-spp one
    (means within 0.1 %; 2026-12-06)."""
    peer, glaze, views = CASES[name]
    scene_json = shared_data / peer / "scene.json"
    material = build_material({"type": "glaze", **glaze})
    save_preset(material, tmp_path / "preset.toml")
    usda = export(tmp_path / "preset.toml", "usd", tmp_path / "usd", size=64)
    capture = open_capture(scene_json)
    for view in views:
        scene = capture.scene_of(view)
        native = render(load_scene(scene_dict(scene, material, 0, SPP)), SPP, seed=5)
        coverage = render(load_scene(coverage_dict(scene, 0, 16)), 16)[..., 0]
        image = blender_render(blender, scene_json, view, usda, tmp_path / f"blender{view}.exr")
        got = compare(image, native, coverage > 0.99)
        assert abs(got["mean"] - 1) <= 0.03, (view, got)
        assert abs(got["highlight"] - 1) <= 0.08, (view, got)
        if name == "sphere":
            assert got["rmse"] <= 0.05, (view, got)


#: Samples per pixel of both renders of the stage test: the Lambertian torus's five views at
#: 4096 came within 0.06 % in mean, 1.5-1.9 % in the brightest 1 %, relative RMSE 0.016-0.019
#: (at 256: the brightest 1 % 9-12 % apart, their noise).
STAGE_SPP = 4096
#: A Lambertian: its mapping to UsdPreviewSurface is exact (sigma 0 is the preview surface's
#: diffuse, tests/fit/test_export.py), so what differs is the scene the stage holds.
LAMBERTIAN = {"type": "oren_nayar", "reflectance": [0.55, 0.33, 0.12], "sigma": 0.0}


def stage_capture(name: str, shared_data: Path, folder: Path) -> tuple[Path, tuple[int, ...]]:
    """(capture, views) of a stage case: the peer torus (an OBJ, two rectangles, a world) seen
    from its first view; the analytic sphere (a UV sphere in the stage) lit by a rectangle and
    a point light, seen through a calibrated pinhole and a thin lens."""
    if name == "torus":
        return shared_data / "peer-cycles" / "torus-amber" / "scene.json", (0,)
    from test_usd_scene import LIGHTS, make_capture

    return make_capture(folder / "capture", lights=LIGHTS[:2]), (0, 1)


@pytest.mark.slow
@pytest.mark.parametrize("name", ["torus", "sphere"])
def test_the_scene_stage_renders_in_blender_as_layerfit_does(name, blender, shared_data, tmp_path):
    """`export --with-scene`'s stage alone in Blender (mesh, material, camera, lights, world:
    nothing built from the capture; the resolution from its render settings) against layerfit's
    render of the same view: mean within 3 %, the brightest 1 % within 5 %, relative RMSE
    <= 0.05. Left out, measured (docs/exports.md): a distant light (Blender's importer reads it
    at 4 x its intensity) and an orthographic camera (its aperture read as metres, 10 x wide)."""
    from pxr import Usd, UsdRender

    capture_path, views = stage_capture(name, shared_data, tmp_path)
    material = build_material(LAMBERTIAN)
    save_preset(material, tmp_path / "preset.toml")
    usda = export(
        tmp_path / "preset.toml",
        "usd",
        tmp_path / "usd",
        size=8,
        with_scene=True,
        capture=capture_path,
    )
    stage = Usd.Stage.Open(str(usda))
    capture = open_capture(capture_path)
    for view in views:
        camera = capture.views[view].name
        settings = UsdRender.Settings(stage.GetPrimAtPath(f"/Render/{camera}"))
        width, height = settings.GetResolutionAttr().Get()
        scene = capture.scene_of(view)
        native = render(load_scene(scene_dict(scene, material, 0, STAGE_SPP)), STAGE_SPP, seed=5)
        coverage = render(load_scene(coverage_dict(scene, 0, 16)), 16)[..., 0]
        out = tmp_path / f"blender{view}.exr"
        args = [BLENDER, STAGE_SCRIPT, usda, camera, width, height, out, STAGE_SPP]
        done = subprocess.run(
            [str(a) for a in args], capture_output=True, text=True, check=False, timeout=900
        )
        assert done.returncode == 0 and out.is_file(), done.stderr[-3000:]
        got = compare(read_image(out)[..., :3], native, coverage > 0.99)
        assert abs(got["mean"] - 1) <= 0.03, (view, got)
        assert abs(got["highlight"] - 1) <= 0.05, (view, got)
        assert got["rmse"] <= 0.05, (view, got)
