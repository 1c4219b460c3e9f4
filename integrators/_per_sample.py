"""The per-sample arithmetic of the host step control, in two representations.

The adaptive Radau IIA loop (:func:`integrators.radau.adaptive_loop`) and its step-size rule
(:class:`integrators.controllers.GustafssonController`) are written once against the small
set of operations below. :class:`ArrayOps` holds every per-sample quantity (time, step size,
flag, counter, error norm) as a host (numpy) array shaped ``(*batch,)``; :class:`ScalarOps`
holds them as Python floats, ints and bools, for one trajectory. Both give the same values:
the operations are the same IEEE operations in the same order (numpy's vectorised ``power``
and the C library's ``pow`` may round one bit apart). Python scalars pay for one trajectory
because the loop does about a hundred such operations per step, and numpy's per-call
overhead on a one-element array is many times that of Python float arithmetic.
"""

from __future__ import annotations

import numpy as np
import torch

from ._irk_core import to_host


def _pick(mask: np.ndarray, new, old):
    """``new`` where the host bool ``mask`` holds, else ``old`` (trailing axes broadcast);
    ``new`` itself when every member moves (the common case, one check instead of a select)."""
    if np.count_nonzero(mask) == mask.size:
        return new
    return np.where(mask.reshape(mask.shape + (1,) * (np.ndim(new) - mask.ndim)), new, old)


class ArrayOps:
    """Per-sample quantities as host (numpy) arrays of shape ``hshape``, steps in ``hdt``."""

    scalar = False
    where = staticmethod(np.where)
    minimum = staticmethod(np.minimum)
    maximum = staticmethod(np.maximum)
    abs = staticmethod(np.abs)
    pick = staticmethod(_pick)

    def __init__(self, hshape: tuple = (1,), hdt=np.float64):
        self.hshape, self.hdt = hshape, hdt

    @staticmethod
    def any(mask) -> bool:
        """``mask.any()`` without the method's Python-level wrapper."""
        return np.count_nonzero(mask) > 0

    @staticmethod
    def not_(mask):
        return ~mask

    @staticmethod
    def errstate():
        """Silence the floating-point warnings of inf and nan operands (they are handled)."""
        return np.errstate(all="ignore")

    def flags(self, value: bool = False):
        return np.full(self.hshape, value, dtype=bool)

    def counts(self):
        return np.zeros(self.hshape, dtype=np.int64)

    def full(self, value):
        """A per-sample time or step size ``value`` (a number)."""
        return np.full(self.hshape, value, dtype=self.hdt)

    def steps(self, h):
        """Step sizes in the state's dtype."""
        return h.astype(self.hdt, copy=False)

    def float64(self, a):
        return a.astype(np.float64, copy=False)

    def from_tensor(self, a: torch.Tensor):
        """A per-sample tensor (*batch,) as step sizes."""
        return to_host(a, self.hshape).astype(self.hdt)

    def host(self, a, dtype=None) -> np.ndarray:
        """``a`` as a host array of shape ``hshape`` (``a`` itself here: updates in place)."""
        return a if dtype is None else a.astype(dtype, copy=False)

    def back(self, a: np.ndarray):
        """The representation of a host array made by :meth:`host`."""
        return a


class ScalarOps(ArrayOps):
    """One trajectory: per-sample quantities as Python floats, ints and bools (float64)."""

    scalar = True
    where = staticmethod(lambda mask, new, old: new if mask else old)
    pick = where
    minimum = staticmethod(min)
    maximum = staticmethod(max)
    abs = staticmethod(abs)

    @staticmethod
    def any(mask) -> bool:
        return bool(mask)

    @staticmethod
    def not_(mask):
        return not mask

    @staticmethod
    def errstate():
        return np.errstate()

    def flags(self, value: bool = False):
        return value

    def counts(self):
        return 0

    def full(self, value):
        return float(value)

    def steps(self, h):
        return h

    def float64(self, a):
        return a

    def from_tensor(self, a: torch.Tensor):
        return float(a.detach().reshape(()))

    def host(self, a, dtype=None) -> np.ndarray:
        """A fresh host array of shape ``hshape`` holding ``a`` (updates go to the copy)."""
        return np.full(self.hshape, a, dtype=dtype)

    def back(self, a: np.ndarray):
        return a.reshape(-1)[0].item()
