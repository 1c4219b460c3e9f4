"""The project's exception and warning hierarchy, as seen from ``sysid``.

Everything ``integrators`` raises is defined in :mod:`integrators.errors` and re-exported here,
so ``sysid`` users catch the whole family (:class:`RKIdentError`, :class:`RKIdentWarning`)
from one place.
"""

from integrators.errors import (
    ConvergenceError,
    ConvergenceWarning,
    GraphMemoryError,
    HighIndexError,
    HighIndexWarning,
    InputValidationError,
    IntegrationError,
    PoorExcitationWarning,
    RKIdentError,
    RKIdentWarning,
    SingularMatrixError,
    TableauError,
    UnstableModelWarning,
)

__all__ = [
    "ConvergenceError",
    "ConvergenceWarning",
    "GraphMemoryError",
    "HighIndexError",
    "HighIndexWarning",
    "InputValidationError",
    "IntegrationError",
    "PoorExcitationWarning",
    "RKIdentError",
    "RKIdentWarning",
    "SingularMatrixError",
    "TableauError",
    "UnstableModelWarning",
]
