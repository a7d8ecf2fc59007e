"""Paint the cup's layer masks (configs/textures/*.exr) as functions of height on the default
procedural cup: where glaze, lime scale and coffee stains sit before the fbm noise breaks them up.

Run from the project root: `.venv/bin/python scripts/make_cup_textures.py`. The masks vary along the
profile (v) only; u (around the axis) is constant, so they tile across the seam.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from captures.geometry import CupShape, cup_profile
from captures.images import write_image

ROWS = 1024
OUT = Path(__file__).resolve().parent.parent / "configs" / "textures"


def smoothstep(x, lo, hi):
    t = np.clip((x - lo) / (hi - lo), 0.0, 1.0)
    return t * t * (3 - 2 * t)


def band(z, lo, hi, soft):
    return smoothstep(z, lo - soft, lo + soft) * (1 - smoothstep(z, hi - soft, hi + soft))


def main() -> None:
    shape = CupShape()
    profile = cup_profile(shape)
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(profile, axis=0), axis=1))])
    v_profile = arc / arc[-1]
    v = (np.arange(ROWS) + 0.5) / ROWS
    r, z = (np.interp(v, v_profile, profile[:, k]) for k in (0, 1))
    rim_v = v_profile[np.argmax(profile[:, 1])]
    inside = v > rim_v
    h = shape.height

    masks = {
        # glaze everywhere but the unglazed foot ring and outer base
        "glaze": np.where(inside, 1.0, smoothstep(z, 0.006, 0.010)),
        # lime scale on the rim, a little way down both walls, and on the inner base
        "lime": np.maximum(
            smoothstep(z, 0.86 * h, 0.97 * h),
            0.7 * inside * (1 - smoothstep(z, shape.base + 0.001, shape.base + 0.006)),
        ),
        # coffee: a ring at the fill line, a wash below it, the inner base; drips outside
        "stain": np.where(
            inside,
            np.maximum(
                band(z, 0.70 * h, 0.75 * h, 0.004), 0.45 * (1 - smoothstep(z, 0.2 * h, 0.7 * h))
            ),
            0.8 * band(z, 0.62 * h, 0.86 * h, 0.01),
        ),
    }
    OUT.mkdir(parents=True, exist_ok=True)
    for name, column in masks.items():
        image = np.repeat(column.astype(np.float32)[:, None, None], 4, axis=1)
        write_image(OUT / f"{name}.exr", image)
        print(f"wrote {OUT / name}.exr: mean {column.mean():.3f}, r from {r.min():.3f}")


if __name__ == "__main__":
    main()
