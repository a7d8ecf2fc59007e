"""Helpers shared by the Python plugins: read declared parameters from Mitsuba properties."""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from .params import Option, ParamSpec, PluginDecl


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


def read_params(props: mi.Properties, decl: PluginDecl, *keys: str) -> list:
    """`decl`'s parameters `keys`, in order: an RGB one as a texture (`read_texture`), a scalar
    as an opaque `mi.Float` (`read_float`)."""
    specs = [decl.params[k] for k in keys]
    return [(read_texture if s.kind == "rgb" else read_float)(props, s, decl.name) for s in specs]


def read_option(props: mi.Properties, option: Option, plugin: str):
    """A declared option (an integer or a choice), checked; its default when absent."""
    return option.check(props.get(option.key, option.default), f"{plugin} plugin")
