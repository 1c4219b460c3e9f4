"""Differentiable Runge-Kutta integrators (numerics only; knows nothing of ``sysid``)."""

from .errors import (
    ConvergenceError,
    HighIndexError,
    HighIndexWarning,
    InputValidationError,
    IntegrationError,
    PoorExcitationWarning,
    RKIdentError,
    RKIdentWarning,
    SingularMatrixError,
    TableauError,
)
from .solution import Solution, SolverStats, Status
from .tableau import TABLEAU_NAMES, ButcherTableau, tableau

__all__ = [
    "TABLEAU_NAMES",
    "ButcherTableau",
    "ConvergenceError",
    "HighIndexError",
    "HighIndexWarning",
    "InputValidationError",
    "IntegrationError",
    "PoorExcitationWarning",
    "RKIdentError",
    "RKIdentWarning",
    "SingularMatrixError",
    "Solution",
    "SolverStats",
    "Status",
    "TableauError",
    "tableau",
]
