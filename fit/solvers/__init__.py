"""Solvers on the bridge, one per module (`adam`, `lm`, `bfgs`), their registry, fit schedules
and the Gauss-Newton uncertainty. No Mitsuba import at module level (renders come through
`Problem`)."""

from .base import AbstractSolver, Options, Outcome, PhaseReport, Result
from .checkpoint import Checkpoint
from .problem import LOSSES, Problem, residuals, shape_loss
from .registry import SOLVERS
from .schedule import DEFAULT_SCHEDULE, Phase, default_schedule, run_schedule, solve
from .uncertainty import MAX_UNCERTAINTY_PARAMS, uncertainty

__all__ = [
    "DEFAULT_SCHEDULE",
    "LOSSES",
    "MAX_UNCERTAINTY_PARAMS",
    "SOLVERS",
    "AbstractSolver",
    "Checkpoint",
    "Options",
    "Outcome",
    "Phase",
    "PhaseReport",
    "Problem",
    "Result",
    "default_schedule",
    "residuals",
    "run_schedule",
    "shape_loss",
    "solve",
    "uncertainty",
]
