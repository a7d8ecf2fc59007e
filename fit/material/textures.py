"""Parameters fitted as textures (a fit config's `[fit.textures]`): a colour (a glaze's pigment,
a layer's reflectance) or a layer mask's painted texture, free texel by texel at a stated
resolution, starting from the material's value: its constant, or its texture file resampled.

```toml
[fit]
free = ["glaze.pigment", "glaze.roughness", "glaze.ior"]
[fit.textures]
"glaze.pigment" = [110, 63]      # width, height in texels (the UV square)
```

A mask without a painted texture starts halfway, a texture of 0.5 (`MASK_START`): neither its
layer nor the one below favoured. From ones (the starting look unchanged: the mask is texture x
the fbm factor) the layer covered everything at first, its colour went to the object's average,
and the fit lost the layers apart (a stained torus: `mask_iou` 0.36 from ones, 0.86 from 0.5).
The start's texels are written once to a file named by their content in the system's temporary
folder (every process that loads the same config, a Ray worker's included, builds the same
file), never beside the user's files."""

from __future__ import annotations

import hashlib
import tempfile
from pathlib import Path

import numpy as np

from .build import Material, build_material
from .keys import parse_key

#: The most texels a free texture may have (a parameter each: the solvers' vectors and Adam's
#: moments are float32 arrays of this size per texture).
MAX_TEXELS = 1 << 20


def texture_keys(material: Material) -> list[str]:
    """The keys of `material` that can be fitted as textures: its colours and its masks'
    textures (present or not)."""
    colours = [k for k, p in material.params.items() if p.spec.kind in ("rgb", "texture")]
    masks = [f"{name}.mask.texture" for name, _ in material.layers[1:]] if material.stacked else []
    return colours + [k for k in masks if k not in colours]


#: The texels of a free mask texture without a painted one (see the module): measured from
#: ones and from 0.5 with the default schedule (EPYC-25, 2026-12-05, seed 0, `mask_iou`): a
#: stained sphere 0.905 and 0.938, a stained torus 0.36 and 0.86, the cup's stain 0.01 and 0.45
#: (BENCHMARKS, "Stained objects", "The main job").
MASK_START = 0.5


def start_texels(material: Material, key: str, size: tuple[int, int]) -> np.ndarray:
    """The starting texels (height, width, channels) of `key` as a texture of `size` (width,
    height): its constant, its texture file resampled (area-averaged or bilinear), or
    `MASK_START` for a mask without a texture. A `KeyError` says why `key` cannot be a texture."""
    width, height = size
    if key not in texture_keys(material):
        known = ", ".join(texture_keys(material)) or "none"
        raise KeyError(
            f"{key}: only colours and mask textures can be fitted as textures (here: {known})"
        )
    param = material.params.get(key)
    if param is None:  # a mask without a painted texture
        return np.full((height, width, 1), MASK_START, np.float32)
    if param.value is not None:
        value = np.asarray(param.value, np.float32).reshape(1, 1, -1)
        return np.broadcast_to(value, (height, width, value.shape[-1])).copy()
    from .free import texture_data

    raw = param.spec.kind == "texture"  # 8-bit colours are sRGB-decoded, masks linear
    texels = texture_data({"type": "bitmap", "filename": str(param.texture), "raw": raw})
    if texels.shape[:2] != (height, width):
        from skimage.transform import resize

        texels = resize(texels, (height, width), order=1, anti_aliasing=True, preserve_range=True)
    spec = param.spec
    return np.clip(texels, spec.lower, spec.upper).astype(np.float32)


def with_free_textures(material: Material, sizes: dict[str, tuple[int, int]]) -> Material:
    """`material` with each key of `sizes` a texture of that size (width, height) holding its
    start (`start_texels`), read from a file named by its content (see the module)."""
    if not sizes:
        return material
    table = material.table()
    for key, size in sizes.items():
        texels = start_texels(material, key, size)
        slot, name = _slot(table, material, key)
        slot[name] = str(cached_texture(texels, key))
    built = build_material(table, "<material with free textures>")
    assert built is not None
    return built


def _slot(table: dict, material: Material, text: str) -> tuple[dict, str]:
    """The table (a layer's, a mask's or the material's own) and name that hold key `text`."""
    k = parse_key(text)
    if not material.stacked and k.owner == table.get("type"):
        return table, k.name
    layer = next(t for t in table["layers"] if t["name"] == k.owner)
    return (layer.setdefault("mask", {}) if k.mask else layer), k.name


def cached_texture(texels: np.ndarray, key: str) -> Path:
    """A float EXR of `texels` in the temporary folder, named by their content and the key they
    are the texture of (written once; `write_image` is atomic, so processes writing it at once
    leave one whole file). Two keys never share a file: Mitsuba loads bitmaps of one file as one
    object, and a second mask starting from the same texels would have no texels of its own."""
    from captures.images import write_image

    digest = hashlib.sha1(texels.astype(np.float32).tobytes())
    digest.update(repr(texels.shape).encode())
    digest.update(key.encode())
    folder = Path(tempfile.gettempdir()) / "layerfit-textures"
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"{digest.hexdigest()[:20]}.exr"
    if not path.is_file():
        write_image(path, texels)
    return path
