"""The solvers a `[[fit.phases]]` table can name: one line each."""

from .adam import Adam
from .base import AbstractSolver
from .bfgs import BFGS
from .gn import GaussNewton
from .lm import LevenbergMarquardt

SOLVERS: dict[str, type[AbstractSolver]] = {
    "adam": Adam,
    "lm": LevenbergMarquardt,
    "bfgs": BFGS,
    "gn": GaussNewton,
}
