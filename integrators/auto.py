"""``method="auto"``: explicit or implicit integration from an estimate of the stiffness.

An explicit method is stable on ``x' = J x`` only while every ``lambda dt`` of the Jacobian
``J = df/dx`` lies in its stability region (notes §6.4, eq. 6.40-6.42); for Dormand-Prince
that region reaches about ``|lambda dt| ~ 3.3`` along the negative real axis. With the
spectral radius ``rho`` of ``J`` at ``x0`` (largest over the batch) and the typical step
``dt`` the output grid asks for (the mean output interval), ``rho dt > threshold`` means the
explicit method would be forced to steps far below ``dt`` by stability alone: the problem is
treated as stiff and integrated with Radau IIA (``integrators.implicit``).
"""

from __future__ import annotations

import torch

from .jacobians import batch_jacobian

__all__ = ["choose_method"]

STIFFNESS_THRESHOLD = 3.0


def choose_method(rhs, x0, t, *, threshold: float = STIFFNESS_THRESHOLD):
    """Pick "dopri5" or "radau_iia" for ``x' = rhs(t, x)`` from ``x0`` over ``t``.

    Args:
        rhs: ``rhs(t, x) -> (*batch, n)`` (input already bound, see :mod:`integrators.inputs`;
            called with the 0-dim time ``t[0]``).
        x0: (*batch, n) initial states.
        t: (T,) output times.
        threshold: stiffness limit on ``rho * dt``.

    Returns:
        ``(method_name, info)`` with ``info`` holding ``spectral_radius`` (max over the batch),
        ``typical_step``, ``stiffness`` (their product), ``threshold`` and a ``reason`` line.
    """
    x0 = torch.as_tensor(x0)
    t = torch.as_tensor(t, dtype=x0.dtype, device=x0.device)
    with torch.no_grad():
        _, J = batch_jacobian(lambda x: rhs(t[0], x), x0, strategy="rows")
        rho = float(torch.linalg.eigvals(J).abs().amax()) if J.numel() else 0.0
    dt = float(t[-1] - t[0]) / max(t.shape[0] - 1, 1)
    stiffness = rho * dt
    stiff = stiffness > threshold
    name = "radau_iia" if stiff else "dopri5"
    reason = (
        f"spectral radius of df/dx at x0 = {rho:.3g}, typical step {dt:.3g}: rho*dt = "
        f"{stiffness:.3g} {'>' if stiff else '<='} {threshold:g} -> "
        f"{'stiff, implicit Radau IIA' if stiff else 'non-stiff, explicit dopri5'}"
    )
    return name, {
        "spectral_radius": rho,
        "typical_step": dt,
        "stiffness": stiffness,
        "threshold": float(threshold),
        "reason": reason,
    }
