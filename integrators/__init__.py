"""Differentiable Runge-Kutta integrators (numerics only; knows nothing of ``sysid``)."""

from .adaptive import solve_adaptive
from .collocation import collocation_output_weights, gauss_legendre, radau_iia
from .controllers import GustafssonController, IController, PIController
from .dae_layer import DAELayer
from .errors import (
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
from .implicit import daeint, solve_implicit_ode
from .inputs import CollocationInput, bind_rhs
from .jacobians import batch_jacobian, jacobian_rows
from .layers import ODELayer
from .methods import METHOD_NAMES
from .newton import (
    MinimizeResult,
    NewtonResult,
    NewtonStatus,
    minimize,
    newton,
)
from .odeint import odeint
from .problems import ImplicitDAE, ImplicitODE, SemiExplicitDAE
from .sensitivities import SensitivityResult, sensitivities, variational_sensitivities
from .solution import Solution, SolverStats, Status
from .tableau import TABLEAU_NAMES, ButcherTableau, tableau

__all__ = [
    "DAELayer",
    "ImplicitDAE",
    "ImplicitODE",
    "SemiExplicitDAE",
    "daeint",
    "solve_implicit_ode",
    "GustafssonController",
    "IController",
    "PIController",
    "solve_adaptive",
    "METHOD_NAMES",
    "TABLEAU_NAMES",
    "ButcherTableau",
    "ConvergenceError",
    "GraphMemoryError",
    "HighIndexError",
    "HighIndexWarning",
    "InputValidationError",
    "IntegrationError",
    "RKIdentError",
    "RKIdentWarning",
    "SingularMatrixError",
    "Solution",
    "SolverStats",
    "Status",
    "TableauError",
    "tableau",
    "collocation_output_weights",
    "gauss_legendre",
    "radau_iia",
    "MinimizeResult",
    "NewtonResult",
    "NewtonStatus",
    "batch_jacobian",
    "jacobian_rows",
    "minimize",
    "newton",
    "SensitivityResult",
    "sensitivities",
    "variational_sensitivities",
    "ODELayer",
    "CollocationInput",
    "bind_rhs",
    "odeint",
]
