"""Fit configs (TOML): which capture, the material (starting values and options), what is free,
and the solver's schedule. Errors name the file and the key.

```toml
capture = "../../shared/data/peer-cycles/sphere-blue/scene.json"  # or a capture folder
[material]                # as in render configs; values are the starting point
type = "glaze"
fresnel = "exact"
[fit]
free = ["glaze.pigment", "glaze.roughness", "glaze.ior"]
solver = "schedule"       # schedule (Adam, then LM) | lm | adam
seed = 0
adam_steps = 150
adam_spp = 8
adam_lr = 0.1
lm_steps = 6
lm_spp = 64
polish_steps = 50         # Adam, fresh seeds, Polyak-averaged: removes LM's fixed-seed bias
polish_spp = 32
polish_lr = 0.01
gains = false             # free RGB gain per view but the first (unknown exposure / white balance)
downscale = 1             # area-average the photos (DiLiGenT folders, capture manifests)
```
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from captures.schema import Table, load_toml

from .material import ConfigError, material_dict

SOLVERS = ("schedule", "lm", "adam")


@dataclass(frozen=True)
class FitConfig:
    path: Path
    capture: Path
    material: dict
    free: list[str]
    solver: str
    seed: int
    adam_steps: int
    adam_spp: int
    adam_lr: float
    lm_steps: int
    lm_spp: int
    polish_steps: int
    polish_spp: int
    polish_lr: float
    gains: bool
    downscale: int


def load_fit_config(path: str | Path) -> FitConfig:
    path = Path(path)
    doc = load_toml(path, "file")
    top = Table(doc, path, "", ("capture", "material", "fit"))
    capture = top.path("capture")
    if "material" not in doc:
        raise ConfigError(f"{path}: missing [material] (the starting point)")
    material = material_dict(doc["material"], path)
    if material is None:
        raise ConfigError(f"{path}: every layer of [material] is disabled")
    t = Table(
        doc.get("fit", {}),
        path,
        "fit",
        (
            "free",
            "solver",
            "seed",
            "adam_steps",
            "adam_spp",
            "adam_lr",
            "lm_steps",
            "lm_spp",
            "polish_steps",
            "polish_spp",
            "polish_lr",
            "gains",
            "downscale",
        ),
    )
    free = t._get("free", None, True)
    if not isinstance(free, list) or not free or not all(isinstance(k, str) for k in free):
        raise t.error("free", "must list parameter keys, e.g. ['glaze.roughness']")
    return FitConfig(
        path=path,
        capture=capture,
        material=material,
        free=free,
        solver=t.string("solver", "schedule", SOLVERS),
        seed=t.number("seed", int, 0, 0),
        adam_steps=t.number("adam_steps", int, 150, 0),
        adam_spp=t.number("adam_spp", int, 8, 1),
        adam_lr=t.positive("adam_lr", 0.1),
        lm_steps=t.number("lm_steps", int, 15, 0),
        lm_spp=t.number("lm_spp", int, 64, 1),
        polish_steps=t.number("polish_steps", int, 50, 0),
        polish_spp=t.number("polish_spp", int, 32, 1),
        polish_lr=t.positive("polish_lr", 0.01),
        gains=t.boolean("gains", False),
        downscale=t.number("downscale", int, 1, 1),
    )
