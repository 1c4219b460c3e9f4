"""Continuous-time identification: grey-box models fitted through the Runge-Kutta layers.

:class:`GreyBoxModel` wraps a physical right-hand side (a function, a zoo plant, a
:class:`~sysid.mechanics.LagrangianSystem`, an index-1 DAE) with named :class:`Param` s;
:func:`sysid.fit` estimates them by the criteria of :mod:`sysid.continuous.fit`;
:func:`start_values` reads starting values off an identified linear model (:func:`d2c`).
:class:`NeuralODE`, :class:`HybridODE` (physics plus a residual network) and
:class:`LagrangianNetwork` (learned mass matrix, potential and dissipation) are
continuous-time models with learned parts (:mod:`sysid.continuous.neural`);
:func:`rollout_diagnostics` compares a model's long rollout with the true system's, against
the floor of the true system's own sensitivity to its initial state, and its energy drift.
"""

from .diagnostics import RolloutDiagnostics, rollout_diagnostics
from .fit import CRITERIA
from .greybox import GreyBoxModel
from .neural import ContinuousTimeModel, HybridODE, LagrangianNetwork, NeuralODE
from .params import Param
from .start import d2c, start_values

__all__ = [
    "CRITERIA",
    "ContinuousTimeModel",
    "GreyBoxModel",
    "HybridODE",
    "LagrangianNetwork",
    "NeuralODE",
    "Param",
    "RolloutDiagnostics",
    "d2c",
    "rollout_diagnostics",
    "start_values",
]
