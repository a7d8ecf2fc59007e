"""Helpers shared by the Python plugins: read declared parameters from Mitsuba properties."""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from .params import ParamSpec


def read_float(props: mi.Properties, spec: ParamSpec, plugin: str) -> mi.Float:
    """A declared scalar as an opaque `mi.Float` (its value changes between renders)."""
    value = float(props.get(spec.key, float(spec.default)))
    spec.check(value, f"{plugin} plugin")
    return dr.opaque(mi.Float, value)


def read_texture(props: mi.Properties, spec: ParamSpec, plugin: str) -> mi.Texture:
    """A declared RGB texture; a constant value is checked against the bounds."""
    if spec.key in props:
        texture = props.get_texture(spec.key)
    else:
        texture = mi.load_dict({"type": "rgb", "value": list(spec.default)})
    params = mi.traverse(texture)
    if "value" in params:
        spec.check(dr.ravel(params["value"]).numpy(), f"{plugin} plugin")
    return texture


def read_choice(props: mi.Properties, key: str, choices: tuple[str, ...], plugin: str) -> str:
    """A string option that must be one of `choices` (the first is the default)."""
    value = props.get(key, choices[0])
    if value not in choices:
        raise ValueError(f"{plugin} plugin: {key} = {value!r}; choose one of {', '.join(choices)}")
    return value


def read_int(
    props: mi.Properties, key: str, default: int, lower: int, upper: int, plugin: str
) -> int:
    """A structural integer option (not differentiable), checked against `[lower, upper]`."""
    value = props.get(key, default)
    if int(value) != value or not lower <= value <= upper:
        raise ValueError(f"{plugin} plugin: {key} = {value}; use an integer in [{lower}, {upper}]")
    return int(value)
