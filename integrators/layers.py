"""``ODELayer``: an ``odeint`` simulation as a ``torch.nn.Module`` (neural-ODE style)."""

from __future__ import annotations

import torch

from ._options import check_flag
from .errors import InputValidationError
from .odeint import odeint


class _SimulationLayer(torch.nn.Module):
    """What :class:`ODELayer` and ``DAELayer`` share: the default output times ``t`` (a buffer,
    or None) and the ``return_solution`` flag, both named after the layer's class in messages.
    """

    def __init__(self, t, return_solution):
        super().__init__()
        name = type(self).__name__
        self.return_solution = check_flag(return_solution, f"{name}: return_solution")
        if t is not None and not isinstance(t, torch.Tensor):  # a list: exact float64 times
            t = torch.as_tensor(t, dtype=torch.float64)
        self.register_buffer("t", t)

    def _apply(self, fn, recurse=True):
        """Module conversions (``.float()``, ``.double()``, ``.to(dtype)``) move the output
        times to the new device but keep the dtype they were given: a float32 round trip
        would round them (0.1 -> 0.10000000149); odeint casts them to the state's dtype."""
        t = self.t
        super()._apply(fn, recurse)
        if t is not None and self.t.dtype != t.dtype:
            self.t = t.to(self.t.device)
        return self

    def _times(self, t):
        """The output times of a forward call: ``t``, else the default ones."""
        t = self.t if t is None else t
        if t is None:
            raise InputValidationError(
                f"{type(self).__name__} needs output times: pass t to the constructor or to "
                "forward()."
            )
        return t


class ODELayer(_SimulationLayer):
    """Maps initial states to trajectories: ``forward(x0) = odeint(f, x0, t, ...)``.

    Args:
        f: the model ``f(t, x)`` or ``f(t, x, u)``; an ``nn.Module`` is registered as the
            submodule ``f`` so its parameters appear in ``layer.parameters()`` and train.
        t: (T,) default output times (a buffer, so it follows ``.to(device)``), or None to
            require ``t`` in every forward call.
        method: any ``odeint`` method.
        return_solution: True returns the :class:`~integrators.solution.Solution`; False
            returns only its states ``x`` (*batch, T, nx).
        **odeint_kwargs: further ``odeint`` options (``substeps``, ``rtol``, ``compile``...).
    """

    def __init__(self, f, t=None, method="rk4", return_solution=True, **odeint_kwargs):
        super().__init__(t, return_solution)
        self.f = f
        self.method = method
        self.odeint_kwargs = odeint_kwargs

    def forward(self, x0, t=None, u=None):
        """Simulate from ``x0`` (*batch, nx) over ``t`` (or the default grid) with input ``u``.

        Returns:
            The Solution, or its (*batch, T, nx) states when ``return_solution=False``.
        """
        sol = odeint(self.f, x0, self._times(t), method=self.method, u=u, **self.odeint_kwargs)
        return sol if self.return_solution else sol.x
