"""Problem classes for implicit ODEs and index-1 DAEs, integrated by :func:`daeint`.

Each class only stores the user's functions; ``daeint`` turns them into stage residuals
(notes eq. 7.52, 7.56, 7.63). The functions take the time first and the input ``u`` last;
``u`` is omitted when ``daeint`` is called without an input (``u=None``), exactly like ``f`` in
``odeint`` (contract C1). Times are 0-dim tensors (fixed step) or (*batch, 1) (adaptive).

Parameters to be identified: pass the functions as ``torch.nn.Module`` instances (or closures
over tensors that require grad). Gradients reach every tensor the functions use through the
implicit-function-theorem step (see ``integrators._irk_core``); no parameter list is needed.
"""

from __future__ import annotations

from collections.abc import Callable

import torch

from .errors import InputValidationError


def _check_callable(fn, label):
    if not callable(fn):
        raise InputValidationError(f"{label} must be callable, got {type(fn).__name__}.")
    return fn


class _Problem:
    kind = ""

    def modules(self) -> list[torch.nn.Module]:
        """The functions that are ``nn.Module`` (registered by :class:`DAELayer`)."""
        return [fn for fn in self.functions() if isinstance(fn, torch.nn.Module)]

    def functions(self) -> tuple:
        raise NotImplementedError


class ImplicitODE(_Problem):
    """Implicit ODE ``F(t, x', x[, u]) = 0`` with ``dF/dx'`` invertible (notes eq. 7.46).

    Args:
        F: ``F(t, xdot, x[, u]) -> (*batch, n)`` residual, e.g. the mechanical form eq. 7.49
            ``M(q) x' - rhs(q, v)``.
    """

    kind = "implicit"

    def __init__(self, F: Callable):
        self.F = _check_callable(F, "F")

    def functions(self) -> tuple:
        return (self.F,)


class SemiExplicitDAE(_Problem):
    """Semi-explicit DAE ``x' = f(t, x, z[, u]), 0 = g(t, x, z[, u])`` (notes eq. 5.24, 7.61).

    Index 1 requires ``dg/dz`` to be invertible along the trajectory (Corollary 1, eq. 5.56);
    :func:`daeint` checks it.

    Args:
        f: ``f(t, x, z[, u]) -> (*batch, n)``.
        g: ``g(t, x, z[, u]) -> (*batch, m)``.
    """

    kind = "semi"

    def __init__(self, f: Callable, g: Callable):
        self.f = _check_callable(f, "f")
        self.g = _check_callable(g, "g")

    def functions(self) -> tuple:
        return (self.f, self.g)


class ImplicitDAE(_Problem):
    """Fully implicit DAE ``F(t, x', x, z[, u]) = 0`` (notes eq. 5.22, 7.53).

    Index 1 requires ``[dF/dx', dF/dz]`` to be invertible (Theorem 9, eq. 5.53); :func:`daeint`
    checks it.

    Args:
        F: ``F(t, xdot, x, z[, u]) -> (*batch, n + m)``.
    """

    kind = "implicit"

    def __init__(self, F: Callable):
        self.F = _check_callable(F, "F")

    def functions(self) -> tuple:
        return (self.F,)
