"""Named physical parameters of a continuous-time model: free or fixed, bounded, shared or
one per experiment.

A bounded parameter is estimated through an unconstrained coordinate ``z`` so that every
iterate respects the bounds (the estimate and its standard error are reported in physical
units, the covariance by the delta method):

* no bounds: ``p = s z`` with the scale ``s = |p_start|`` (1 for a zero start), so that every
  coordinate of the minimiser is of order one;
* ``min`` only: ``p = min + exp(z)``; ``max`` only: ``p = max - exp(z)``;
* both: ``p = min + (max - min) / (1 + exp(-z))``.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from integrators._options import check_flag
from integrators.errors import InputValidationError

__all__ = ["Param"]


def value_in_experiment(
    value: torch.Tensor, per_experiment: bool, n_experiments: int, experiment: int, who="Param"
) -> torch.Tensor:
    """A parameter's ``value`` in ``experiment`` of ``n_experiments``: ``()`` or ``(*batch,)``.
    A per-experiment value has the experiments last (``(*batch, n_experiments)``, or one
    shared value ``(*batch, 1)``); another last dimension raises
    :class:`InputValidationError` (``who`` names the caller)."""
    if per_experiment and value.numel() > 1:
        if value.shape[-1] not in (1, n_experiments):
            raise InputValidationError(
                f"{who}: a per-experiment parameter of shape {tuple(value.shape)} has "
                f"{value.shape[-1]} values for {n_experiments} experiment(s); its last "
                "dimension must be 1 (one value for every experiment) or one per experiment: "
                "(*batch, 1) for one value per data set of a batch."
            )
        value = value[..., experiment if value.shape[-1] > 1 else 0]
    return value.reshape(()) if value.numel() == 1 else value


class Param:
    """A named physical parameter of a grey-box model.

    Args:
        value: the starting value (free) or the value (fixed), in physical units: a float, or
            for ``per_experiment=True`` a float or one value per experiment.
        free: estimate it (True) or hold it at ``value`` (False).
        min, max: optional bounds (free parameters only); the start must lie strictly inside.
        per_experiment: one value per experiment of the data (e.g. an offset or an initial
            condition that differs between runs) instead of one value shared by all.

    Raises:
        InputValidationError: a value or bound that is not a number, non-finite values,
            ``min >= max``, or a start outside the bounds.
    """

    def __init__(self, value, *, free: bool = True, min=None, max=None, per_experiment=False):
        free = check_flag(free, "Param: free")
        per_experiment = check_flag(per_experiment, "Param: per_experiment")
        try:
            values = torch.as_tensor(value, dtype=torch.float64).detach().reshape(-1)
        except (TypeError, ValueError, RuntimeError):
            raise InputValidationError(
                f"Param: value must be a number (or, per experiment, a sequence of numbers), "
                f"got {value!r}."
            ) from None
        if values.numel() == 0 or not bool(torch.isfinite(values).all()):
            raise InputValidationError(f"Param: value must be finite, got {value!r}.")
        if values.numel() > 1 and not per_experiment:
            raise InputValidationError(
                f"Param: {values.numel()} values given for a shared parameter; give one value, "
                "or per_experiment=True for one value per experiment."
            )
        for name, bound in (("min", min), ("max", max)):
            real = isinstance(bound, (int, float, np.integer, np.floating)) or (
                isinstance(bound, torch.Tensor) and bound.numel() == 1 and bound.dtype != torch.bool
            )
            if bound is not None and (isinstance(bound, bool) or not real):
                raise InputValidationError(
                    f"Param: {name} must be a number or None, got {bound!r}."
                )
            if bound is not None and not math.isfinite(float(bound)):
                raise InputValidationError(f"Param: {name} must be finite or None, got {bound!r}.")
        if min is not None and max is not None and float(min) >= float(max):
            raise InputValidationError(f"Param: min = {min} must be < max = {max}.")
        lo = -math.inf if min is None else float(min)
        hi = math.inf if max is None else float(max)
        if free and not bool(((values > lo) & (values < hi)).all()):
            raise InputValidationError(
                f"Param: the start {values.tolist()} lies outside the bounds ({min}, {max}); "
                "start strictly inside them (a bounded parameter is estimated through a "
                "logarithmic or logistic coordinate that never reaches the bound)."
            )
        self.values = values
        self.free = bool(free)
        self.min = None if min is None else float(min)
        self.max = None if max is None else float(max)
        self.per_experiment = bool(per_experiment)

    def __repr__(self) -> str:
        value = float(self.values[0]) if self.values.numel() == 1 else self.values.tolist()
        bounds = (
            "" if self.min is None and self.max is None else f", min={self.min}, max={self.max}"
        )
        extra = ", per_experiment=True" if self.per_experiment else ""
        return f"Param({value}, free={self.free}{bounds}{extra})"

    def start(self, n_experiments: int, experiment: int = 0) -> torch.Tensor:
        """The (starting) value in ``experiment`` of ``n_experiments``: ``()``, or
        ``(*batch,)`` where the values are a fitted model's, one per data set of its batch
        (``GreyBoxModel.with_values``: ``(*batch,)`` shared, ``(*batch, n_experiments)`` per
        experiment)."""
        return value_in_experiment(self.values, self.per_experiment, n_experiments, experiment)

    def scale(self, start: torch.Tensor) -> torch.Tensor:
        """The scale ``s`` of an unbounded parameter (see the module docstring)."""
        s = start.abs()
        return torch.where(s > 0, s, torch.ones_like(s))

    def to_unconstrained(self, value: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
        """``z`` of a physical value (strictly inside the bounds)."""
        if self.min is not None and self.max is not None:
            frac = (value - self.min) / (self.max - self.min)
            return torch.log(frac) - torch.log1p(-frac)
        if self.min is not None:
            return torch.log(value - self.min)
        if self.max is not None:
            return torch.log(self.max - value)
        return value / scale

    def to_physical(
        self, z: torch.Tensor, scale: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The physical value ``p(z)`` and the derivative ``dp/dz`` (same shape as ``z``)."""
        if self.min is not None and self.max is not None:
            sig = torch.sigmoid(z)
            width = self.max - self.min
            return self.min + width * sig, width * sig * (1 - sig)
        if self.min is not None:
            e = torch.exp(z)
            return self.min + e, e
        if self.max is not None:
            e = torch.exp(z)
            return self.max - e, -e
        return scale * z, scale.expand_as(z)
