"""Free parameters: which declared parameters a fit moves, where they live in the Mitsuba scene,
and the unconstrained vector solvers see (each value through its declaration's transform)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from materials.params import (
    EMITTER_PARAMS,
    GLAZE_OPTIONAL_PARAMS,
    GLAZE_PARAMS,
    LAYERED_PARAMS,
    MASK_PARAMS,
    MASK_TEXTURE,
    OREN_NAYAR_PARAMS,
    ParamSpec,
)

from .scene import MATERIAL_PREFIX

_PLUGIN_SPECS = {
    "glaze": {**GLAZE_PARAMS, **GLAZE_OPTIONAL_PARAMS},
    "oren_nayar": OREN_NAYAR_PARAMS,
}


@dataclass(frozen=True)
class Free:
    """One free parameter: its design key (`glaze.roughness`), traverse key, declaration, size.
    Emitter scales (`lights.scale`, `environment.scale`) have no single traverse key: they
    multiply every matching emitter's configured radiance (see `Renderer`)."""

    key: str
    traverse_key: str | None
    spec: ParamSpec
    shape: tuple[int, ...] = ()  # a texture's texels (height, width, channels)

    @property
    def emitter(self) -> str | None:
        """`lights` or `environment` for an emitter scale, else None."""
        return self.key.split(".")[0] if self.traverse_key is None else None

    @property
    def size(self) -> int:
        if self.shape:
            return int(np.prod(self.shape))
        return 3 if self.spec.kind == "rgb" else 1


def resolve(material: dict, keys: list[str]) -> list[Free]:
    """The free parameters named by design keys in `material` (a Mitsuba BSDF dict).

    For a single plugin the key's first part is the plugin type (`glaze.ior`); for a stack it is the
    layer name (`glaze.ior`, `lime.mask.threshold`) or `bump`. `lights.scale` and
    `environment.scale` scale the scene's emitters.
    """
    out = []
    for key in keys:
        parts = key.split(".")
        if parts[0] in EMITTER_PARAMS:
            if parts[1:] != ["scale"]:
                raise KeyError(f"{key}: emitters have one free parameter, {parts[0]}.scale")
            out.append(Free(key, None, EMITTER_PARAMS[parts[0]]))
            continue
        if material["type"] == "layered":
            if parts == ["bump"] and "bump" in material:
                out.append(Free(key, MATERIAL_PREFIX + "bump", LAYERED_PARAMS["bump"]))
                continue
            layer = material.get(parts[0]) if parts[0] in material["layers"].split(",") else None
            if layer is None:
                raise KeyError(f"{key}: no layer {parts[0]!r} (or it is not built)")
            if parts[1:] == ["mask", "texture"]:
                texture = material.get(f"{parts[0]}_mask", {}).get("texture")
                if texture is None:
                    raise KeyError(f"{key}: the {parts[0]} mask has no texture to fit")
                shape = texture_data(texture).shape
                traverse_key = f"{MATERIAL_PREFIX}{key}.data"
                out.append(Free(key, traverse_key, MASK_TEXTURE, shape))
                continue
            if len(parts) == 3 and parts[1] == "mask" and parts[2] in MASK_PARAMS:
                out.append(Free(key, MATERIAL_PREFIX + key, MASK_PARAMS[parts[2]]))
                continue
            specs, local = _PLUGIN_SPECS.get(layer["type"], {}), parts[1:]
        else:
            if parts[0] != material["type"]:
                raise KeyError(f"{key}: the material is a {material['type']}, not {parts[0]}")
            specs, local = _PLUGIN_SPECS.get(material["type"], {}), parts[1:]
        if len(local) != 1 or local[0] not in specs:
            raise KeyError(f"{key}: not a declared parameter; known: {', '.join(specs)}")
        spec = specs[local[0]]
        tkey = key if material["type"] == "layered" else local[0]
        out.append(
            Free(key, MATERIAL_PREFIX + tkey + (".value" if spec.kind == "rgb" else ""), spec)
        )
    return out


def texture_data(texture: dict) -> np.ndarray:
    """A bitmap texture's texels as Mitsuba holds them (height, width, channels)."""
    import mitsuba as mi

    return np.asarray(mi.traverse(mi.load_dict(texture))["data"], dtype=np.float32)


def to_unconstrained(free: list[Free], values: dict, xp=np):
    """The solver's vector from physical values keyed by design key."""
    parts = [
        xp.ravel(xp.asarray(f.spec.to_unconstrained(np.asarray(values[f.key], float), xp)))
        for f in free
    ]
    return xp.concatenate(parts)


def to_physical(free: list[Free], u, xp=np):
    """Physical values (one flat vector) from the solver's unconstrained vector."""
    parts, i = [], 0
    for f in free:
        parts.append(xp.ravel(f.spec.from_unconstrained(u[i : i + f.size], xp)))
        i += f.size
    return xp.concatenate(parts)


def as_dict(free: list[Free], flat) -> dict:
    out, i = {}, 0
    for f in free:
        chunk = np.asarray(flat[i : i + f.size], dtype=float)
        out[f.key] = chunk.tolist() if f.size > 1 else float(chunk[0])
        i += f.size
    return out
