"""What a free texture costs a step: the cup's Adam step (a primal render and a reverse pass)
with its three masks' 64x32 textures free, against the same step with them fixed."""

from __future__ import annotations

import statistics
import time
from pathlib import Path

import numpy as np

from .common import Table, machine, ticker

#: The cup with its masks free as textures (its scalars those of the main job).
CONFIG = Path("configs/cup-masks-fit.toml")


def texture_step_table(spp: int = 16, steps: int = 12, warm: int = 4, progress=None) -> Table:
    """Seconds per Adam step (primal and reverse pass at `spp`, the fit's full resolution) of
    the cup: the scalars free with the masks' textures fixed, then with the textures free too
    (new texels every step), frozen and unfrozen; the median of `steps` after `warm` untimed
    (recordings, kernel compilation)."""
    from ..commands.prepare import prepare
    from ..config import load_fit_config
    from ..render import Renderer

    cfg = load_fit_config(CONFIG)
    problem = prepare(cfg, trace=False).problem
    capture = problem.at(1)
    start = {f.key: np.ravel(np.asarray(f.start, np.float32)) for f in problem.free}
    scalars = [f for f in problem.free if not f.shape]
    setups = [
        ("the masks' textures fixed (the scalars free)", scalars, True),
        ("the three 64x32 textures free too", problem.free, True),
        ("the same, unfrozen", problem.free, False),
    ]
    rng = np.random.default_rng(0)
    advance = ticker(progress, "bench: a step with textures free", len(setups) * (warm + steps))
    medians, rows = [], []
    for label, free, freeze in setups:
        renderer = Renderer(capture, problem.material, free, freeze=freeze)
        cotangent = None
        seconds = []
        for step in range(warm + steps):
            values = np.concatenate(
                [rng.uniform(0.3, 1.0, f.size) if f.shape else start[f.key] for f in free]
            ).astype(np.float32)
            began = time.perf_counter()
            image = renderer.render(values, step, spp)
            if cotangent is None:
                cotangent = rng.standard_normal(image.size).astype(np.float32)
            renderer.vjp(values, step, spp, cotangent)
            seconds.append(time.perf_counter() - began)
            advance()
        medians.append(statistics.median(seconds[warm:]))
        rows.append([label, str(sum(f.size for f in free)), f"{medians[-1]:.3f}"])
    for row, median in zip(rows, medians, strict=True):
        row.append(f"{median / medians[0]:.2f}x")
    views = capture.views
    return Table(
        title=f"A step with textures free: the cup, {len(views)} views of "
        f"{views[0].camera.width}x{views[0].camera.height}, {spp} spp",
        columns=["free", "values", "seconds a step", "vs textures fixed"],
        rows=rows,
        notes=[
            f"{CONFIG}: a primal render and a reverse pass per step, new texels every step; "
            f"the median of {steps} steps after {warm} untimed (recordings, compilation)",
            machine(),
        ],
    )
