"""A `[material]` table (TOML) -> a Mitsuba BSDF dict, building only what the table requires.

```toml
[material]
type = "layered"              # or a single plugin: "glaze", "oren_nayar"
bump = 0.0004                 # metres; 0 or absent: no bump is built

[[material.layers]]           # bottom to top
name = "clay"
type = "oren_nayar"
reflectance = [0.62, 0.5, 0.4]   # linear RGB, or a texture file (8-bit: sRGB-decoded)
sigma = 0.35

[[material.layers]]
name = "glaze"
type = "glaze"
enabled = true                # false: the layer, its mask and its parameters are not built
roughness = 0.02
[material.layers.mask]        # every layer but the bottom one: texture x sigmoid((fbm - t) / s)
scale = 8
threshold = 0.3
softness = 0.03
texture = "textures/glaze.png"   # optional painted mask (linear)
```
A disabled layer, a zero noise amount or a zero bump leaves no plugin, parameter or texture behind;
a stack left with one layer is that layer.
"""

from __future__ import annotations

from pathlib import Path

from captures.errors import CaptureError
from materials.params import (
    GLAZE_OPTIONAL_PARAMS,
    GLAZE_PARAMS,
    LAYERED_PARAMS,
    MASK_PARAMS,
    OREN_NAYAR_PARAMS,
)


class ConfigError(CaptureError):
    """A config file is wrong; the message names the file, the key and the fix."""


# plugin: (declared parameters, string options, integer options (lower, upper))
PLUGINS = {
    "glaze": (
        {**GLAZE_PARAMS, **GLAZE_OPTIONAL_PARAMS},
        {"coupling": ("paper", "reciprocal"), "fresnel": ("schlick", "exact")},
        {
            "pigment_noise_scale": (8, 1, 4096),
            "normal_noise_scale": (16, 1, 4096),
            "noise_seed": (0, 0, 2**31 - 1),
        },
    ),
    "oren_nayar": (OREN_NAYAR_PARAMS, {}, {}),
}
MASK_INTS = {"scale": (1, 4096), "octaves": (1, 12), "seed": (0, 2**31 - 1)}
#: Declared parameters whose zero value means "off": then they are not built.
OPTIONAL_ZERO = {*GLAZE_OPTIONAL_PARAMS, *LAYERED_PARAMS}


def _integer(value, bounds, where, file):
    lower, upper = bounds
    if isinstance(value, bool) or not isinstance(value, int) or not lower <= value <= upper:
        raise ConfigError(f"{file}: {where} = {value!r}; use an integer in [{lower}, {upper}]")
    return value


def _texture_file(value: str, file: Path, where: str, raw: bool) -> dict:
    path = (Path(file).parent / value).resolve()
    if not path.exists():
        raise ConfigError(f"{file}: {where} = {value!r} does not exist (relative to the config)")
    return {"type": "bitmap", "filename": str(path), "raw": raw}


def _check(spec, value, file, where):
    try:
        spec.check(value, f"{file}: {where.rsplit('.', 1)[0]}")
    except ValueError as err:
        raise ConfigError(str(err)) from None


def _value(spec, value, file, where):
    """A declared parameter's value as Mitsuba wants it (checked against its bounds)."""
    if spec.kind == "rgb":
        if isinstance(value, str):
            return _texture_file(value, file, where, raw=False)  # 8-bit files are sRGB-decoded
        if isinstance(value, int | float) and not isinstance(value, bool):
            value = [value] * 3
        if not isinstance(value, list) or len(value) != 3:
            raise ConfigError(f"{file}: {where} must be 3 numbers (linear RGB) or a texture file")
        _check(spec, value, file, where)
        return {"type": "rgb", "value": [float(x) for x in value]}
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ConfigError(f"{file}: {where} must be a number, got {value!r}")
    _check(spec, value, file, where)
    return float(value)


def _plugin(kind: str, table: dict, file, where) -> dict:
    specs, options, integers = PLUGINS[kind]
    out: dict = {"type": kind}
    for key, value in table.items():
        at = f"{where}.{key}"
        if key in options:
            if value not in options[key]:
                raise ConfigError(
                    f"{file}: {at} = {value!r}; choose one of {', '.join(options[key])}"
                )
            out[key] = value
        elif key in integers:
            out[key] = _integer(value, integers[key], at, file)
        elif key in specs:
            out[key] = _value(specs[key], value, file, at)
        else:
            known = ", ".join(sorted([*specs, *options, *integers, "enabled"]))
            raise ConfigError(f"{file}: unknown key {at} for {kind}; known: {known}")
    for key in OPTIONAL_ZERO & set(out):
        if out[key] == 0.0:
            del out[key]
    if not any(k in out for k in GLAZE_OPTIONAL_PARAMS):  # noise options without a noise
        for key in integers:
            out.pop(key, None)
    return out


def _mask(table, file, where) -> dict:
    if not isinstance(table, dict):
        raise ConfigError(f"{file}: [{where}] must be a table (scale, threshold, softness, ...)")
    out: dict = {"type": "fbm"}
    for key, value in table.items():
        at = f"{where}.{key}"
        if key in MASK_INTS:
            out[key] = _integer(value, MASK_INTS[key], at, file)
        elif key in MASK_PARAMS:
            out[key] = _value(MASK_PARAMS[key], value, file, at)
        elif key == "texture":
            if not isinstance(value, str):
                raise ConfigError(f"{file}: {at} must be a texture file name")
            out[key] = _texture_file(value, file, at, raw=True)  # a painted mask is linear
        else:
            known = ", ".join([*MASK_INTS, *MASK_PARAMS, "texture"])
            raise ConfigError(f"{file}: unknown key {at}; known: {known}")
    return out


def material_dict(table: dict, file: Path | str = "<material>", where: str = "material"):
    """The Mitsuba BSDF dict of a `[material]` table, or None when it is disabled."""
    if not isinstance(table, dict):
        raise ConfigError(f"{file}: [{where}] must be a table")
    table = dict(table)
    enabled = table.pop("enabled", True)
    if not isinstance(enabled, bool):
        raise ConfigError(f"{file}: {where}.enabled must be true or false")
    kind = table.pop("type", None)
    choices = [*PLUGINS, "layered"]
    if kind not in choices:
        raise ConfigError(f"{file}: {where}.type = {kind!r}; choose one of {', '.join(choices)}")
    if not enabled:
        return None
    if kind != "layered":
        return _plugin(kind, table, file, where)

    layers = table.pop("layers", None)
    bump = table.pop("bump", 0.0)
    if table:
        raise ConfigError(
            f"{file}: unknown key(s) {', '.join(table)} in [{where}]; known: type, bump, layers"
        )
    if not isinstance(layers, list) or not layers:
        raise ConfigError(f"{file}: [{where}] needs [[{where}.layers]] (bottom to top)")
    built: list[tuple[str, dict, dict | None]] = []
    for i, entry in enumerate(layers):
        at = f"{where}.layers[{i}]"
        if not isinstance(entry, dict) or not isinstance(entry.get("name"), str):
            raise ConfigError(f"{file}: [[{where}.layers]] number {i} needs a name")
        layer = dict(entry)
        name, mask = layer.pop("name"), layer.pop("mask", None)
        if not name.isidentifier():
            raise ConfigError(f"{file}: {at}.name = {name!r} must be an identifier")
        if name in [b[0] for b in built]:
            raise ConfigError(f"{file}: {at}.name = {name!r} is used twice")
        bsdf = material_dict(layer, file, f"{where}.{name}")
        if bsdf is None:
            continue
        if built and mask is None:
            raise ConfigError(f"{file}: layer {name!r} needs a [{where}.layers.mask] table")
        built.append((name, bsdf, _mask(mask, file, f"{where}.{name}.mask") if built else None))
    if not built:
        return None
    if len(built) == 1:
        return built[0][1]
    out: dict = {"type": "layered", "layers": ",".join(name for name, _, _ in built)}
    for name, bsdf, mask in built:
        out[name] = bsdf
        if mask is not None:
            out[f"{name}_mask"] = mask
    bump = _value(LAYERED_PARAMS["bump"], bump, file, f"{where}.bump")
    if bump > 0:
        out["bump"] = bump
    return out
