"""System identification and modelling built on ``integrators``."""

from . import dae, zoo
from .data import IOData
from .errors import (
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
from .estimation import FitResult, UniformNoiseSet, fit, uniform_noise_mle_set
from .filters import iir_filter
from .linearize import linearize, simulate_lti_zoh, steady_state, zoh_discretize
from .lls import LLSResult, fir_lls, lls
from .mechanics import LagrangianSystem, distributed_body, spring_potential
from .models import ARMAX, ARX, BJ, FIR, OE, PolynomialModel
from .validation import (
    OrderSelection,
    ResidualTestResult,
    aic,
    fit_percent,
    fpe,
    residual_test,
    select_order,
)

__all__ = [
    "ARMAX",
    "ARX",
    "BJ",
    "FIR",
    "OE",
    "IOData",
    "PolynomialModel",
    "iir_filter",
    "FitResult",
    "UniformNoiseSet",
    "fit",
    "uniform_noise_mle_set",
    "LLSResult",
    "fir_lls",
    "lls",
    "ResidualTestResult",
    "aic",
    "fit_percent",
    "fpe",
    "residual_test",
    "OrderSelection",
    "select_order",
    "dae",
    "zoo",
    "linearize",
    "simulate_lti_zoh",
    "steady_state",
    "zoh_discretize",
    "LagrangianSystem",
    "distributed_body",
    "spring_potential",
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
