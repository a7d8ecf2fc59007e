"""Forward rendering: a Mitsuba scene to a linear float32 image, in passes for progress."""

from __future__ import annotations

from collections.abc import Callable

import mitsuba as mi
import numpy as np

#: Samples per pixel of one pass; a render of more spp averages passes with distinct seeds.
PASS_SPP = 64


def render(
    scene: mi.Scene,
    spp: int,
    seed: int = 0,
    progress: Callable[[int], None] | None = None,
) -> np.ndarray:
    """Render `spp` samples per pixel as (H, W, 3) float32, calling `progress(spp_done)` per pass.

    Passes of at most `PASS_SPP` samples use seeds `seed, seed + 1, ...` (modulo 2^32, the
    sampler's seed width); the result is their spp-weighted mean, equal in distribution to one
    render at `spp`.
    """
    total, done, seed_i = None, 0, seed
    while done < spp:
        n = min(PASS_SPP, spp - done)
        image = np.asarray(mi.render(scene, spp=n, seed=seed_i), dtype=np.float64)[..., :3]
        total = image * n if total is None else total + image * n
        done, seed_i = done + n, (seed_i + 1) % 2**32
        if progress is not None:
            progress(done)
    return (total / spp).astype(np.float32)
