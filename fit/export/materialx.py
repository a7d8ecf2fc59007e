"""MaterialX: one `open_pbr_surface` per layer, stacked by `mix` nodes driven by the masks.

Per layer (values from `mapping`):

- colour (pigment, clay/lime/stain reflectance) -> `base_color`, times the EON colour factor of
  its sigma; a varying colour (texture, pigment noise) is a baked `image` beside the document;
- Oren-Nayar sigma (radians) -> `base_diffuse_roughness` (OpenPBR's EON, [0, 1]) through
  `mapping.eon_roughness`; a layer with `diffuse = "eon"` is EON already: its sigma and colour
  go over as they are;
- the glaze -> the specular layer: `specular_ior` = ior, `specular_roughness` = the GGX r whose
  lobe is nearest its Beckmann alpha (alpha_GGX = r^2); an Oren-Nayar layer has
  `specular_weight` 0 (and `specular_roughness` `NO_SPECULAR_ROUGHNESS`). The glaze is a
  dielectric directly over its pigment, which is OpenPBR's dielectric base (specular over
  diffuse). The coat slot would darken the base by its internal reflections,
  `(1 - K) / (1 - E_base K)` with K = 1 - (1 - F0) / ior^2 (`coat_darkening`): at ior 1.5 the
  cup's pigment (0.06, 0.2, 0.42) would keep 0.44, 0.48, 0.56 of its value where the glaze keeps
  0.96 (1 - F at normal incidence); with the darkening off and the specular off, a coat is the
  same GGX dielectric lobe. So the specular slot matches better;
- layers bottom to top: `mix(fg = layer k, bg = the stack below, mix = mask k)`, each mask an
  `image` node reading the baked texture x fbm (linear EXR), which gives every layer its share
  `w_k = m_k prod_{j>k} (1 - m_j)`, as the native stack.

Lost: the bump from the masks, the glaze's normal noise, its Fresnel coupling (`paper` weighs
the whole specular lobe by F(n.v), OpenPBR by F(v.h)) and Schlick's approximation.
"""

from __future__ import annotations

import functools
from pathlib import Path

from ..errors import ConfigError
from ..material import Material
from .bake import Layer, Progress, plan, write_exr
from .mapping import as_eon, ggx_roughness

#: The file each export writes in its folder.
FILE = "material.mtlx"
#: `specular_roughness` of a layer without a specular lobe (`specular_weight` 0, so ior 1: no
#: interface). Exact renderers ignore it; MaterialX's GLSL darkens the base under its dielectric
#: by the lobe's directional albedo with F90 = 1 whatever the ior, which at the default 0.3 took
#: 2.6 % off a Lambertian sphere's mean (11 % and more near its silhouette) and at 1 takes 0.2 %
#: (docs/exports.md).
NO_SPECULAR_ROUGHNESS = 1.0


def standard_libraries():
    """MaterialX's standard data libraries (shipped with the `materialx` package)."""
    import MaterialX as mx

    lib = mx.createDocument()
    mx.loadLibraries(mx.getDefaultDataLibraryFolders(), mx.getDefaultDataSearchPath(), lib)
    return lib


@functools.cache
def _library_names() -> frozenset[str]:
    """The names of the standard libraries' elements (type and node definitions...)."""
    return frozenset(child.getName() for child in standard_libraries().getChildren())


def child_name(doc, wanted: str) -> str:
    """A layer's node name, free in `doc` and in the standard libraries it validates against: a
    layer named `material`, `float`, `color3` or `BSDF` took the name of a library element, and
    the document failed validation ("Invalid port connection")."""
    name = wanted
    while name in _library_names():
        name += "_"
    return doc.createValidChildName(name)


def check_document(doc) -> None:
    """Raise unless `doc` validates against the standard libraries with every node's
    definition resolved (validation skips the inputs of nodes it cannot resolve)."""
    doc.setDataLibrary(standard_libraries())
    valid, message = doc.validate()
    unresolved = [node.getName() for node in doc.getNodes() if node.getNodeDef() is None]
    if not valid or unresolved:
        problem = message.strip().replace("\n", "; ") or f"no definition for {unresolved}"
        raise ConfigError(f"MaterialX document: {problem}")


def export(material: Material, folder: Path, size: int, progress: Progress | None = None) -> Path:
    """Write `material.mtlx` and its baked images into `folder`."""
    import MaterialX as mx

    baked = plan(material, size, progress)
    doc = mx.createDocument()
    doc.setDocString("layerfit export: " + __doc__.splitlines()[0])
    shader = None
    for layer in baked.layers:
        surface = _surface(doc, layer, folder)
        if shader is None:
            shader = surface
            continue
        mask = doc.addNode("image", child_name(doc, f"{layer.name}_mask"), "float")
        file = write_exr(folder / f"{layer.name}.mask.exr", layer.mask)
        mask.setInputValue("file", file, "filename")
        mix = doc.addNode("mix", child_name(doc, f"{layer.name}_over"), "surfaceshader")
        mix.addInput("fg", "surfaceshader").setConnectedNode(surface)
        mix.addInput("bg", "surfaceshader").setConnectedNode(shader)
        mix.addInput("mix", "float").setConnectedNode(mask)
        shader = mix
    node = doc.addMaterialNode(doc.createValidChildName("material"), shader)
    node.setDocString("layerfit material")
    check_document(doc)
    path = folder / FILE
    mx.writeToXmlFile(doc, str(path))
    return path


def _surface(doc, layer: Layer, folder: Path):
    """One layer's `open_pbr_surface`."""
    import MaterialX as mx

    diffuse_roughness, scale = as_eon(layer.sigma, layer.diffuse)
    node = doc.addNode("open_pbr_surface", child_name(doc, layer.name), "surfaceshader")
    if layer.colour_map is not None:
        name = write_exr(folder / f"{layer.name}.colour.exr", layer.colour_map * scale)
        image = doc.addNode("image", child_name(doc, f"{layer.name}_colour"), "color3")
        image.setInputValue("file", name, "filename").setColorSpace("lin_rec709")
        node.addInput("base_color", "color3").setConnectedNode(image)
    else:
        node.setInputValue("base_color", mx.Color3(*(float(c) * scale for c in layer.colour)))
    node.setInputValue("base_weight", 1.0)
    node.setInputValue("base_diffuse_roughness", diffuse_roughness)
    if layer.kind == "glaze":
        node.setInputValue("specular_weight", 1.0)
        node.setInputValue("specular_ior", float(layer.ior))
        node.setInputValue("specular_roughness", ggx_roughness(layer.roughness))
    else:
        node.setInputValue("specular_weight", 0.0)
        node.setInputValue("specular_roughness", NO_SPECULAR_ROUGHNESS)
    return node
