"""The input between its samples, at the stage times of a fixed-step Runge-Kutta simulation.

A continuous-time model sees the input at every stage time ``t_k + tau Ts`` of sample
interval ``k`` (``tau = (m + c_i) / substeps`` for stage ``i`` of substep ``m``, notes
eq. 8.32). :func:`input_between_samples` reconstructs it from the samples ``u_k`` in the way
:attr:`sysid.IOData.intersample` names:

* ``"zoh"``: held, ``u(t_k + tau Ts) = u_k`` on the closed interval (eq. 8.34);
* ``"foh"``: linear, ``(1 - tau) u_k + tau u_{k+1}``;
* ``"cubic"``: the not-a-knot cubic spline through all samples (scipy ``CubicSpline``);
* ``"bl"``: band-limited, the trigonometric interpolant of the record taken as one period:
  ``u(t_k + tau Ts) = IDFT(U_f exp(2 pi i f tau / N))``, with the Nyquist bin of an even
  ``N`` multiplied by ``cos(pi tau)`` (its real interpolant). Exact for a periodic
  multisine below the Nyquist frequency; on a record that is not periodic the mismatch of
  its ends rings near them (Gibbs).

The values come as the coefficients of a :class:`integrators.inputs.CollocationInput` whose
nodes are the stage fractions, so :func:`integrators.sensitivities` evaluates exactly these
values at every stage.
"""

from __future__ import annotations

import numpy as np
import scipy.interpolate
import torch

from integrators.tableau import ButcherTableau

__all__ = ["input_between_samples", "stage_fractions"]


def stage_fractions(tab: ButcherTableau, substeps: int) -> np.ndarray:
    """The distinct fractions ``tau = (m + c_i) / substeps`` in [0, 1] of a sample interval at
    which a fixed-step method with ``substeps`` steps per interval evaluates the input,
    sorted: (q,) float64."""
    c = np.asarray(tab.c, dtype=float)
    tau = (np.arange(substeps)[:, None] + c[None, :]).ravel() / substeps
    return np.unique(np.round(tau, 14))


def input_between_samples(u: torch.Tensor, kind: str, tau: np.ndarray) -> torch.Tensor:
    """The input at ``t_k + tau_j Ts`` for every interval ``k = 0, ..., N-2``.

    Args:
        u: (*batch, N, nu) samples at ``t_k = k Ts`` (N >= 2).
        kind: ``"zoh"``, ``"foh"``, ``"cubic"`` or ``"bl"`` (see the module docstring).
        tau: (q,) fractions of the interval in [0, 1].

    Returns:
        (*batch, N-1, q, nu) tensor (dtype and device of ``u``); empty for ``nu = 0`` (an
        autonomous system: nothing to interpolate), whatever ``kind``.
    """
    N = u.shape[-2]
    tau_t = torch.as_tensor(tau, dtype=u.dtype, device=u.device)
    if u.shape[-1] == 0:
        return u.new_zeros(*u.shape[:-2], N - 1, tau_t.shape[0], 0)
    lo, hi = u[..., :-1, None, :], u[..., 1:, None, :]
    if kind == "zoh":
        return lo.expand(*lo.shape[:-2], tau_t.shape[0], u.shape[-1]).clone()
    if kind == "foh":
        w = tau_t[:, None]
        return (1 - w) * lo + w * hi
    if kind == "cubic":
        samples = u.detach().cpu().double().numpy()
        spline = scipy.interpolate.CubicSpline(np.arange(N), samples, axis=-2)
        points = np.arange(N - 1)[:, None] + np.asarray(tau)[None, :]
        return torch.as_tensor(spline(points), dtype=u.dtype, device=u.device)
    if kind == "bl":
        spectrum = torch.fft.rfft(u, dim=-2)  # (*batch, N // 2 + 1, nu)
        f = torch.arange(spectrum.shape[-2], dtype=u.dtype, device=u.device)
        phase = torch.exp(2j * torch.pi * f[None, :] * tau_t[:, None] / N)  # (q, F)
        if N % 2 == 0:
            phase[:, -1] = torch.cos(torch.pi * tau_t)
        shifted = torch.fft.irfft(spectrum.unsqueeze(-3) * phase[..., None], n=N, dim=-2)
        return shifted[..., :-1, :].movedim(-3, -2)  # (*batch, N-1, q, nu)
    raise ValueError(f"unknown intersample kind {kind!r}")
