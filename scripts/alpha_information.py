"""How well the recovery sweep's targets determine alpha, the fit aside: chi^2 of a 5 % change
of alpha (all else at the truth) against a 256-spp target's own Monte Carlo noise.

    .venv/bin/python scripts/alpha_information.py sphere 0.01,0.02,0.05

The change is rendered twice with independent seeds (each with common random numbers across
the change) and their product summed, so the renders' own noise does not add to it; the target's
per-pixel variance comes from two 256-spp renders (3x3 mean). 5 % / sqrt(chi^2) is alpha's sd
for a fit that weighs each pixel by its inverse noise variance, not for layerfit's loss (its
limit: `fit.recovery.data_limit`), and the box-filtered variance of one pair is too low in a
highlight, so it reads low (README, "Recovery over the range"; BENCHMARKS, "What the targets
allow").
"""

import sys

import numpy as np
from scipy.ndimage import uniform_filter

from fit.variant import select_variant

select_variant()
import materials  # noqa: E402

materials.register()

from fit import recovery  # noqa: E402
from fit.render import load_scene, render, scene_dict  # noqa: E402

WIDTH, HEIGHT, CHANGE = 160, 120, 1.05


def images(case, spp, seed):
    scene = recovery.studio(case.shape, WIDTH, HEIGHT)
    material = recovery.glaze(case.truth())
    return [
        render(load_scene(scene_dict(scene, material, i, spp)), spp, seed + 1000 * i)
        for i in range(len(scene.cameras))
    ]


def main(shapes: str, alphas: str) -> None:
    for shape in shapes.split(","):
        for alpha in (float(a) for a in alphas.split(",")):
            base = recovery.Case(shape, roughness=alpha)
            changed = recovery.Case(shape, roughness=alpha * CHANGE)
            one, two = images(base, 256, 1), images(base, 256, 2)
            variance = [
                uniform_filter(0.5 * (a - b) ** 2, (3, 3, 1)) for a, b in zip(one, two, strict=True)
            ]
            d1 = [b - a for a, b in zip(images(base, 512, 7), images(changed, 512, 7), strict=True)]
            d2 = [b - a for a, b in zip(images(base, 512, 8), images(changed, 512, 8), strict=True)]
            chi2 = sum(
                float(np.sum(a * b / np.maximum(v, 1e-12)))
                for a, b, v in zip(d1, d2, variance, strict=True)
            )
            sd = 100 * (CHANGE - 1) / np.sqrt(chi2) if chi2 > 0 else float("inf")
            print(f"{shape} alpha {alpha:g}: chi^2 {chi2:.1f}; sd from the images ~{sd:.1f} %")


if __name__ == "__main__":
    main(*(sys.argv[1:3] if len(sys.argv) > 2 else ("sphere", "0.01,0.02,0.05")))
