"""The project's exception and warning hierarchy, as seen from ``sysid``.

Everything ``integrators`` raises is defined in :mod:`integrators.errors` and re-exported here;
the warnings that only ``sysid`` issues (estimation, least squares) are defined here, as
subclasses of :class:`RKIdentWarning`. ``sysid`` users catch the whole family
(:class:`RKIdentError`, :class:`RKIdentWarning`) from one place.
"""

from integrators.errors import (
    ConvergenceError,
    GraphMemoryError,
    HighIndexError,
    HighIndexWarning,
    InputValidationError,
    IntegrationError,
    RKIdentError,
    RKIdentWarning,
    SingularMatrixError,
    TableauError,
)


class PoorExcitationWarning(RKIdentWarning):
    """The input does not excite all parameters: the regressor matrix is ill-conditioned."""


class ConvergenceWarning(RKIdentWarning):
    """An iterative estimate stopped short of a stationary point (iteration limit, failed
    line search, or a step that would still move it by a sizeable part of its standard
    errors); the per-data-set flags say which."""


class ParameterAtBoundWarning(RKIdentWarning):
    """A bounded parameter's estimate ended at its bound: the criterion decreases beyond it,
    so the model or the bound is wrong for these data, and its standard error (and those of
    the parameters it correlates with) do not describe the uncertainty of a minimum."""


class StudyDeclarationError(InputValidationError):
    """A Monte-Carlo study folder holds results of a different declaration (grid, trials,
    seed, chunk, block, estimators or version) than the study asked to run in it."""


class UnstableModelWarning(RKIdentWarning):
    """An estimated model is unstable: its free-run simulation diverges, so simulation
    errors, fit percentages and step responses computed from it are meaningless."""


__all__ = [
    "ConvergenceError",
    "ConvergenceWarning",
    "GraphMemoryError",
    "HighIndexError",
    "HighIndexWarning",
    "InputValidationError",
    "IntegrationError",
    "ParameterAtBoundWarning",
    "PoorExcitationWarning",
    "RKIdentError",
    "RKIdentWarning",
    "SingularMatrixError",
    "StudyDeclarationError",
    "TableauError",
    "UnstableModelWarning",
]
