"""Fit schedules: phases of a solver at a sample count and resolution, and the default one.
Plain data (no JAX, no Mitsuba), so configs load without the heavy imports."""

from __future__ import annotations

from dataclasses import dataclass

LOSSES = ("l2", "huber", "cauchy")
SOLVERS = ("adam", "lm", "bfgs")


@dataclass(frozen=True)
class Phase:
    """One phase of a schedule: a solver, its steps, samples per pixel and resolution
    (`downscale`: area-average the photos by this factor, the cameras follow).
    Adam: `lr` and the averaged fraction of the last iterates (`average`); LM: the decorrelated
    Jacobian's spp (`jacobian_spp`, None: the residual's own seed and spp)."""

    solver: str
    steps: int
    spp: int
    downscale: int = 1
    lr: float = 0.05
    average: float = 0.0
    jacobian_spp: int | None = None

    def __post_init__(self):
        if self.solver not in SOLVERS:
            raise ValueError(f"solver {self.solver!r}; choose one of {', '.join(SOLVERS)}")


#: The default schedule (measured on the Cycles sphere, README "Fitting"): Adam with fresh seeds
#: at half resolution and 8 spp is cheap and robust from far away (its scale-free steps also move
#: a parameter started next to a bound, where the sigmoid is flat); then Adam at full resolution,
#: 32 spp, a small rate, averaging the last half of the iterates (Polyak: the steps' Monte Carlo
#: noise cancels). LM polishes measured worse there: with one seed it converges to that seed's
#: biased optimum (alpha +7 % at 64 spp), with a decorrelated Jacobian to alpha +3 %.
DEFAULT_SCHEDULE = (
    Phase("adam", 100, 8, downscale=2, lr=0.1),
    Phase("adam", 60, 32, lr=0.02, average=0.5),
)
