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
        else:  # a mask's texels as painted, or a colour given as a texture file
            raw = param.spec.kind == "texture"  # 8-bit colours are sRGB-decoded, masks linear
            bitmap = {"type": "bitmap", "filename": str(param.texture), "raw": raw}
            texels = texture_data(bitmap)
            channels = 1 if param.spec.kind == "texture" else 3
            if texels.shape[-1] != channels:
                raise KeyError(
                    f"{text}: its texture {param.texture.name} has {texels.shape[-1]} channels, "
                    f"{channels} wanted; save it with {channels}"
                )
            start = texels.ravel().tolist()
            out.append(Free(text, param.traverse, param.spec, texels.shape, start))
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
    layer_names = [name for name, _ in material.layers]
    if text in layer_names:  # a layer named alone
        keys = ", ".join(k for k in material.params if parse_key(k).owner == text)
        return f"{text!r} is a layer; name its parameters: {keys}"
    owners = set(layer_names) | ({""} if "bump" in material.params else set())
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
    """A bitmap texture's texels as Mitsuba holds them (height, width, channels). Read with
    the scalar variant where none is set yet: a fit config is loaded (a free texture's start
    resampled from its file) before the command chooses its variant."""
    import mitsuba as mi

    if mi.variant() is None:
        mi.set_variant("scalar_rgb")
    return np.asarray(mi.traverse(mi.load_dict(texture))["data"], dtype=np.float32)


def to_unconstrained(free: list[Free], values: dict, xp=np):
    """The solver's vector from physical values keyed by design key."""
    parts = [
        xp.ravel(xp.asarray(f.spec.to_unconstrained(np.asarray(values[f.key], float), xp)))
        for f in free
    ]
    return xp.concatenate(parts)


def to_physical(free: list[Free], u, xp=np):
    """Physical values (one flat vector) from the solver's unconstrained vector (under JAX a
    `clipped_sigmoid`'s derivative passes straight through its clip)."""
    stop_gradient = None
    if xp is not np:
        import jax

        stop_gradient = jax.lax.stop_gradient
    parts, i = [], 0
    for f in free:
        parts.append(xp.ravel(f.spec.from_unconstrained(u[i : i + f.size], xp, stop_gradient)))
        i += f.size
    return xp.concatenate(parts)


def as_dict(free: list[Free], flat) -> dict:
    out, i = {}, 0
    for f in free:
        chunk = np.asarray(flat[i : i + f.size], dtype=float)
        out[f.key] = chunk.tolist() if f.size > 1 else float(chunk[0])
        i += f.size
    return out


#: A fitted value within this share of its range of a bound (in its transform's space: log space
#: for scale factors) ended at the bound.
AT_BOUND = 2e-3


def at_bounds(free: list[Free], values: dict) -> list[dict]:
    """The fitted values that ended at a bound of their declared range, one entry per component
    (`glaze.pigment[2]`): its label, which bound, the value and the range. Textures are left out
    (a mask's texels at 0 and 1 are what a mask is). A value there is the truth sitting on the
    bound, or one the photographs ask past it, or a fit stopped in a local minimum: from ior at
    1.011 of [1.01, 3] (the truth 1.52) the pigment was 29 sd off; four starts found 1.23 and
    every value within 1.6 sd."""
    out = []
    for f in free:
        spec = f.spec
        if f.shape or spec.transform == "identity":
            continue
        x = np.atleast_1d(np.asarray(values[f.key], float))
        lo, hi = np.broadcast_to(spec.lower, x.shape), np.broadcast_to(spec.upper, x.shape)
        # the share of the range (its transform's own: log space for scales), clipped by
        # `to_unconstrained` at BOUND_MARGIN, which is inside AT_BOUND
        t = 1.0 / (1.0 + np.exp(-spec.to_unconstrained(x)))
        for i, share in enumerate(t):
            if AT_BOUND < share < 1 - AT_BOUND:
                continue
            label = f.key if x.size == 1 else f"{f.key}[{i}]"
            bound = "lower" if share <= AT_BOUND else "upper"
            out.append(
                {
                    "parameter": label,
                    "bound": bound,
                    "value": float(x[i]),
                    "range": [float(lo[i]), float(hi[i])],
                }
            )
    return out


def bound_note(entry: dict, starts: int = 1) -> str:
    """One line on an `at_bounds` entry, with what tells its causes apart."""
    low, high = entry["range"]
    more = "more starts" if starts > 1 else "4 starts (`--starts 4`)"
    return (
        f"{entry['parameter']} ended at its {entry['bound']} bound ({entry['value']:.4g}; range "
        f"{low:g} to {high:g}): the truth may sit there, or the photographs ask for a value past "
        "it, or the fit stopped in a local minimum, where the other values can be off by more "
        f"than their sd; a fit from {more} tells these apart"
    )
