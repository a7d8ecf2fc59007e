"""USD: a `.usda` layer with one `UsdPreviewSurface` material, baked maps through `UsdUVTexture`.

UsdPreviewSurface is one surface, not a stack, and cannot hold (`LIMITS`, written into the file's
`comment` metadata too): a diffuse roughness (Oren-Nayar or EON sigma: the colour is scaled by
`mapping.as_lambert` instead), more than one ior (its `ior` is shared by the base and the
clearcoat), a coloured clearcoat, per-layer lobes, bump or normal noise. So the stack is baked:

- `diffuseColor`: sum_k w_k c_k (each layer's colour times its Lambert factor, weighted by its
  share w_k = m_k prod_{j>k} (1 - m_j)); a constant when nothing varies;
- where the glaze covers the surface whole (one glaze, or no glaze: `ior` 1, no reflection), the
  metallic workflow: `metallic` 0 and the glaze's `ior`, so the reflection follows the Fresnel
  curve (Blender imports it as a Principled BSDF of that IOR: the brightest 1 % at 0.99 and
  0.88 of layerfit's own in two views, against 0.90 and 0.76 for the same glaze as a
  `specularColor`, which Blender reads as a Specular Tint; docs/exports.md);
- where its share varies (a stack), the specular workflow: `specularColor` = sum over glaze
  layers of w_k F0(ior_k), F0 = ((ior - 1) / (ior + 1))^2: the glaze's reflection where the
  glaze is, none elsewhere (the one input that can vary it over the surface);
- `roughness`: the GGX r of the glaze's Beckmann alpha (`mapping.ggx_roughness`; the preview
  surface squares it as OpenPBR does); `ior`: the glaze's; `clearcoat` 0.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..material import Material
from .bake import Plan, Progress, plan, write_exr
from .mapping import as_lambert, ggx_roughness

#: The file each export writes in its folder.
FILE = "material.usda"
#: What a UsdPreviewSurface cannot hold of a layerfit material.
LIMITS = (
    "UsdPreviewSurface cannot hold: a diffuse roughness (Oren-Nayar sigma; colours are scaled "
    "to the best Lambertian instead), more than one ior (one ior for base and clearcoat), a "
    "coloured clearcoat (white only; the glaze is the base's reflection instead: metallic 0 and"
    " its ior where it covers the surface, else specularColor = its share times F0(ior)), "
    "layers (their shares are baked into the maps), the bump from the masks and the glaze's "
    "normal noise."
)


def _f0(ior: float) -> float:
    return ((ior - 1.0) / (ior + 1.0)) ** 2


def maps(baked: Plan) -> dict[str, np.ndarray | float | tuple]:
    """The preview surface's inputs: constants or (size, size, C) images."""
    shares = baked.shares() if len(baked.layers) > 1 else [None]
    glazes = [
        (w, layer) for w, layer in zip(shares, baked.layers, strict=True) if layer.kind == "glaze"
    ]
    varies = len(baked.layers) > 1 or any(layer.colour_map is not None for layer in baked.layers)
    out: dict = {}
    if varies:
        diffuse = sum(
            (1.0 if w is None else w[..., None])
            * as_lambert(baked.colour_image(layer), layer.sigma, layer.diffuse)
            for w, layer in zip(shares, baked.layers, strict=True)
        )
        out["diffuseColor"] = np.asarray(diffuse, np.float32)
    else:
        (layer,) = baked.layers
        colour = as_lambert(layer.colour, layer.sigma, layer.diffuse)
        out["diffuseColor"] = tuple(float(c) for c in colour)
    if len(baked.layers) > 1 and glazes:  # the glaze's share varies: the specular workflow
        spec = sum(w * _f0(layer.ior) for w, layer in glazes)
        out["specularColor"] = np.repeat(np.asarray(spec, np.float32)[..., None], 3, -1)
        out["useSpecularWorkflow"] = 1
    else:  # the glaze everywhere, or nowhere (ior 1: no reflection)
        out["useSpecularWorkflow"], out["metallic"] = 0, 0.0
    out["roughness"] = ggx_roughness(glazes[-1][1].roughness) if glazes else 1.0
    out["ior"] = glazes[-1][1].ior if glazes else (1.5 if len(baked.layers) > 1 else 1.0)
    return out


def export(material: Material, folder: Path, size: int, progress: Progress | None = None) -> Path:
    """Write `material.usda` and its baked maps into `folder`."""
    from pxr import Sdf, Usd, UsdShade

    baked = plan(material, size, progress)
    inputs = maps(baked)
    path = folder / FILE
    stage = Usd.Stage.CreateNew(str(path))
    stage.SetMetadata("comment", LIMITS)
    material_prim = UsdShade.Material.Define(stage, "/Material")
    stage.SetDefaultPrim(material_prim.GetPrim())
    shader = UsdShade.Shader.Define(stage, "/Material/PreviewSurface")
    shader.CreateIdAttr("UsdPreviewSurface")
    workflow = inputs["useSpecularWorkflow"]
    shader.CreateInput("useSpecularWorkflow", Sdf.ValueTypeNames.Int).Set(workflow)
    if "metallic" in inputs:
        shader.CreateInput("metallic", Sdf.ValueTypeNames.Float).Set(inputs["metallic"])
    shader.CreateInput("clearcoat", Sdf.ValueTypeNames.Float).Set(0.0)
    shader.CreateInput("opacity", Sdf.ValueTypeNames.Float).Set(1.0)
    shader.CreateInput("roughness", Sdf.ValueTypeNames.Float).Set(float(inputs["roughness"]))
    shader.CreateInput("ior", Sdf.ValueTypeNames.Float).Set(float(inputs["ior"]))
    reader = None
    for name in ("diffuseColor", "specularColor")[: 1 + workflow]:
        value = inputs[name]
        target = shader.CreateInput(name, Sdf.ValueTypeNames.Color3f)
        if isinstance(value, tuple):
            target.Set(tuple(float(v) for v in value))
            continue
        if reader is None:
            reader = UsdShade.Shader.Define(stage, "/Material/TexCoord")
            reader.CreateIdAttr("UsdPrimvarReader_float2")
            reader.CreateInput("varname", Sdf.ValueTypeNames.String).Set("st")
            reader.CreateOutput("result", Sdf.ValueTypeNames.Float2)
        texture = UsdShade.Shader.Define(stage, f"/Material/{name}Texture")
        texture.CreateIdAttr("UsdUVTexture")
        file = write_exr(folder / f"{name}.exr", value)
        texture.CreateInput("file", Sdf.ValueTypeNames.Asset).Set(Sdf.AssetPath(file))
        texture.CreateInput("sourceColorSpace", Sdf.ValueTypeNames.Token).Set("raw")
        texture.CreateInput("wrapS", Sdf.ValueTypeNames.Token).Set("repeat")
        texture.CreateInput("wrapT", Sdf.ValueTypeNames.Token).Set("repeat")
        texture.CreateInput("st", Sdf.ValueTypeNames.Float2).ConnectToSource(
            reader.ConnectableAPI(), "result"
        )
        target.ConnectToSource(texture.CreateOutput("rgb", Sdf.ValueTypeNames.Float3))
    material_prim.CreateSurfaceOutput().ConnectToSource(shader.ConnectableAPI(), "surface")
    stage.GetRootLayer().Save()
    return path
