"""Read render configs (TOML): `[scene]`, `[material]`, `[render]`. Errors name file and key."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from captures import Scene, parse_scene
from captures.schema import load_toml

from .material import ConfigError, material_dict


@dataclass(frozen=True)
class RenderConfig:
    scene: Scene
    material: dict
    spp: int


def load_render_config(path: str | Path) -> RenderConfig:
    path = Path(path)
    doc = load_toml(path, "file")
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
    material = material_dict(doc["material"], path)
    if material is None:
        raise ConfigError(f"{path}: every layer of [material] is disabled: nothing to render")
    return RenderConfig(parse_scene(doc["scene"], path), material, spp)
