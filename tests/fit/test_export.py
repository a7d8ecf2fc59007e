"""`layerfit export`: Mitsuba XML (native, portable), MaterialX and USD read back with each
target's own library; the fitted lobe maps; bad input leaves nothing behind."""

from __future__ import annotations

import os
import subprocess
import sys
import xml.etree.ElementTree as ET
from dataclasses import replace
from pathlib import Path

import mitsuba as mi
import numpy as np
import pytest
from bundled import CUP, SPHERE, cup_material
from test_blender import compare
from typer.testing import CliRunner

from captures.images import read_image
from fit.cli import app
from fit.config import load_render_config
from fit.errors import ConfigError
from fit.export import export
from fit.export.bake import plan
from fit.export.mapping import (
    EON_TABLE,
    GGX_TABLE,
    eon_lambert_factor,
    eon_roughness,
    fit_eon,
    fit_ggx,
    ggx_roughness,
    glaze_diffuse_albedo,
    lambert_scale,
)
from fit.export.mitsuba import (
    coat_diffuse_scale,
    image_difference,
    roughplastic_diffuse_albedo,
    white_sky_albedo,
)
from fit.material import build_material, load_preset, save_preset
from fit.render import bake_texture, coverage_dict, load_scene, render, scene_dict

BUILTIN = {"bumpmap", "blendbsdf", "roughplastic", "diffuse", "bitmap", "rgb"}


def cup_preset(folder: Path) -> Path:
    return save_preset(cup_material(), folder / "cup.toml")


def sphere_preset(folder: Path) -> Path:
    return save_preset(load_render_config(SPHERE).material, folder / "glaze.toml")


def tiny_scene(config: Path, size: int = 32):
    """A config's scene with its first camera at size x size."""
    scene = load_render_config(config).scene
    return replace(scene, cameras=[replace(scene.cameras[0], width=size, height=size)])


def leftovers(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if p.name.startswith("."))


# Mitsuba ------------------------------------------------------------------------------------------


def test_mitsuba_native_renders_as_the_native_material(tmp_path):
    """The XML loads once the plugins are registered and renders the same image as the preset
    (same seed: identical; the scene is the glazed sphere at 32x32, 16 spp)."""
    preset = load_preset(sphere_preset(tmp_path))
    path = export(preset, "mitsuba", tmp_path / "xml")
    assert path == tmp_path / "xml" / "material.xml"
    loaded = mi.load_file(str(path))
    scene = tiny_scene(SPHERE)
    native = render(load_scene(scene_dict(scene, preset.material, 0, 16)), 16, seed=3)
    again = render(load_scene(scene_dict(scene, loaded, 0, 16)), 16, seed=3)
    assert native.mean() > 0.05
    np.testing.assert_array_equal(again, native)


def test_mitsuba_native_cup_keeps_every_parameter_and_texture(tmp_path):
    """The cup's four-layer stack round-trips: every traversed value equal, textures copied
    beside the XML under relative names."""
    preset = load_preset(cup_preset(tmp_path))
    path = export(preset, "mitsuba", tmp_path / "xml")
    text = path.read_text()
    assert 'type="layered"' in text and str(tmp_path) not in text  # relative file names
    assert (path.parent / "glaze.mask.texture.exr").read_bytes() == (
        tmp_path / "cup.glaze.mask.texture.exr"
    ).read_bytes()
    native = mi.traverse(mi.load_dict(preset.material.bsdf))
    loaded = mi.traverse(mi.load_file(str(path)))
    assert sorted(native.keys()) == sorted(loaded.keys())
    for key in native.keys():
        if key.endswith("to_uv"):  # a bitmap's UV transform (identity in both)
            continue
        np.testing.assert_allclose(np.ravel(loaded[key]), np.ravel(native[key]), err_msg=key)


#: fresnel: (mean, brightest 1 %, relative RMSE) the portable glazed sphere keeps to. Measured
#: at 64x64, 4096 spp (seeds apart): Schlick's +0.9 %, +5.6 %, 0.065 (its exact Fresnel is
#: above Schlick's at 45-75 degrees), the exact one's +0.1 %, +0.7 %, 0.049 (with the noise of
#: both renders). `principled` was +6.9 % in the mean (160x120, 8192 spp).
PORTABLE_SPHERE = {"schlick": (0.02, 0.08, 0.08), "exact": (0.01, 0.03, 0.06)}


@pytest.mark.parametrize("fresnel", sorted(PORTABLE_SPHERE))
def test_mitsuba_portable_uses_builtins_only_and_renders_alike(tmp_path, fresnel):
    """--portable: only built-in plugins in the XML; on the glazed sphere (64x64, 4096 spp, its
    object's pixels) its render is within `PORTABLE_SPHERE` of the native one."""
    table = {"type": "glaze", "pigment": [0.1, 0.22, 0.55], "roughness": 0.0625, "ior": 1.52}
    table["fresnel"] = fresnel
    toml = tmp_path / "glaze.toml"
    preset = load_preset(save_preset(build_material(table, toml), toml))
    path = export(preset, "mitsuba", tmp_path / "p", portable=True, size=16)
    types = {e.get("type") for e in ET.parse(path).iter() if e.get("type")}
    assert types <= BUILTIN, types
    scene, spp = tiny_scene(SPHERE, 64), 4096
    native = render(load_scene(scene_dict(scene, preset.material, 0, spp)), spp, seed=1000)
    loaded = mi.load_file(str(path))
    portable = render(load_scene(scene_dict(scene, loaded, 0, spp)), spp, seed=1500)
    coverage = render(load_scene(coverage_dict(scene, 0, 16)), 16)[..., 0]
    got = compare(portable, native, coverage > 0.99)
    mean, highlight, rmse = PORTABLE_SPHERE[fresnel]
    assert abs(got["mean"] - 1) <= mean, got
    assert abs(got["highlight"] - 1) <= highlight, got
    assert got["rmse"] <= rmse, got


@pytest.mark.parametrize("coupling", ["paper", "reciprocal"])
@pytest.mark.parametrize("fresnel", ["schlick", "exact"])
def test_the_portable_glaze_keeps_the_glazes_diffuse_albedo(tmp_path, coupling, fresnel):
    """A glaze exports as `roughplastic` of its alpha and ior, its pigment scaled so that the
    plugin's diffuse part has the white-sky albedo of the glaze's: `glaze_diffuse_albedo`
    against the glaze plugin's own diffuse lobe integrated, and the exported reflectance."""
    pigment = [0.1, 0.22, 0.55]
    table = {"type": "glaze", "pigment": pigment, "roughness": 0.0625, "ior": 1.52}
    table |= {"coupling": coupling, "fresnel": fresnel}
    white = {**table, "pigment": {"type": "rgb", "value": [1.0, 1.0, 1.0]}}
    albedo = glaze_diffuse_albedo(1.52, fresnel, coupling)
    assert white_sky_albedo(white, component=1) == pytest.approx(albedo, rel=2e-3)
    preset = save_preset(build_material(table, tmp_path / "g.toml"), tmp_path / "g.toml")
    path = export(preset, "mitsuba", tmp_path / "p", portable=True)
    params = mi.traverse(mi.load_file(str(path)))
    scale = albedo / roughplastic_diffuse_albedo(0.0625, 1.52)
    assert 0.9 < scale < 1.1  # the coat seen through once or twice; eta^2 (1 - internal F)
    np.testing.assert_allclose(
        np.ravel(params["diffuse_reflectance.value"]), np.multiply(pigment, scale), rtol=1e-5
    )


def test_mitsuba_portable_cup_bakes_masks_and_stacks_blends(tmp_path):
    path = export(cup_preset(tmp_path), "mitsuba", tmp_path / "p", portable=True, size=32)
    root = ET.parse(path).getroot()
    assert root.get("type") == "bumpmap"
    types = [e.get("type") for e in root.iter() if e.get("type")]
    assert set(types) <= BUILTIN and types.count("blendbsdf") == 3
    assert types.count("roughplastic") == 1 and types.count("diffuse") == 3
    material = load_preset(tmp_path / "cup.toml").material
    mask = read_image(path.parent / "lime.mask.exr")[..., 0]
    np.testing.assert_allclose(mask, bake_texture(material.bsdf["lime_mask"], 32, 32), atol=1e-6)
    assert mi.load_file(str(path)) is not None
    # the glaze's pigment noise baked: its mean colour is the pigment (the noise has mean ~1)
    # times the coat's diffuse factor
    (glaze,) = [layer for layer in plan(material, 8).layers if layer.kind == "glaze"]
    colour = read_image(path.parent / "glaze.colour.exr") / coat_diffuse_scale(glaze)
    assert np.allclose(colour.mean((0, 1)), [0.06, 0.20, 0.42], rtol=0.1)
    assert (colour.std((0, 1)) / colour.mean((0, 1))).min() > 0.02  # it varies


def test_mitsuba_portable_loads_in_plain_mitsuba(tmp_path):
    """In a fresh process without layerfit's plugins (another variant, too)."""
    path = export(cup_preset(tmp_path), "mitsuba", tmp_path / "p", portable=True, size=8)
    code = (
        "import sys, mitsuba as mi; mi.set_variant('scalar_rgb'); "
        "print(type(mi.load_file(sys.argv[1])).__name__)"
    )
    done = subprocess.run(
        [sys.executable, "-c", code, str(path)], capture_output=True, text=True, check=False
    )
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "BSDF"


@pytest.mark.slow
def test_mitsuba_cup_renders_alike(tmp_path):
    """The cup at 32x32: the native export renders identically; the portable one's difference
    (one seed, 16 spp) stays below the native render's own noise between seeds."""
    preset = load_preset(cup_preset(tmp_path))
    scene = tiny_scene(CUP)
    images = {}
    for name, portable in (("native", False), ("portable", True)):
        path = export(preset, "mitsuba", tmp_path / name, portable=portable, size=256)
        images[name] = render(load_scene(scene_dict(scene, mi.load_file(str(path)))), 16, 0)
    truth = render(load_scene(scene_dict(scene, preset.material)), 16, 0)
    other = render(load_scene(scene_dict(scene, preset.material)), 16, 1)
    np.testing.assert_array_equal(images["native"], truth)
    assert image_difference(truth, images["portable"]) < image_difference(truth, other)


# MaterialX ----------------------------------------------------------------------------------------


def test_materialx_cup_validates_with_every_definition(tmp_path):
    import MaterialX as mx

    from fit.export.materialx import standard_libraries

    path = export(cup_preset(tmp_path), "materialx", tmp_path / "mtlx", size=32)
    doc = mx.createDocument()
    mx.readFromXmlFile(doc, str(path))
    doc.setDataLibrary(standard_libraries())
    valid, message = doc.validate()
    assert valid, message
    nodes = doc.getNodes()
    assert all(node.getNodeDef() is not None for node in nodes)
    kinds = [node.getCategory() for node in nodes]
    assert kinds.count("open_pbr_surface") == 4 and kinds.count("mix") == 3
    glaze = doc.getNode("glaze")
    assert glaze.getInputValue("specular_roughness") == pytest.approx(ggx_roughness(0.05), 1e-5)
    assert glaze.getInputValue("specular_ior") == pytest.approx(1.5)
    lime = doc.getNode("lime")
    r, k = eon_roughness(0.9)
    assert lime.getInputValue("base_diffuse_roughness") == pytest.approx(r, 1e-5)
    assert np.allclose(
        list(lime.getInputValue("base_color")), np.multiply([0.86, 0.85, 0.8], k), 1e-5
    )
    # the top mix is the stain over the rest, its mask the baked image beside the document
    (material,) = doc.getMaterialNodes()
    top = material.getInput("surfaceshader").getConnectedNode()
    assert top.getInput("fg").getConnectedNode().getName() == "stain"
    mask = top.getInput("mix").getConnectedNode().getInputValue("file")
    assert (path.parent / mask).is_file()


def test_materialx_generates_shaders_with_the_fitted_values(tmp_path):
    """MaterialX's own shader generators (GLSL, OSL, MDL) accept the cup's document, and the
    GLSL holds the mapped values as its uniforms' defaults: the glaze's GGX roughness and ior, a
    layer without specular at `NO_SPECULAR_ROUGHNESS` (rendered with MaterialX's GLSL renderer:
    tests/fit/test_materialx_render.py)."""
    import MaterialX as mx
    from MaterialX import PyMaterialXGenGlsl, PyMaterialXGenMdl, PyMaterialXGenOsl
    from MaterialX import PyMaterialXGenShader as gen

    from fit.export.materialx import NO_SPECULAR_ROUGHNESS, standard_libraries

    path = export(cup_preset(tmp_path), "materialx", tmp_path / "mtlx", size=8)
    doc = mx.createDocument()
    mx.readFromXmlFile(doc, str(path))
    doc.setDataLibrary(standard_libraries())
    code = {}
    for name, generator in (
        ("glsl", PyMaterialXGenGlsl.GlslShaderGenerator.create()),
        ("osl", PyMaterialXGenOsl.OslShaderGenerator.create()),
        ("mdl", PyMaterialXGenMdl.MdlShaderGenerator.create()),
    ):
        context = gen.GenContext(generator)
        context.registerSourceCodeSearchPath(mx.getDefaultDataSearchPath())
        generator.registerTypeDefs(doc)
        (element,) = gen.findRenderableElements(doc)
        code[name] = generator.generate("cup", element, context).getSourceCode(gen.PIXEL_STAGE)
        assert "open_pbr_surface" in code[name], name
    glsl = code["glsl"]
    assert f"uniform float glaze_specular_roughness = {ggx_roughness(0.05):.6f};" in glsl
    assert "uniform float glaze_specular_ior = 1.500000;" in glsl
    assert f"uniform float lime_specular_roughness = {NO_SPECULAR_ROUGHNESS:.6f};" in glsl
    assert "uniform float lime_specular_weight = 0.000000;" in glsl


def test_materialx_single_glaze(tmp_path):
    import MaterialX as mx

    path = export(sphere_preset(tmp_path), "materialx", tmp_path / "mtlx")
    doc = mx.createDocument()
    mx.readFromXmlFile(doc, str(path))
    (surface,) = [n for n in doc.getNodes() if n.getCategory() == "open_pbr_surface"]
    assert surface.getInputValue("specular_roughness") == pytest.approx(ggx_roughness(0.0625), 1e-5)
    assert sorted(p.name for p in path.parent.iterdir()) == [".layerfit-export", "material.mtlx"]


def eon_preset(folder: Path, kind: str = "glaze") -> Path:
    colour = "pigment" if kind == "glaze" else "reflectance"
    table = {"type": kind, colour: [0.7, 0.4, 0.1], "sigma": 0.6, "diffuse": "eon"}
    return save_preset(build_material(table, folder / "eon.toml"), folder / "eon.toml")


def test_an_eon_layer_goes_to_openpbr_as_it_is(tmp_path):
    """OpenPBR's diffuse lobe is EON: a layer with `diffuse = "eon"` keeps its roughness and
    colour (the qualitative model's sigma goes through the fitted table instead)."""
    import MaterialX as mx

    path = export(eon_preset(tmp_path), "materialx", tmp_path / "mtlx")
    doc = mx.createDocument()
    mx.readFromXmlFile(doc, str(path))
    (surface,) = [n for n in doc.getNodes() if n.getCategory() == "open_pbr_surface"]
    assert surface.getInputValue("base_diffuse_roughness") == pytest.approx(0.6, abs=1e-6)
    assert list(surface.getInputValue("base_color")) == pytest.approx([0.7, 0.4, 0.1], abs=1e-6)


def test_an_eon_layer_becomes_a_lambertian_of_its_albedo(tmp_path):
    """USD's and portable Mitsuba's Lambertian gets EON's hemispherical albedo per channel:
    `eon_lambert_factor` against the plugin's own directional albedo, integrated over incidence
    (Gauss-Legendre in cos theta, Monte Carlo per direction)."""
    import drjit as dr
    from pxr import Usd, UsdShade

    colour = np.array([0.7, 0.4, 0.1])
    rgb = {"type": "rgb", "value": list(colour)}
    bsdf = mi.load_dict({"type": "oren_nayar", "sigma": 0.6, "diffuse": "eon", "reflectance": rgb})
    nodes, weights = np.polynomial.legendre.leggauss(6)
    n = 1 << 18
    rng = np.random.default_rng(3)
    hemispherical = np.zeros(3)
    for node, weight in zip(nodes, weights, strict=True):
        mu = 0.5 * (node + 1)  # cos theta in (0, 1); weight 2 mu d mu
        si = dr.zeros(mi.SurfaceInteraction3f, n)
        si.wi = mi.Vector3f(float(np.sqrt(1 - mu * mu)), 0.0, float(mu))
        si.sh_frame = mi.Frame3f(mi.Vector3f(0.0, 0.0, 1.0))
        u = rng.random((3, n), dtype=np.float32)
        _, value = bsdf.sample(mi.BSDFContext(), si, mi.Float(u[0]), mi.Point2f(u[1], u[2]))
        hemispherical += 0.5 * weight * 2 * mu * np.asarray(value).mean(axis=1)
    factor = eon_lambert_factor(colour, 0.6)
    np.testing.assert_allclose(colour * factor, hemispherical, rtol=4e-3)
    assert np.all(factor < 1.0) and eon_lambert_factor(1.0, 0.6) == pytest.approx(1.0)
    path = export(eon_preset(tmp_path, "oren_nayar"), "usd", tmp_path / "usd")
    stage = Usd.Stage.Open(str(path))
    shader = UsdShade.Shader(stage.GetPrimAtPath("/Material/PreviewSurface"))
    np.testing.assert_allclose(shader.GetInput("diffuseColor").Get(), colour * factor, rtol=1e-5)
    xml = export(eon_preset(tmp_path, "oren_nayar"), "mitsuba", tmp_path / "xml", portable=True)
    loaded = mi.traverse(mi.load_file(str(xml)))
    np.testing.assert_allclose(np.ravel(loaded["reflectance.value"]), colour * factor, rtol=1e-5)


# USD ----------------------------------------------------------------------------------------------


def test_usd_cup_reads_back_with_its_maps(tmp_path):
    from pxr import Usd, UsdShade

    path = export(cup_preset(tmp_path), "usd", tmp_path / "usd", size=32)
    stage = Usd.Stage.Open(str(path))
    assert "one ior for base and clearcoat" in stage.GetMetadata("comment")
    shader = UsdShade.Shader(stage.GetPrimAtPath("/Material/PreviewSurface"))
    assert shader.GetIdAttr().Get() == "UsdPreviewSurface"
    assert shader.GetInput("roughness").Get() == pytest.approx(ggx_roughness(0.05), 1e-6)
    assert shader.GetInput("ior").Get() == pytest.approx(1.5)
    source = shader.GetInput("diffuseColor").GetConnectedSources()[0][0].source
    texture = UsdShade.Shader(source.GetPrim())
    assert texture.GetIdAttr().Get() == "UsdUVTexture"
    st = texture.GetInput("st").GetConnectedSources()[0][0].source
    assert UsdShade.Shader(st.GetPrim()).GetIdAttr().Get() == "UsdPrimvarReader_float2"
    diffuse = read_image(path.parent / texture.GetInput("file").Get().path)
    # the baked diffuse colour is the share-weighted sum of the layers' colours
    baked = plan(load_preset(tmp_path / "cup.toml").material, 32)
    expected = sum(
        w[..., None] * baked.colour_image(layer) * lambert_scale(layer.sigma)
        for w, layer in zip(baked.shares(), baked.layers, strict=True)
    )
    np.testing.assert_allclose(diffuse, expected, atol=1e-5)
    material = UsdShade.Material(stage.GetPrimAtPath("/Material"))
    assert material.ComputeSurfaceSource()[0].GetPath() == shader.GetPath()


def test_usd_single_glaze_is_constants(tmp_path):
    from pxr import Usd, UsdShade

    path = export(sphere_preset(tmp_path), "usd", tmp_path / "usd")
    stage = Usd.Stage.Open(str(path))  # held: its prims are valid while it lives
    shader = UsdShade.Shader(stage.GetPrimAtPath("/Material/PreviewSurface"))
    pigment = np.multiply([0.1, 0.22, 0.55], lambert_scale(0.0))
    assert np.allclose(list(shader.GetInput("diffuseColor").Get()), pigment)
    # the glaze covers it whole: the metallic workflow, its reflection from the ior (Blender
    # read a specularColor as a Specular Tint: highlights 0.90 and 0.76 of layerfit's own)
    assert shader.GetInput("useSpecularWorkflow").Get() == 0 and not shader.GetInput(
        "specularColor"
    )
    assert shader.GetInput("metallic").Get() == 0 and shader.GetInput("ior").Get() == pytest.approx(
        1.52
    )


def test_usd_textured_oren_nayar_bakes_its_texture(tmp_path):
    """A texture-valued colour is baked texel for texel (scaled by the Lambert factor)."""
    from captures.images import write_image

    texels = np.random.default_rng(1).uniform(0.1, 0.9, (8, 8, 3)).astype(np.float32)
    write_image(tmp_path / "albedo.exr", texels)
    table = {"type": "oren_nayar", "reflectance": "albedo.exr", "sigma": 0.3}
    preset = save_preset(build_material(table, tmp_path / "m.toml"), tmp_path / "m.toml")
    path = export(preset, "usd", tmp_path / "usd", size=8)
    baked = read_image(path.parent / "diffuseColor.exr")
    np.testing.assert_allclose(baked, texels * lambert_scale(0.3), rtol=1e-5)


# Mappings -----------------------------------------------------------------------------------------


def test_shipped_tables_are_the_fits():
    """The tables in `mapping` are what the fits give (refitted at two points each), and the
    interpolated maps stay close to a fit between table points."""
    for alpha, r, residual in (GGX_TABLE[2], GGX_TABLE[6]):
        assert fit_ggx(alpha) == pytest.approx((r, residual), abs=2e-4)
    for sigma, r, k, residual in (EON_TABLE[3], EON_TABLE[9]):
        assert fit_eon(sigma) == pytest.approx((r, k, residual), abs=2e-4)
    assert ggx_roughness(0.05) == pytest.approx(fit_ggx(0.05)[0], abs=0.01)
    assert eon_roughness(0.45)[0] == pytest.approx(fit_eon(0.45)[0], abs=0.01)
    assert ggx_roughness(0.01) ** 2 == pytest.approx(0.01, rel=0.1)  # sharp lobes: alpha ~ r^2


def test_sigma_zero_maps_to_lambert_exactly():
    assert eon_roughness(0.0) == (0.0, 1.0) and lambert_scale(0.0) == 1.0


# The command --------------------------------------------------------------------------------------


def cli(*args):
    return CliRunner().invoke(app, [str(a) for a in args])


def test_cli_exports_and_refuses_to_overwrite(tmp_path):
    preset = sphere_preset(tmp_path)
    out = tmp_path / "x"
    first = cli("export", preset, "--to", "usd", "--out", out)
    assert first.exit_code == 0, first.output
    assert (out / "material.usda").is_file()
    again = cli("export", preset, "--to", "usd", "--out", out)
    assert again.exit_code == 2 and "exists and is not empty; pass --force" in again.output
    forced = cli("export", preset, "--to", "materialx", "--out", out, "--force")
    assert forced.exit_code == 0, forced.output
    assert sorted(p.name for p in out.iterdir()) == [".layerfit-export", "material.mtlx"]
    assert leftovers(tmp_path) == []
    # a user's files beside an earlier export: `--force` would delete them with the folder
    (out / "scene.xml").write_text("<scene/>")
    (out / "meshes").mkdir()
    kept = cli("export", preset, "--to", "mitsuba", "--out", out, "--force")
    assert kept.exit_code == 2, kept.output
    assert "also holds meshes, scene.xml, which the earlier export did not write" in kept.output
    assert sorted(p.name for p in out.iterdir()) == [
        ".layerfit-export",
        "material.mtlx",
        "meshes",
        "scene.xml",
    ]
    # a file without an extension named like a node of the material (`material`, a layer's
    # name) is not one the export wrote: it was deleted with the folder
    (out / "scene.xml").unlink(), (out / "meshes").rmdir()
    (out / "material").write_text("notes")
    kept = cli("export", preset, "--to", "usd", "--out", out, "--force")
    assert kept.exit_code == 2 and "also holds material," in kept.output, kept.output
    assert (out / "material").read_text() == "notes"


def test_cli_force_never_replaces_a_users_own_material_folder(tmp_path):
    """A user's hand-written material.xml and the texture it names looked like an earlier
    export, and `--force` replaced the folder; an export writes a marker, and without it the
    folder is refused."""
    preset = sphere_preset(tmp_path)
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "material.xml").write_text('<bsdf type="diffuse"><texture filename="wood.png"/></bsdf>')
    (mine / "wood.png").write_bytes(b"png")
    result = cli("export", preset, "--to", "usd", "--out", mine, "--force")
    assert result.exit_code == 2 and "no .layerfit-export" in result.output, result.output
    assert sorted(p.name for p in mine.iterdir()) == ["material.xml", "wood.png"]


def test_cli_default_out_of_a_bare_preset_toml(tmp_path, monkeypatch):
    """`layerfit export preset.toml` in a run folder names the export after that folder (it
    wrote out/-usd: the relative path's parent has no name)."""
    run = tmp_path / "run7"
    run.mkdir()
    save_preset(load_render_config(SPHERE).material, run / "preset.toml")
    monkeypatch.chdir(run)
    result = cli("export", "preset.toml", "--to", "usd")
    assert result.exit_code == 0, result.output
    assert (run / "out" / "run7-usd" / "material.usda").is_file()


def test_cli_force_replaces_only_an_export(tmp_path, monkeypatch):
    """`--force` replaces an earlier export, never a user's own folder nor the current folder
    (refused before any work, nothing left behind); a new export folder is readable by others
    as the umask allows (not mkdtemp's 0700)."""
    preset = sphere_preset(tmp_path)
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "thesis.txt").write_text("draft")
    refused = cli("export", preset, "--to", "usd", "--out", mine, "--force")
    assert refused.exit_code == 2 and "not a layerfit export" in refused.output
    assert [p.name for p in mine.iterdir()] == ["thesis.txt"]
    monkeypatch.chdir(mine)
    here = cli("export", preset, "--to", "usd", "--out", ".", "--force")
    assert here.exit_code == 2 and "current folder" in here.output, here.output
    assert [p.name for p in mine.iterdir()] == ["thesis.txt"] and leftovers(tmp_path) == []
    monkeypatch.chdir(tmp_path)
    umask = os.umask(0o022)
    try:
        made = cli("export", preset, "--to", "mitsuba", "--out", tmp_path / "new")
    finally:
        os.umask(umask)
    assert made.exit_code == 0, made.output
    assert (tmp_path / "new").stat().st_mode & 0o777 == 0o755


def test_cli_never_replaces_the_folder_holding_its_input(tmp_path):
    """`--out` the preset's own folder, even with --force: refused before any work (replacing it
    would delete the preset and its run folder)."""
    preset = cup_preset(tmp_path)
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir() if p.is_file()}
    result = cli("export", preset, "--to", "usd", "--out", tmp_path, "--force")
    assert result.exit_code == 2
    (line,) = [x for x in result.output.splitlines() if x.strip()]
    assert "is an input of this command" in line
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir() if p.is_file()} == before


@pytest.mark.parametrize("case", ["schema", "texture", "file", "target"])
def test_cli_bad_input_is_one_line_and_writes_nothing(tmp_path, case):
    preset = cup_preset(tmp_path)
    out, args = tmp_path / "out", ["--to", "mitsuba"]
    if case == "schema":
        preset.write_text(preset.read_text().replace("schema = 1", "schema = 7"))
        message = "schema = 7 was written by a newer layerfit"
    elif case == "texture":
        (tmp_path / "cup.lime.mask.texture.exr").unlink()
        message = "material.lime.mask.texture"
    elif case == "file":
        out.write_text("not a folder")
        message = "is a file; give --out a folder"
    else:
        args, message = ["--to", "blender"], "choose one of mitsuba, materialx, usd"
    before = sorted(p.name for p in tmp_path.iterdir())
    result = cli("export", preset, *args, "--out", out)
    assert result.exit_code == 2
    (line,) = [x for x in result.output.splitlines() if x.strip()]
    assert message in line
    assert sorted(p.name for p in tmp_path.iterdir()) == before


def test_an_interrupted_export_leaves_nothing(tmp_path):
    """A failure while baking (here Ctrl-C) removes the partial folder and keeps the old one."""
    preset = cup_preset(tmp_path)
    out = tmp_path / "out"
    out.mkdir()
    (out / "material.usda").write_text("an earlier export")
    (out / ".layerfit-export").write_text("layerfit export: usd, material.usda\n")

    def interrupt(done, total):
        if done == 2:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        export(preset, "materialx", out, force=True, size=16, progress=interrupt)
    assert sorted(p.name for p in out.iterdir()) == [".layerfit-export", "material.usda"]
    assert leftovers(tmp_path) == []


def test_cli_ctrl_c_is_one_line(tmp_path, monkeypatch):
    """Ctrl-C while exporting: one `interrupted:` line, exit 130, nothing written."""
    import fit.export

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(fit.export, "export", interrupted)
    preset = sphere_preset(tmp_path)
    result = cli("export", preset, "--to", "usd", "--out", tmp_path / "x")
    assert result.exit_code == 130
    (line,) = [x for x in result.output.splitlines() if "interrupted" in x]
    assert "interrupted: nothing written" in line and "Traceback" not in result.output
    assert not (tmp_path / "x").exists()


@pytest.mark.parametrize("name", ["material", "float", "BSDF"])
def test_materialx_layer_named_as_a_library_element(tmp_path, name):
    """A layer named like an element of MaterialX's standard libraries (a type, a definition)
    made the document fail validation; its nodes now take a free name."""
    import MaterialX as mx

    table = {
        "type": "layered",
        "layers": [
            {"name": "clay", "type": "oren_nayar"},
            {"name": name, "type": "glaze", "mask": {"threshold": 0.5, "octaves": 1}},
        ],
    }
    preset = save_preset(build_material(table, tmp_path / "m.toml"), tmp_path / "m.toml")
    path = export(preset, "materialx", tmp_path / "out", size=8)
    doc = mx.createDocument()
    mx.readFromXmlFile(doc, str(path))
    surfaces = [n.getName() for n in doc.getNodes() if n.getCategory() == "open_pbr_surface"]
    assert sorted(surfaces) == sorted(["clay", f"{name}_"])


def test_baking_in_bands_is_baking_at_once(tmp_path, monkeypatch):
    """Masks and colours are evaluated a band of rows at a time (a 16384-texel square at once
    held a surface interaction per texel: tens of GB); the bands change nothing, the last one
    shorter than the others. The largest size is refused before any work."""
    import fit.render.bake as render_bake

    material = cup_material()
    whole = plan(material, 24)
    monkeypatch.setattr(render_bake, "BAND_TEXELS", 130)  # 5 rows of 24 a band: 5x4 + 4
    banded = plan(material, 24)
    for a, b in zip(whole.layers, banded.layers, strict=True):
        for field in ("mask", "colour_map"):
            x, y = getattr(a, field), getattr(b, field)
            assert (x is None) == (y is None)
            if x is not None:
                np.testing.assert_array_equal(x, y)
    assert any(layer.colour_map is not None for layer in whole.layers)
    with pytest.raises(ConfigError, match="--size 8193: give texels per side from 1 to 8192"):
        export(cup_preset(tmp_path), "usd", tmp_path / "out", size=8193)
    assert not (tmp_path / "out").exists()
