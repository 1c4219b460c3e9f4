"""The project's exception and warning hierarchy.

Every error raised by ``integrators`` and ``sysid`` derives from :class:`RKIdentError`, so a
caller can catch the whole family at once. Messages say what was wrong, where (time, step,
sample index) and what to try.
"""


class RKIdentError(Exception):
    """Base class of every exception raised by this project."""


class InputValidationError(RKIdentError, ValueError):
    """An argument has the wrong shape, dtype, ordering or contains non-finite values."""


class TableauError(InputValidationError):
    """A Butcher tableau is malformed, inconsistent, or does not have the claimed order."""


class ConvergenceError(RKIdentError, RuntimeError):
    """An iterative solve (Newton, Gauss-Newton, step-size search) did not converge."""


class IntegrationError(RKIdentError, RuntimeError):
    """A simulation could not be completed (raised only where no per-sample status fits)."""


class GraphMemoryError(RKIdentError, MemoryError):
    """The autograd graph a simulation would keep for its gradient does not fit in the
    available memory (estimated before the run)."""


class HighIndexError(RKIdentError, ValueError):
    """A DAE is of differential index > 1 and must be index-reduced before integration."""


class SingularMatrixError(RKIdentError, RuntimeError):
    """A matrix that must be invertible (normal equations, Newton Jacobian) is singular."""


class RKIdentWarning(UserWarning):
    """Base class of every warning issued by this project."""


class PoorExcitationWarning(RKIdentWarning):
    """The input does not excite all parameters: the regressor matrix is ill-conditioned."""


class ConvergenceWarning(RKIdentWarning):
    """An iterative estimate stopped short of a stationary point (iteration limit, failed
    line search, or a step that would still move it by a sizeable part of its standard
    errors); the per-data-set flags say which."""


class UnstableModelWarning(RKIdentWarning):
    """An estimated model is unstable: its free-run simulation diverges, so simulation
    errors, fit percentages and step responses computed from it are meaningless."""


class HighIndexWarning(RKIdentWarning):
    """An algebraic Jacobian became (nearly) rank deficient during a DAE integration."""
