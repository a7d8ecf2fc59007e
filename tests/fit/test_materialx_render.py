"""The MaterialX export where it renders: MaterialX's own GLSL renderer (the `materialx` package,
OpenGL under Xvfb with Mesa's llvmpipe) renders the exported document on a peer mesh, against
layerfit's own render of the preset in the same scene.

The hardware renderer has point, spot and directional lights only, no shadows and no
interreflection, so the scene is the peer sphere (convex: neither matters) under its two
rectangle lights made distant: each a directional light along the line from the light to the
object, of the irradiance it gives there (radiance x area / distance^2), with a black
environment. Both renders are noise-free enough to compare pixels: the GLSL one is exact per
sample (`SUPERSAMPLE`^2 samples a pixel, averaged: a box filter as layerfit's), and layerfit
renders each light on its own and sums the images (one light picked per sample left 1.6 % of
noise at 4096 spp; a light alone, 0.1 % at 512).
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from test_blender import compare

from captures import open_capture
from captures.scene import DirectionalLight, RectLight
from fit.commands.export import export
from fit.material import build_material, save_preset
from fit.render import coverage_dict, load_scene, render, scene_dict

SCRIPT = Path(__file__).with_name("materialx_render.py")
PEER = "peer-cycles/sphere-blue"
VIEWS = (0, 1)
#: Samples per pixel of layerfit's render, per light: 512 leave 0.1 % of noise (relative RMSE)
#: on a Lambertian, 0.5 % on the glazed sphere; a stack picks one layer per sample: 2048 leave
#: 1 %; the glossy glaze's highlight spans a few pixels: its brightest 1 % moved by 2 % between
#: seeds at 512, under 1 % at 4096.
SPP = {"lambertian": 512, "stack": 2048, "glossy": 4096, "glazed": 512}
#: Pixels rendered per side of each pixel by the GLSL renderer, averaged: the glossy highlight's
#: brightest 1 % was 1.026 of layerfit's at 2, 1.041 at 4, 1.043 at 8.
SUPERSAMPLE = 4

#: name: material table. A Lambertian (the renderers agree: the scene and light units); two
#: Oren-Nayar layers, the top one masked by an fbm (the baked mask, the `mix` stack, the EON
#: mapping of sigma 0.3); a glossy glaze (alpha 0.0144) and the glazed sphere's (alpha 0.0625).
CASES = {
    "lambertian": {"type": "oren_nayar", "reflectance": [0.5, 0.4, 0.3]},
    "stack": {
        "type": "layered",
        "layers": [
            {"name": "clay", "type": "oren_nayar", "reflectance": [0.6, 0.45, 0.3], "sigma": 0.3},
            {
                "name": "stain",
                "type": "oren_nayar",
                "reflectance": [0.12, 0.1, 0.3],
                "mask": {"scale": 4, "threshold": 0.5, "softness": 0.05},
            },
        ],
    },
    "glossy": {"type": "glaze", "pigment": [0.55, 0.33, 0.12], "roughness": 0.0144, "ior": 1.6},
    "glazed": {
        "type": "glaze",
        "pigment": [0.1, 0.22, 0.55],
        "roughness": 0.0625,
        "ior": 1.52,
        "fresnel": "schlick",
    },
}


@pytest.fixture(scope="module")
def xvfb_run() -> str:
    found = shutil.which("xvfb-run")
    if found is None:
        pytest.skip(
            "no xvfb-run: MaterialX's GLSL renderer needs an X display (`bash scripts/setup.sh "
            "--with-xvfb` installs Xvfb and Mesa)"
        )
    return found


def distant(light: RectLight) -> DirectionalLight:
    """A rectangle light as a directional one: along the line from its centre to the origin (the
    object's centre), of the irradiance it gives there."""
    centre = np.asarray(light.center, np.float64)
    distance2 = float(centre @ centre)
    irradiance = np.multiply(light.radiance, light.size[0] * light.size[1] / distance2)
    direction = -centre / np.sqrt(distance2)
    return DirectionalLight(tuple(map(float, direction)), tuple(map(float, irradiance)))


def glsl_render(xvfb_run: str, mtlx: Path, mesh: Path, scene, out: Path) -> np.ndarray:
    camera = scene.cameras[0]
    spec = {
        "mtlx": str(mtlx),
        "mesh": str(mesh),
        "supersample": SUPERSAMPLE,
        "camera": {
            "origin": list(camera.origin),
            "target": list(camera.target),
            "up": list(camera.up),
            "fov_x_deg": camera.fov_x_deg,
            "width": camera.width,
            "height": camera.height,
        },
        "lights": [
            {"direction": list(light.direction), "irradiance": list(light.irradiance)}
            for light in scene.lights
        ],
    }
    spec_file = out.with_suffix(".json")
    spec_file.write_text(json.dumps(spec))
    args = [xvfb_run, "-a", sys.executable, SCRIPT, spec_file, out]
    done = subprocess.run(
        [str(a) for a in args], capture_output=True, text=True, check=False, timeout=300
    )
    assert done.returncode == 0 and out.is_file(), done.stderr[-3000:]
    return np.load(out)


@pytest.mark.slow
@pytest.mark.parametrize(
    "name",
    [
        "lambertian",
        "stack",
        "glossy",
        pytest.param(
            "glazed",
            marks=pytest.mark.xfail(
                strict=True,
                reason="2026-12-05: the brightest 1 % is 0.88 and 0.91 of layerfit's (views 0, "
                "1), relative RMSE 0.105 and 0.131 (means 1.008, 1.011): the GGX lobe of the "
                "mapped roughness against the Beckmann one at alpha 0.0625 (each renderer "
                "matches its own lobe's closed form within 1 %)",
            ),
        ),
    ],
)
def test_the_materialx_export_renders_as_layerfit_does(name, xvfb_run, shared_data, tmp_path):
    """Mean within 3 %, the brightest 1 % within 5 %; relative RMSE <= 0.05 but on the glossy
    glaze (its few highlight pixels are left to the highlight's check, as in Blender's test)."""
    material = build_material(CASES[name], tmp_path / "preset.toml")
    save_preset(material, tmp_path / "preset.toml")
    mtlx = export(tmp_path / "preset.toml", "materialx", tmp_path / "mtlx", size=512)
    capture = open_capture(shared_data / PEER / "scene.json")
    spp = SPP[name]
    for view in VIEWS:
        scene = capture.scene_of(view)
        scene = replace(scene, lights=tuple(map(distant, scene.lights)), environment=(0.0,) * 3)
        native = sum(
            render(
                load_scene(scene_dict(replace(scene, lights=(light,)), material, 0, spp)), spp, 5
            )
            for light in scene.lights
        )
        coverage = render(load_scene(coverage_dict(scene, 0, 16)), 16)[..., 0]
        mesh = shared_data / PEER / "mesh.obj"
        image = glsl_render(xvfb_run, mtlx, mesh, scene, tmp_path / f"glsl{view}.npy")
        got = compare(image, native, coverage > 0.99)
        assert abs(got["mean"] - 1) <= 0.03, (view, got)
        assert abs(got["highlight"] - 1) <= 0.05, (view, got)
        if name != "glossy":
            assert got["rmse"] <= 0.05, (view, got)
