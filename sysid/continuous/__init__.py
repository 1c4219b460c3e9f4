"""Continuous-time identification: grey-box models fitted through the Runge-Kutta layers.

:class:`GreyBoxModel` wraps a physical right-hand side (a function, a zoo plant, a
:class:`~sysid.mechanics.LagrangianSystem`, an index-1 DAE) with named :class:`Param` s;
:func:`sysid.fit` estimates them by the criteria of :mod:`sysid.continuous.fit`;
:func:`start_values` reads starting values off an identified linear model (:func:`d2c`).
"""

from .fit import CRITERIA
from .greybox import GreyBoxModel
from .params import Param
from .start import d2c, start_values

__all__ = ["CRITERIA", "GreyBoxModel", "Param", "d2c", "start_values"]
