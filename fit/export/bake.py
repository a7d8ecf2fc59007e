"""What every export needs from a material: its layers as plain values, masks and varying colours
baked to images in UV space (Mitsuba's `bitmap` layout: row r at v = (r + 0.5) / size, which is
the usual image layout for a mesh's UVs as an OBJ file stores them, since Mitsuba flips v when it
loads one)."""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..material import Material

log = logging.getLogger(__name__)

#: `progress(done, total)` after each baked image.
Progress = Callable[[int, int], None]


@dataclass(frozen=True)
class Layer:
    """One layer of a material as plain values.

    - `kind`: `glaze` or `oren_nayar`; `colour`: the pigment or reflectance (linear RGB), or
      `colour_map` (size, size, 3) where it varies (a texture, the pigment noise).
    - `sigma`: Oren-Nayar sigma (radians; EON's roughness with the option `diffuse = "eon"`);
      `roughness`, `ior`: the glaze's Beckmann alpha and ior
      (None for `oren_nayar`); `options`: the plugin's options (`fresnel`, `coupling`, ...).
    - `mask`: (size, size) in [0, 1] (texture x fbm, baked), None for the bottom layer.
    """

    name: str
    kind: str
    colour: tuple[float, float, float] | None
    colour_map: np.ndarray | None
    sigma: float
    roughness: float | None
    ior: float | None
    options: dict
    mask: np.ndarray | None
    normal_noise: float = 0.0

    @property
    def diffuse(self) -> str:
        """The diffuse lobe (`qualitative` Oren-Nayar or `eon`), the `sigma`'s meaning."""
        return self.options.get("diffuse", "qualitative")


@dataclass(frozen=True)
class Plan:
    """A material's layers bottom to top with their baked images, and its bump (metres)."""

    layers: tuple[Layer, ...]
    bump: float
    size: int

    def shares(self) -> list[np.ndarray]:
        """Each layer's share `w_k = m_k prod_{j > k} (1 - m_j)` per texel (they sum to 1)."""
        ones = np.ones((self.size, self.size), np.float32)
        masks = [ones if layer.mask is None else layer.mask for layer in self.layers]
        shares, remaining = [ones] * len(masks), ones
        for k in reversed(range(len(masks))):
            shares[k] = masks[k] * remaining
            remaining = remaining * (1.0 - masks[k])
        return shares

    def height(self) -> np.ndarray:
        """The stack's height field `sum_{k > 0} m_k` (times `bump`: metres)."""
        return sum((layer.mask for layer in self.layers[1:]), np.zeros((self.size,) * 2))

    def colour_image(self, layer: Layer) -> np.ndarray:
        """A layer's colour as a (size, size, 3) image."""
        if layer.colour_map is not None:
            return layer.colour_map
        return np.broadcast_to(np.float32(layer.colour), (self.size, self.size, 3))


def _bake_rgb(plugin, size: int, glaze: bool) -> np.ndarray:
    """A loaded glaze's pigment (noise applied) or an RGB texture, as a (size, size, 3) image."""
    from ..render.bake import uv_bands

    out = np.empty((size, size, 3), np.float32)
    for first, si in uv_bands(size, size):
        values = plugin.eval_pigment(si) if glaze else plugin.eval(si)
        band = np.asarray(values, np.float32).T.reshape(-1, size, 3)  # Color3f: (3, N)
        out[first : first + len(band)] = band
    return out


def layer_dicts(material: Material) -> list[tuple[str, str, dict, dict | None]]:
    """(name, kind, plugin dict, mask dict or None) per layer, bottom to top."""
    if not material.stacked:
        ((name, kind),) = material.layers
        return [(name, kind, material.bsdf, None)]
    return [
        (name, kind, material.bsdf[name], material.bsdf.get(f"{name}_mask"))
        for name, kind in material.layers
    ]


def plan(material: Material, size: int, progress: Progress | None = None) -> Plan:
    """The material's layers with their masks and varying colours baked at size x size."""
    import mitsuba as mi

    from ..render import bake_texture

    entries = layer_dicts(material)
    varying = [_varies(bsdf, kind) for _, kind, bsdf, _ in entries]
    total = sum(mask is not None for *_, mask in entries) + sum(varying)
    done = 0

    def step():
        nonlocal done
        done += 1
        if progress is not None:
            progress(done, total)

    if progress is not None:
        progress(0, total)
    layers = []
    for (name, kind, bsdf, mask_dict), varies in zip(entries, varying, strict=True):
        colour_key = "pigment" if kind == "glaze" else "reflectance"
        colour, colour_map = None, None
        if varies:
            if kind == "glaze":
                colour_map = _bake_rgb(mi.load_dict(bsdf), size, glaze=True)
            else:
                colour_map = _bake_rgb(mi.load_dict(bsdf[colour_key]), size, glaze=False)
            step()
        else:
            colour = tuple(float(x) for x in bsdf[colour_key]["value"])
        mask = None
        if mask_dict is not None:
            mask = bake_texture(mask_dict, size, size)
            step()
        layers.append(
            Layer(
                name=name,
                kind=kind,
                colour=colour,
                colour_map=colour_map,
                sigma=float(bsdf.get("sigma", 0.0)),
                roughness=float(bsdf["roughness"]) if kind == "glaze" else None,
                ior=float(bsdf["ior"]) if kind == "glaze" else None,
                options={k: v for k, v in bsdf.items() if isinstance(v, str) and k != "type"},
                mask=mask,
                normal_noise=float(bsdf.get("normal_noise", 0.0)),
            )
        )
    bump = float(material.bsdf.get("bump", 0.0)) if material.stacked else 0.0
    return Plan(tuple(layers), bump, size)


def _varies(bsdf: dict, kind: str) -> bool:
    """Whether a layer's colour varies over the surface (a texture, or the pigment noise)."""
    colour = bsdf["pigment" if kind == "glaze" else "reflectance"]
    return colour["type"] != "rgb" or bsdf.get("pigment_noise", 0.0) != 0.0


def write_exr(path: Path, image: np.ndarray) -> str:
    """Write a linear image as float EXR (atomically); its file name."""
    from captures.images import write_image

    image = np.asarray(image, np.float32)
    write_image(path, image[..., None] if image.ndim == 2 else image)
    return path.name
