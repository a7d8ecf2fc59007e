"""Fit configs (TOML): which capture, the material (starting values and options), what is free,
and the solver's schedule. Errors name the file and the key.

```toml
capture = "../../shared/data/peer-cycles/sphere-blue/scene.json"  # or a capture folder
[material]                # as in render configs; values are the starting point
type = "glaze"
fresnel = "exact"
[fit]
free = ["glaze.pigment", "glaze.roughness", "glaze.ior"]  # declared keys; also lights.scale,
                          # environment.scale, <layer>.mask.texture (texel by texel), bump, ...
seed = 0
gains = false             # free RGB gain per view but the first (unknown exposure / white balance)
loss = "l2"               # l2 | huber | cauchy (robust: biased under Monte Carlo noise)
loss_scale = 0.05         # robust losses: differences beyond this count less (default: 0.1 x mean)
uncertainty_spp = 64      # the final Jacobian's samples per pixel
downscale = 1             # area-average the photos before anything (DiLiGenT folders, manifests)

[[fit.phases]]            # optional: the default schedule when absent (fit/schedule.py)
solver = "adam"           # adam | lm | bfgs
steps = 100
spp = 8
downscale = 2             # this phase's resolution: the photos area-averaged by this factor
lr = 0.1                  # adam: learning rate
average = 0.0             # adam: fraction of the last iterates averaged (Polyak)
[[fit.phases]]
solver = "lm"
steps = 5
spp = 128
jacobian_spp = 16         # lm: decorrelated Jacobian at this spp (absent: the residual's own)
```
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from captures.schema import Table, load_toml

from .material import ConfigError, material_dict
from .schedule import DEFAULT_SCHEDULE, LOSSES, SOLVERS, Phase


@dataclass(frozen=True)
class FitConfig:
    path: Path
    capture: Path
    material: dict
    free: list[str]
    phases: tuple[Phase, ...]
    seed: int
    gains: bool
    loss: str
    loss_scale: float | None
    uncertainty_spp: int
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
            "seed",
            "gains",
            "loss",
            "loss_scale",
            "uncertainty_spp",
            "downscale",
            "phases",
        ),
    )
    free = t._get("free", None, True)
    if not isinstance(free, list) or not free or not all(isinstance(k, str) for k in free):
        raise t.error("free", "must list parameter keys, e.g. ['glaze.roughness']")
    phases = t._get("phases", None, False)
    if phases is None:
        phases = DEFAULT_SCHEDULE
    elif not isinstance(phases, list) or not phases or not all(isinstance(x, dict) for x in phases):
        raise t.error("phases", "must be one or more [[fit.phases]] tables")
    else:
        phases = tuple(
            _phase(Table(item, path, f"fit.phases[{i}]", PHASE_KEYS))
            for i, item in enumerate(phases)
        )
    return FitConfig(
        path=path,
        capture=capture,
        material=material,
        free=free,
        phases=phases,
        seed=t.number("seed", int, 0, 0),
        gains=t.boolean("gains", False),
        loss=t.string("loss", "l2", LOSSES),
        loss_scale=t.positive("loss_scale", None, False),
        uncertainty_spp=t.number("uncertainty_spp", int, 64, 1),
        downscale=t.number("downscale", int, 1, 1),
    )


PHASE_KEYS = ("solver", "steps", "spp", "downscale", "lr", "average", "jacobian_spp")


def _phase(t: Table) -> Phase:
    solver = t.string("solver", None, SOLVERS)
    allowed = {"adam": ("lr", "average"), "lm": ("jacobian_spp",), "bfgs": ()}[solver]
    for key in ("lr", "average", "jacobian_spp"):
        if t.has(key) and key not in allowed:
            raise t.error(key, f"does not apply to solver = {solver!r}")
    average = t.number("average", float, 0.0, 0.0)
    if average > 1:
        raise t.error("average", f"= {average} is a fraction of the steps: use 0 to 1")
    return Phase(
        solver=solver,
        steps=t.number("steps", int, None, 1),
        spp=t.number("spp", int, None, 1),
        downscale=t.number("downscale", int, 1, 1),
        lr=t.positive("lr", 0.05),
        average=average,
        jacobian_spp=t.number("jacobian_spp", int, None, 1, False),
    )
