"""Materials as data: a `[material]` table -> the Mitsuba dict and its parameter table, the key
grammar, free parameters and the native preset. No Mitsuba import at module level."""

from .build import Material, Param, build_material, check_uvs, material_dict
from .free import (
    Free,
    as_dict,
    at_bounds,
    bound_note,
    resolve,
    start_values,
    to_physical,
    to_unconstrained,
)
from .keys import Key, key, parse_key
from .preset import (
    PRESET_SCHEMA,
    Preset,
    load_material,
    load_preset,
    provenance,
    read_toml,
    save_preset,
)

__all__ = [
    "PRESET_SCHEMA",
    "Free",
    "Key",
    "Material",
    "Param",
    "Preset",
    "as_dict",
    "at_bounds",
    "bound_note",
    "build_material",
    "check_uvs",
    "key",
    "load_material",
    "load_preset",
    "material_dict",
    "parse_key",
    "provenance",
    "read_toml",
    "resolve",
    "save_preset",
    "start_values",
    "to_physical",
    "to_unconstrained",
]
