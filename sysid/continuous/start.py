"""Start values of a grey-box model from an identified linear discrete-time model.

A linear model (ARX, OE, ... or any python-control discrete system) fitted to the data is
turned into continuous time by inverting zero-order-hold sampling, and a user map reads the
physical parameters off the continuous system. Zero-order hold with sample time ``Ts`` maps
``x' = A x + B u`` to ``x_{k+1} = Ad x_k + Bd u_k`` with ``[[Ad, Bd], [0, I]] =
expm([[A, B], [0, 0]] Ts)`` (the course notes (Modelling and Simulation) eq. 1.55 with the
input constant over a step), so ``[[A, B], [0, 0]] = logm([[Ad, Bd], [0, I]]) / Ts``
(principal matrix logarithm: the inverse where every ``|Im(eig(A))| Ts < pi``). ``C`` and
``D`` are unchanged.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import scipy.linalg
import torch

from integrators.errors import InputValidationError

__all__ = ["d2c", "start_values"]


def d2c(sys_d, Ts: float | None = None):
    """The continuous-time system whose zero-order-hold sampling is ``sys_d``.

    Args:
        sys_d: a python-control discrete system (``StateSpace`` or ``TransferFunction``,
            ``dt`` its sample time), a fitted :class:`sysid.PolynomialModel` (unbatched) or the
            :class:`sysid.FitResult` of one.
        Ts: sample time where ``sys_d`` has none (``dt=True``); else it must agree.

    Returns:
        ``control.StateSpace`` in continuous time (the state coordinates of a ``StateSpace``
        input are kept).

    Raises:
        InputValidationError: a continuous-time input, no sample time, or a discrete pole on
            the closed negative real axis (``z <= 0``: a pure delay or an integrating /
            oscillating mode at the Nyquist frequency), where no real logarithm exists.
    """
    import control

    sys_d = _as_control(sys_d)
    dt = sys_d.dt
    if dt is None or dt == 0:
        raise InputValidationError(
            "d2c: the system is continuous-time (dt = 0 or None); give a discrete system."
        )
    if dt is True:
        if Ts is None:
            raise InputValidationError("d2c: the system has no sample time (dt=True); pass Ts=.")
        dt = float(Ts)
    elif Ts is not None and abs(float(Ts) - float(dt)) > 1e-12 * float(dt):
        raise InputValidationError(f"d2c: Ts = {Ts} disagrees with the system's dt = {dt}.")
    ss = control.ss(sys_d)
    A, B, C, D = (np.atleast_2d(np.asarray(m, dtype=float)) for m in (ss.A, ss.B, ss.C, ss.D))
    n, m = B.shape
    poles = np.linalg.eigvals(A)
    bad = [z for z in poles if abs(z.imag) <= 1e-9 * max(1.0, abs(z)) and z.real <= 1e-12]
    if bad:
        raise InputValidationError(
            f"d2c: the discrete pole(s) {[complex(z) for z in bad]} lie on the negative real "
            "axis or at 0, where exp(s Ts) = z has no real solution s: no continuous-time "
            "system sampled by zero-order hold gives them. A pole at 0 is a pure delay (e.g. "
            "an input delay nk > 1, or an FIR model); a negative one is a mode at the Nyquist "
            "frequency or an artefact of noise. Fit a lower-order model (nf, na), an OE model "
            "instead of ARX, or sample faster."
        )
    aug = np.zeros((n + m, n + m))
    aug[:n, :n], aug[:n, n:], aug[n:, n:] = A, B, np.eye(m)
    log = scipy.linalg.logm(aug) / dt
    if np.iscomplexobj(log):
        log = log.real
    return control.ss(log[:n, :n], log[:n, n:], C, D)


def start_values(
    linear, to_params: Callable, Ts: float | None = None
) -> dict[str, float | torch.Tensor]:
    """Start values of a grey-box model read off an identified linear model.

    Args:
        linear: the discrete-time linear model (see :func:`d2c`); a batched
            :class:`sysid.PolynomialModel` / :class:`sysid.FitResult` gives one set per
            member.
        to_params: ``to_params(sys_c) -> dict[name, value]`` with ``sys_c`` the continuous
            system as a python-control ``TransferFunction`` (``control.ss(sys_c)`` for its
            state space). E.g. for a spring-mass-damper ``1 / (m s^2 + d s + k)`` with the
            monic denominator ``s^2 + (d/m) s + k/m``: ``m = 1 / num[-1]``,
            ``d = den[1] m``, ``k = den[2] m``.
        Ts: sample time where ``linear`` has none.

    Returns:
        name -> float (one model) or (*batch,) tensor (a batched one), usable as
        :class:`Param` values or in ``GreyBoxModel.with_values``.

    Raises:
        InputValidationError: see :func:`d2c`; ``to_params`` returning anything but a dict
            of finite numbers.
    """
    import control

    systems = _as_control(linear, allow_batch=True)
    batch = None
    if isinstance(systems, tuple):
        batch, systems = systems
    out = []
    for sys_d in systems if batch is not None else [systems]:
        sys_c = control.ss2tf(d2c(sys_d, Ts))
        values = to_params(sys_c)
        if not isinstance(values, dict) or not values:
            raise InputValidationError(
                f"start_values: to_params must return a dict name -> value, got {values!r}."
            )
        clean = {}
        for name, v in values.items():
            v = float(np.real(v))
            if not np.isfinite(v):
                raise InputValidationError(
                    f"start_values: to_params gave {name} = {v} for the continuous system "
                    f"{sys_c}; check the map (which coefficient is which)."
                )
            clean[name] = v
        out.append(clean)
    if batch is None:
        return out[0]
    return {
        n: torch.tensor([o[n] for o in out], dtype=torch.float64).reshape(batch) for n in out[0]
    }


def _as_control(linear, allow_batch: bool = False):
    """A python-control system from a control system, a PolynomialModel or a FitResult;
    with ``allow_batch`` a batched model gives ``(batch_shape, [systems])``."""
    from ..estimation.results import FitResult
    from ..models import PolynomialModel

    model = linear.model if isinstance(linear, FitResult) else linear
    if isinstance(model, PolynomialModel):
        systems = model.to_control()
        if model.batch_shape == ():
            return systems
        if not allow_batch:
            raise InputValidationError(
                f"d2c: the model is batched {tuple(model.batch_shape)}; convert one member "
                "(model[i]) or use start_values, which takes a batch."
            )
        return tuple(model.batch_shape), systems
    if hasattr(linear, "dt") and hasattr(linear, "poles"):
        return linear
    raise InputValidationError(
        f"d2c: expected a python-control discrete system, a PolynomialModel or a FitResult, "
        f"got {type(linear).__name__}."
    )
