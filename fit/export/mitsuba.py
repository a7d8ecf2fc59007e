"""Mitsuba 3 XML, written by Mitsuba's own writer (`mitsuba.parser`).

- Native (default): the material's dict as it is rendered, layerfit's plugins (`layered`,
  `glaze`, `oren_nayar`, `fbm`) included, textures copied beside the XML. It loads with
  `mi.load_file` once `materials.register()` has run, and renders as the native material.
- Portable: Mitsuba's built-in plugins only. A glaze becomes `principled` (base colour the
  pigment, GGX roughness from `mapping.ggx_roughness`, eta the ior), an Oren-Nayar layer a
  `diffuse` (its colour scaled by `mapping.as_lambert`); layers nest in `blendbsdf`s weighted
  by the masks baked to bitmaps, the bump is a `bumpmap` of the baked height field, and the
  pigment noise a baked bitmap. The glaze's normal noise and its diffuse sigma are lost.

The XML's root is the BSDF (`<bsdf type=...>`): `mi.load_file` returns it; a scene can
`<include filename="material.xml"/>` it after giving it an id.
"""

from __future__ import annotations

import copy
import shutil
from pathlib import Path

import numpy as np

from materials.params import FBM, LAYER_PLUGINS, LAYERED

from ..material import Material
from .bake import Layer, Plan, Progress, plan, write_exr
from .mapping import as_lambert, ggx_roughness

#: The file each export writes in its folder.
FILE = "material.xml"
_BSDFS = {*LAYER_PLUGINS, LAYERED.name}
_TEXTURES = {FBM.name}


def export_native(material: Material, folder: Path) -> Path:
    """Write the material as it renders (layerfit's plugins), textures copied beside it."""
    names = {path: f"{key}{path.suffix.lower()}" for key, path in material.texture_files().items()}
    for source, name in names.items():
        shutil.copyfile(source, folder / name)
    bsdf = _rename_files(copy.deepcopy(material.bsdf), {str(p): n for p, n in names.items()})
    return _write(bsdf, folder / FILE)


def export_portable(
    material: Material, folder: Path, size: int, progress: Progress | None = None
) -> Path:
    """Write the material with Mitsuba's built-in plugins only (textures baked beside it)."""
    baked = plan(material, size, progress)
    return _write(portable_dict(baked, folder), folder / FILE)


def portable_dict(baked: Plan, folder: Path) -> dict:
    """The built-in BSDF dict of a baked material; its images written into `folder`."""
    bsdf = _layer(baked.layers[0], folder)
    for k, layer in enumerate(baked.layers[1:], start=1):
        mask = write_exr(folder / f"{layer.name}.mask.exr", layer.mask)
        bsdf = {
            "type": "blendbsdf",
            "weight": {"type": "bitmap", "filename": mask, "raw": True},
            f"bsdf_{k - 1}_below": bsdf,
            f"bsdf_{k}_{layer.name}": _layer(layer, folder),
        }
    if baked.bump > 0:
        height = write_exr(folder / "height.exr", baked.height())
        bsdf = {
            "type": "bumpmap",
            "height": {"type": "bitmap", "filename": height, "raw": True},
            "scale": baked.bump,
            "bsdf": bsdf,
        }
    return bsdf


def _layer(layer: Layer, folder: Path) -> dict:
    if layer.colour_map is not None:
        image = as_lambert(layer.colour_map, layer.sigma, layer.diffuse)
        name = write_exr(folder / f"{layer.name}.colour.exr", image)
        colour: dict = {"type": "bitmap", "filename": name, "raw": True}
    else:
        value = as_lambert(layer.colour, layer.sigma, layer.diffuse)
        colour = {"type": "rgb", "value": [float(c) for c in value]}
    if layer.kind == "glaze":
        return {
            "type": "principled",
            "base_color": colour,
            "roughness": ggx_roughness(layer.roughness),
            "eta": layer.ior,
            "metallic": 0.0,
            "spec_tint": 0.0,
        }
    return {"type": "diffuse", "reflectance": colour}


def _rename_files(value, names: dict[str, str]):
    """`value` with every bitmap's absolute file name replaced by its name in the export."""
    if isinstance(value, dict):
        out = {k: _rename_files(v, names) for k, v in value.items()}
        if out.get("type") == "bitmap" and out.get("filename") in names:
            out["filename"] = names[out["filename"]]
        return out
    return value


def _write(bsdf: dict, path: Path) -> Path:
    """Write a BSDF dict as Mitsuba XML through `mitsuba.parser` (telling the writer which of
    our plugins are BSDFs and textures: it only knows the built-ins' object types)."""
    import mitsuba as mi
    from mitsuba import parser

    state = parser.parse_dict(parser.ParserConfig(mi.variant()), bsdf)
    for node in state.nodes:
        if node.type == mi.ObjectType.Unknown:
            name = node.props.plugin_name()
            if name in _BSDFS:
                node.type = mi.ObjectType.BSDF
            elif name in _TEXTURES:
                node.type = mi.ObjectType.Texture
    parser.write_file(state, str(path))
    return path


def image_difference(a: np.ndarray, b: np.ndarray) -> float:
    """Relative RMSE of `b` against `a` over pixels where `a` is not black."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    return float(np.sqrt(np.mean((a - b) ** 2)) / np.sqrt(np.mean(a**2)))
