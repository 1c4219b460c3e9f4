"""The project's exception and warning hierarchy.

Every error raised by ``integrators`` and ``sysid`` derives from :class:`RKIdentError` and
every warning from :class:`RKIdentWarning`, so a caller can catch the whole family at once.
This module holds what ``integrators`` raises; the warnings only ``sysid`` issues live in
``sysid.errors``, which re-exports everything here. Messages say what was wrong, where (time, step,
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


class HighIndexWarning(RKIdentWarning):
    """An algebraic Jacobian became (nearly) rank deficient during a DAE integration."""
