"""Typed configs (TOML): render configs and fit configs. Each field has a one-line doc; loading is
derived from the fields (pydantic), and every error names the file, the key and the fix.

Render config:
```toml
[scene]                   # captures/schema.py: geometry, cameras, lights, environment
[material]                # fit/material/build.py; or material = "preset.toml"
[render]
spp = 64
```
Fit config:
```toml
capture = "../../shared/data/peer-cycles/sphere-blue/scene.json"  # or a capture folder
[material]                # as in render configs (or a preset); values are the starting point
type = "glaze"
fresnel = "exact"
[fit]
free = ["glaze.pigment", "glaze.roughness", "glaze.ior"]  # keys (fit/material/keys.py); also
                          # lights.scale, environment.scale, <layer>.mask.texture, bump, ...
seed = 0
gains = false             # a free RGB gain per view, geometric mean 1 (exposure, white balance)
loss = "l2"               # l2 | huber | cauchy (robust: biased under Monte Carlo noise)
loss_scale = 0.05         # robust losses: differences beyond this count less (default: 0.1 x mean)
uncertainty_spp = 64      # the final Jacobian's samples per pixel
downscale = 1             # area-average the photos before anything (DiLiGenT folders, manifests)
quality = "default"       # draft | default | best: half the steps at half resolution (views
                          # keeping 48 pixels a side), or twice the steps (of the default
                          # schedule or the phases below)
starts = 1                # multi-start: this many starts on Ray workers, the best kept (fit/batch)
start_spread = 1.5        # the other starts' spread around this one (unconstrained units)
starts_spp = 256          # spp of the common loss that picks the best start
[fit.textures]            # optional: colours or mask textures fitted texel by texel (in free too)
"glaze.pigment" = [64, 32]   # width, height (fit/material/textures.py), or "photo": the size
                             # of the first photograph at fit.downscale

[[fit.phases]]            # optional: the default schedule when absent (fit/solvers/schedule.py;
                          # with a mask threshold free, its first 30 Adam steps hold them)
solver = "adam"           # adam | gn | lm | bfgs, and its options (fit/solvers/<solver>.py)
steps = 100
spp = 8
downscale = 2             # this phase's resolution: the photos area-averaged by this factor
lr = 0.1                  # adam: learning rate
average = 0.0             # adam: fraction of the last iterates averaged (Polyak)
hold = []                 # adam: keys or patterns held through the phase ("*.mask.threshold")
[[fit.phases]]
solver = "lm"
steps = 5
spp = 128
jacobian_spp = 16         # lm: decorrelated Jacobian at this spp (absent: the residual's own)
```
"""

from .models import (
    FitConfig,
    FitSettings,
    RenderConfig,
    config_identity,
    load_fit_config,
    load_render_config,
)

__all__ = [
    "FitConfig",
    "FitSettings",
    "RenderConfig",
    "config_identity",
    "load_fit_config",
    "load_render_config",
]
