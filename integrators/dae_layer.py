"""``DAELayer``: a ``daeint`` simulation as a ``torch.nn.Module``."""

from __future__ import annotations

import torch

from .errors import InputValidationError
from .implicit import daeint
from .layers import _SimulationLayer
from .problems import ImplicitDAE, ImplicitODE, SemiExplicitDAE


class DAELayer(_SimulationLayer):
    """Maps initial states to trajectories of an implicit ODE or index-1 DAE.

    ``forward(x0, z0=None, t=None, u=None) = daeint(problem, x0, z0, t, ...)``; gradients
    reach ``x0`` and the parameters of the problem's functions by
    the implicit function theorem at every step.

    Args:
        problem: :class:`~integrators.problems.ImplicitODE`,
            :class:`~integrators.problems.SemiExplicitDAE` or
            :class:`~integrators.problems.ImplicitDAE`; its functions that are ``nn.Module``
            are registered as submodules ``fn0, fn1`` so their parameters train. Anything
            else (a bare function ``f(t, x)``: use ``ODELayer``) raises InputValidationError.
        t: (T,) default output times (a buffer) or None to require ``t`` in ``forward``.
        return_solution: True returns the Solution, False only ``x`` (*batch, T, n).
        **daeint_kwargs: further ``daeint`` options (``method``, ``rtol``, ``substeps``...).
    """

    def __init__(self, problem, t=None, return_solution=True, **daeint_kwargs):
        if not isinstance(problem, ImplicitODE | SemiExplicitDAE | ImplicitDAE):
            raise InputValidationError(
                f"DAELayer expects an ImplicitODE, SemiExplicitDAE or ImplicitDAE as problem, "
                f"got {type(problem).__name__}; wrap the residual or the (f, g) pair in one of "
                "them (integrators.problems), or use ODELayer for an explicit ODE x' = f(t, x)."
            )
        super().__init__(t, return_solution)
        self.problem = problem
        self.fns = torch.nn.ModuleList(problem.modules())
        self.daeint_kwargs = daeint_kwargs

    def forward(self, x0, z0=None, t=None, u=None):
        """Simulate from ``x0`` (*batch, n) (and algebraic guess ``z0`` (*batch, m))."""
        sol = daeint(self.problem, x0, z0, self._times(t), u=u, **self.daeint_kwargs)
        return sol if self.return_solution else sol.x
