"""Free parameters: which parameters of a built material (or emitter scales) a fit moves, their
starting values, and the unconstrained vector solvers see (each value through its declaration's
transform). Everything is read from the material's parameter table."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from materials.params import EMITTER_PARAMS, ParamSpec

from .build import Material
from .keys import parse_key


@dataclass(frozen=True)
class Free:
    """One free parameter: its design key (`glaze.roughness`), its key in `mi.traverse` of the
    material (None for emitter scales, which multiply every matching emitter's configured
    radiance: see `Renderer`), declaration, texel shape for a texture, and starting value."""

    key: str
    traverse: str | None
    spec: ParamSpec
    shape: tuple[int, ...] = ()  # a texture's texels (height, width, channels)
    start: float | list[float] | None = None

    @property
    def emitter(self) -> str | None:
        """`lights` or `environment` for an emitter scale, else None."""
        return self.key.split(".")[0] if self.traverse is None else None

    @property
    def size(self) -> int:
        if self.shape:
            return int(np.prod(self.shape))
        return 3 if self.spec.kind == "rgb" else 1


def resolve(material: Material, keys: list[str]) -> list[Free]:
    """The free parameters named by `keys` in a built `material`: its parameters (`glaze.ior`,
    `lime.mask.threshold`, `bump`, `glaze.mask.texture` texel by texel) and the scene's emitter
    scales (`lights.scale`, `environment.scale`). A `KeyError` names what is wrong."""
    out = []
    for text in keys:
        key = parse_key(text)
        if key.emitter:
            if key.mask or key.name != "scale":
                raise KeyError(f"{text}: emitters have one free parameter, {key.owner}.scale")
            out.append(Free(text, None, EMITTER_PARAMS[key.owner], start=1.0))
            continue
        param = material.params.get(text)
        if param is None:
            raise KeyError(f"{text}: {_why_not(material, text)}")
        if param.value is not None:
            out.append(Free(text, param.traverse, param.spec, start=param.value))
        elif param.spec.kind == "texture":  # a mask's texels as painted
            texels = texture_data({"type": "bitmap", "filename": str(param.texture), "raw": True})
            start = texels.ravel().tolist()
            out.append(Free(text, param.traverse, param.spec, texels.shape, start))
        else:
            raise KeyError(f"{text}: is a texture file ({param.texture.name}); give a value to fit")
    return out


def _why_not(material: Material, text: str) -> str:
    """Why `text` is not a parameter of `material`, with the keys that are."""
    if text.split(".")[0] in ("gain", "gains"):
        return (
            "per-view gains are not material parameters; set fit.gains = true (RGB) or "
            '"exposure" (one grey gain per view) instead'
        )
    key = parse_key(text)
    if text == "bump":
        if len(material.layers) < 2:
            return "the bump comes from the masks of a stack of two or more layers; drop the key"
        return "bump is 0 in [material], so it is not built; give it a start > 0 (e.g. 0.0002)"
    owners = {name for name, _ in material.layers} | ({""} if "bump" in material.params else set())
    if key.owner not in owners:
        layers = ", ".join(name for name, _ in material.layers)
        return (
            f"no layer {key.owner!r} is built (built: {layers}); enable the layer or drop the key"
        )
    if key.mask and key.name == "texture":
        return f"the {key.owner} mask has no texture to fit; give it one or drop the key"
    known = ", ".join(k for k in material.params if parse_key(k).owner == key.owner)
    return f"not a built parameter; choose from {known}"


def start_values(free: list[Free]) -> dict:
    """Each free parameter's starting value, by key."""
    return {f.key: f.start for f in free}


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
