"""Read render configs (TOML): `[scene]`, `[material]`, `[render]`. Errors name file and key."""

from __future__ import annotations

import tomllib
from dataclasses import dataclass
from pathlib import Path

from captures import CaptureError, Scene, parse_scene

from .material import ConfigError, material_dict


@dataclass(frozen=True)
class RenderConfig:
    scene: Scene
    material: dict
    spp: int


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
