"""Read render configs (TOML): `[scene]`, `[material]`, `[render]`. Errors name file and key."""

from __future__ import annotations

import tomllib
from dataclasses import dataclass
from pathlib import Path

from captures import CaptureError, Scene, parse_scene
from materials.params import GLAZE_PARAMS, OREN_NAYAR_PARAMS

#: Declared parameters and string options of each material plugin a config may name.
MATERIALS = {
    "glaze": (GLAZE_PARAMS, {"coupling": ("paper", "reciprocal"), "fresnel": ("schlick", "exact")}),
    "oren_nayar": (OREN_NAYAR_PARAMS, {}),
}


class ConfigError(CaptureError):
    """A config file is wrong; the message names the file, the key and the fix."""


@dataclass(frozen=True)
class RenderConfig:
    scene: Scene
    material: dict
    spp: int


def material_dict(table: dict, file: Path | str = "<material>") -> dict:
    """A Mitsuba BSDF dict from a `[material]` table, checked against the parameter declarations."""
    table = dict(table)
    kind = table.pop("type", None)
    if kind not in MATERIALS:
        raise ConfigError(f"{file}: material.type = {kind!r}; choose one of {', '.join(MATERIALS)}")
    specs, options = MATERIALS[kind]
    out: dict = {"type": kind}
    for key, value in table.items():
        if key in options:
            if value not in options[key]:
                raise ConfigError(
                    f"{file}: material.{key} = {value!r}; choose one of {', '.join(options[key])}"
                )
            out[key] = value
        elif key in specs:
            spec = specs[key]
            spec.check(value, f"{file}: material")
            if spec.kind == "rgb":
                if not isinstance(value, list) or len(value) != 3:
                    raise ConfigError(f"{file}: material.{key} must be 3 numbers (linear RGB)")
                out[key] = {"type": "rgb", "value": [float(x) for x in value]}
            else:
                out[key] = float(value)
        else:
            known = ", ".join(sorted([*specs, *options]))
            raise ConfigError(f"{file}: unknown key material.{key} for {kind}; known: {known}")
    return out


def load_render_config(path: str | Path) -> RenderConfig:
    path = Path(path)
    try:
        doc = tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such file") from None
    except tomllib.TOMLDecodeError as err:
        raise ConfigError(f"{path}: not valid TOML ({err})") from None
    unknown = sorted(set(doc) - {"scene", "material", "render"})
    if unknown:
        raise ConfigError(
            f"{path}: unknown table(s) {', '.join(unknown)}; known: scene, material, render"
        )
    for table in ("scene", "material"):
        if table not in doc:
            raise ConfigError(f"{path}: missing [{table}]")
    render = dict(doc.get("render", {}))
    spp = render.pop("spp", 64)
    if render:
        raise ConfigError(f"{path}: unknown key(s) {', '.join(render)} in [render]; known: spp")
    if not isinstance(spp, int) or spp < 1:
        raise ConfigError(f"{path}: render.spp = {spp!r} must be a positive integer")
    try:
        return RenderConfig(
            parse_scene(doc["scene"], path), material_dict(doc["material"], path), spp
        )
    except ValueError as err:  # bounds violations raised by the declarations
        if isinstance(err, CaptureError):
            raise
        raise ConfigError(str(err)) from None
