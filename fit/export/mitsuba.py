"""Mitsuba 3 XML, written by Mitsuba's own writer (`mitsuba.parser`).

- Native (default): the material's dict as it is rendered, layerfit's plugins (`layered`,
  `glaze`, `oren_nayar`, `fbm`) included, textures copied beside the XML. It loads with
  `mi.load_file` once `materials.register()` has run, and renders as the native material.
- Portable: Mitsuba's built-in plugins only. A glaze becomes `roughplastic`: Mitsuba's own
  diffuse base under a rough dielectric coat, with the glaze's Beckmann alpha and ior as they
  are, its pigment as `diffuse_reflectance` times `coat_diffuse_scale`; an Oren-Nayar layer a
  `diffuse` (its colour scaled by `mapping.as_lambert`); layers nest in `blendbsdf`s weighted
  by the masks baked to bitmaps, the bump is a `bumpmap` of the baked height field, and the
  pigment noise a baked bitmap. The glaze's normal noise and its diffuse sigma are lost.

`roughplastic` rather than `principled`: `principled`'s Disney diffuse is not under its
specular lobe (`(1 - F_i / 2)(1 - F_o / 2)` with F Schlick's weight (1 - cos)^5, plus a
retro-reflection): seen head-on, at 60 and at 75 degrees its directional albedo is 1.03, 1.08
and 1.17 x its base colour, where the glaze's pigment, weighed by 1 - F(n.v), keeps 0.96, 0.93
and 0.74 (ior 1.52). On the peer sphere the `principled` export was 5.8-7.1 % brighter than the
native render, and no factor on its base colour fits both the views head-on and the grazing
ones (scaled to the glaze's white-sky albedo it was 6.8-7.7 % darker). `roughplastic` weighs its
base by the coat's transmittance t(mu) = 1 - (rough reflectance) on the way in and out, and
divides it by eta^2 (1 - its internal reflectance): 0.93, 0.88 and 0.72 at the same angles once
scaled; its specular lobe is the glaze's Beckmann distribution (Smith shadowing, exact Fresnel
at v.h where `paper` takes F(n.v): with an exact-Fresnel glaze the specular parts' renders
agree within 1.3 %, with Schlick's the plugin's is 4-9 % brighter).

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
from .mapping import as_lambert, glaze_diffuse_albedo

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
    # a glaze's pigment times its coat factor, clipped at 1: Mitsuba refuses an RGB reflectance
    # above 1 (a pigment above about 0.97 at ior 1.5, `paper`, loses the rest)
    glaze = layer.kind == "glaze"
    scale, top = (coat_diffuse_scale(layer), 1.0) if glaze else (1.0, np.inf)
    if layer.colour_map is not None:
        image = np.minimum(as_lambert(layer.colour_map, layer.sigma, layer.diffuse) * scale, top)
        name = write_exr(folder / f"{layer.name}.colour.exr", image)
        colour: dict = {"type": "bitmap", "filename": name, "raw": True}
    else:
        value = np.minimum(as_lambert(layer.colour, layer.sigma, layer.diffuse) * scale, top)
        colour = {"type": "rgb", "value": [float(c) for c in value]}
    if glaze:
        return {
            "type": "roughplastic",
            "distribution": "beckmann",
            "alpha": float(layer.roughness),
            "int_ior": float(layer.ior),
            "ext_ior": 1.0,
            "diffuse_reflectance": colour,
        }
    return {"type": "diffuse", "reflectance": colour}


def coat_diffuse_scale(layer: Layer) -> float:
    """The factor on a glaze's (Lambertian) pigment as `roughplastic`'s `diffuse_reflectance`
    that gives the plugin's diffuse part the glaze's white-sky albedo
    (`mapping.glaze_diffuse_albedo`, by its coupling and Fresnel); about 1.03 for `paper` at
    ior 1.5 (there roughplastic's base is seen through the coat twice, the glaze's once),
    0.94 for `reciprocal` (both twice)."""
    options = layer.options
    target = glaze_diffuse_albedo(
        float(layer.ior), options.get("fresnel", "schlick"), options.get("coupling", "paper")
    )
    return target / roughplastic_diffuse_albedo(float(layer.roughness), float(layer.ior))


def roughplastic_diffuse_albedo(alpha: float, ior: float) -> float:
    """The white-sky albedo of `roughplastic`'s diffuse part at `diffuse_reflectance` 1 (Beckmann
    `alpha`, `int_ior` = `ior`), evaluated on the plugin itself: its transmittance table and
    internal reflectance are its own."""
    bsdf = {
        "type": "roughplastic",
        "distribution": "beckmann",
        "alpha": alpha,
        "int_ior": ior,
        "ext_ior": 1.0,
        "diffuse_reflectance": {"type": "rgb", "value": [1.0, 1.0, 1.0]},
    }
    return white_sky_albedo(bsdf, component=1)  # 0: the specular lobe


def white_sky_albedo(bsdf: dict, component: int) -> float:
    """The white-sky (hemispherical) albedo of one lobe without azimuthal dependence (a
    Lambertian weighed by functions of the two cosines), mean over RGB:
    `A = 4 pi int int f(mu_i, mu_o) mu_i mu_o dmu_i dmu_o` (Gauss-Legendre, 24 x 24)."""
    import drjit as dr
    import mitsuba as mi

    plugin = mi.load_dict(bsdf)
    nodes, weights = np.polynomial.legendre.leggauss(24)
    mu, w = 0.5 * (nodes + 1.0), 0.5 * weights
    mu_i, mu_o = (a.ravel() for a in np.meshgrid(mu, mu, indexing="ij"))
    ctx = mi.BSDFContext()
    ctx.component = component

    def lobe(ci, co):
        """f (eval returns f cos) for views at cos ci, lights at cos co, opposite azimuths."""
        si = dr.zeros(mi.SurfaceInteraction3f, np.size(ci))
        si.sh_frame = mi.Frame3f(mi.Vector3f(0.0, 0.0, 1.0))
        si.wi = mi.Vector3f(np.sqrt(1.0 - ci * ci), 0.0 * ci, ci)
        wo = mi.Vector3f(-np.sqrt(1.0 - co * co), 0.0 * co, co)
        return np.ravel(np.mean(np.asarray(plugin.eval(ctx, si, wo)), axis=0)) / co

    if dr.is_jit_v(mi.Float):  # one vectorised call
        values = lobe(mu_i.astype(np.float32), mu_o.astype(np.float32))
    else:  # scalar variants: a call per pair
        values = [lobe(float(ci), float(co))[0] for ci, co in zip(mu_i, mu_o, strict=True)]
    f = np.reshape(values, (mu.size, mu.size))
    return float(4.0 * np.pi * np.einsum("i,j,i,j,ij->", w, w, mu, mu, f))


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
