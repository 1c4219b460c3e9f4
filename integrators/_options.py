"""Entry checks of the options shared by ``odeint``, ``daeint`` and the solvers behind them.

Every option is checked before anything is integrated, with the same rule on every path the
option reaches, so a bad value fails at once with :class:`InputValidationError` instead of
surfacing later as a step-size failure, a raw torch error or a silently different run.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from .errors import InputValidationError

#: State dtypes the integrators compute in.
STATE_DTYPES = (torch.float32, torch.float64)
#: ``rtol`` must be at least this many machine epsilons of the state dtype. Measured on a
#: harmonic oscillator (amplitude 1 and 1e8 in float64, 1 and 1e4 in float32), dopri5 and Radau
#: IIA succeed down to rtol = eps with errors of a few eps relative, while at rtol = 1e-16
#: (0.45 eps, float64) Radau IIA ran out of max_steps: below eps the error estimates and the
#: Newton tolerance (:func:`integrators.implicit.newton_tolerance`) drown in rounding errors.
#: Four epsilons leave a margin and accept float32's usual rtol = 1e-6 (8.4 eps).
RTOL_MIN_EPS = 4.0
#: Names accepted by the implicit solvers' ``linear_solver`` option (``_irk_linalg``).
LINEAR_SOLVERS = ("auto", "transformed", "full")


def check_flag(value, name: str, *, allow: tuple = ()):
    """``value`` as a bool when it is one (Python or numpy), else the allowed non-bool value
    it equals (``None``, ``"auto"``); anything else (a string such as ``"no"``, which would
    count as true, or a number) raises."""
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    for option in allow:
        if value is option or (
            isinstance(option, str) and isinstance(value, str) and value == option
        ):
            return value
    accepted = ", ".join(["True", "False", *(repr(a) for a in allow)])
    raise InputValidationError(
        f"{name} must be one of {accepted}, got {value!r} of type {type(value).__name__}; "
        "pass a bool: strings and numbers are not read as one ('no' would count as true)."
    )


def check_int(value, name: str, minimum: int = 1) -> int:
    """An integer option (Python or numpy int, not a bool or a float) ``>= minimum``."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise InputValidationError(
            f"{name} must be an integer >= {minimum}, got {value!r} of type {type(value).__name__}."
        )
    if value < minimum:
        raise InputValidationError(f"{name} must be an integer >= {minimum}, got {value}.")
    return int(value)


def is_real_number(value) -> bool:
    """Whether ``value`` is a real Python or numpy number (not a bool)."""
    real = isinstance(value, (int, float, np.integer, np.floating))
    return real and not isinstance(value, (bool, np.bool_))


def check_positive(value, name: str, what: str = "") -> float:
    """A finite real number ``> 0`` (a Python/numpy number or a one-element tensor)."""
    return _check_number(value, name, what, strict=True)


def check_nonnegative(value, name: str, what: str = "") -> float:
    """A finite real number ``>= 0`` (a Python/numpy number or a one-element tensor)."""
    return _check_number(value, name, what, strict=False)


def _check_number(value, name: str, what: str, strict: bool) -> float:
    """``value`` as a float when it is a finite real number ``> 0`` (``strict``) or ``>= 0``;
    the message appends ``what`` to the bound."""
    if isinstance(value, torch.Tensor) and value.numel() == 1:
        value = value.detach().item()
    ok = is_real_number(value) and math.isfinite(value)
    if not ok or (value <= 0 if strict else value < 0):
        op = ">" if strict else ">="
        raise InputValidationError(f"{name} must be a finite number {op} 0{what}, got {value!r}.")
    return float(value)


def check_state_dtype(dtype, label: str = "x0") -> None:
    """Refuse state dtypes other than float32 and float64 (half precisions included)."""
    if dtype not in STATE_DTYPES:
        raise InputValidationError(
            f"{label} has dtype {dtype}; the integrators compute in torch.float32 or "
            "torch.float64 (their step-size control, Newton tolerances and linear algebra "
            f"need at least single precision): pass {label}.float() or {label}.double() and a "
            "model in that dtype."
        )


def min_rtol(dtype) -> float:
    """The smallest ``rtol`` accepted for states of ``dtype``: ``RTOL_MIN_EPS`` epsilons."""
    return RTOL_MIN_EPS * torch.finfo(dtype).eps


def check_tolerances(rtol, atol, dtype) -> None:
    """``rtol`` (number or tensor, every entry finite and ``>= min_rtol(dtype)``) and ``atol``
    (number or tensor, every entry finite and ``>= 0``)."""
    low = {}
    for name, value in (("rtol", rtol), ("atol", atol)):
        if isinstance(value, (bool, np.bool_)):
            values = None
        elif isinstance(value, torch.Tensor):
            values = value.detach().to(torch.float64).reshape(-1) if value.numel() else None
        else:
            try:
                values = torch.as_tensor(value, dtype=torch.float64).reshape(-1)
            except (TypeError, ValueError, RuntimeError):
                values = None
        if values is None or values.numel() == 0 or not bool(torch.isfinite(values).all()):
            raise InputValidationError(
                f"{name} must be a finite non-negative number or tensor, got {value!r}."
            )
        low[name] = float(values.min())
    if low["atol"] < 0:
        raise InputValidationError(f"atol must be >= 0, got a value {low['atol']:g}.")
    floor = min_rtol(dtype)
    if low["rtol"] < floor:
        raise InputValidationError(
            f"rtol = {low['rtol']:g} is below what {dtype} arithmetic can deliver: the "
            f"smallest sensible value is rtol = {floor:.2g} ({RTOL_MIN_EPS:g} machine epsilons; "
            "below it the error estimates and Newton tolerances drown in rounding errors). Use "
            f"rtol >= {floor:.2g}"
            + (", or float64 states for tighter tolerances." if dtype != torch.float64 else ".")
        )


def broadcast_tolerance(value, name: str, shape, like: torch.Tensor, hint: str = ""):
    """``value`` (``rtol`` or ``atol``, checked by :func:`check_tolerances`) as a float, or a
    tensor detached and broadcast to ``shape`` in ``like``'s dtype and device; a tensor that
    does not broadcast raises, naming both shapes, with ``hint`` appended."""
    if not isinstance(value, torch.Tensor):
        return float(value)
    try:
        return value.detach().to(dtype=like.dtype, device=like.device).expand(shape)
    except RuntimeError as exc:
        raise InputValidationError(
            f"{name} of shape {tuple(value.shape)} does not broadcast to {tuple(shape)}{hint}"
        ) from exc


def refuse_time_gradient(t, method: str) -> None:
    """Raise when the output times ``t`` require grad (and autograd is on): ``method`` does
    not differentiate with respect to them, and the gradient would silently be None."""
    if isinstance(t, torch.Tensor) and t.requires_grad and torch.is_grad_enabled():
        raise InputValidationError(
            f"gradients with respect to the output times t are not supported by {method!r} "
            "(they would silently be None): pass t.detach(). The derivative of the state at an "
            "output time t_k is f(t_k, x(t_k)); evaluate the model there if it is needed."
        )


def raise_shape_change(out, x: torch.Tensor, t, who: str = "", changed: bool = True) -> None:
    """Raise for a model output ``out`` whose shape is not that of the state ``x`` it was
    evaluated at, at time(s) ``t`` (a number or a tensor of per-sample or stage times);
    ``who`` prefixes the message, ``changed`` says the model returned the state's shape at
    t0. The solvers check this at every evaluation: broadcasting in the step sums would
    otherwise hide a model whose output changes shape during the run."""
    got = f"shape {tuple(out.shape)}" if isinstance(out, torch.Tensor) else type(out).__name__
    tt = torch.as_tensor(t).detach()
    lo, hi = float(tt.min()), float(tt.max())
    when = f"t = {lo:.6g}" + (f" .. {hi:.6g}" if hi > lo else "")
    since = " (it returned the state's shape at t0)" if changed else ""
    raise InputValidationError(
        f"{who}the model returned {got} for a state of shape {tuple(x.shape)} at {when}"
        f"{since}; it must return dx/dt as a tensor of the shape of x, (*batch, nx), at every "
        "call."
    )


def first_nonfinite(value: torch.Tensor) -> tuple[int, ...] | None:
    """Index of the first non-finite entry of ``value`` (row-major order), or None.

    One reduction when every entry is finite (a finite sum; an overflowing one falls through to
    the entry-wise test), the entry-wise search only on failure.
    """
    value = value.detach()
    if bool(torch.isfinite(value.sum())):
        return None
    bad = ~torch.isfinite(value)
    if not bool(bad.any()):
        return None
    return tuple(torch.nonzero(bad)[0].tolist())


def sample_indices(mask: torch.Tensor, limit: int) -> tuple[list[tuple[int, ...]], int]:
    """The first ``limit`` indices where ``mask`` (*batch,) holds, for messages, and how many
    there are in all; a 0-d mask (one unbatched sample) is sample ``(0,)``."""
    idx = torch.nonzero(mask.reshape(mask.shape or (1,)))
    return [tuple(i) for i in idx[:limit].tolist()], idx.shape[0]


def check_finite(
    value: torch.Tensor,
    label: str,
    time_dim: int | None = None,
    advice: str = "clean or interpolate the data before simulating",
) -> None:
    """Raise InputValidationError naming the first non-finite entry of ``value``.

    Args:
        value: tensor to check.
        label: name used in the message.
        time_dim: the dimension that is the time axis (named as "time index"), if any; the
            leading dimensions are then named as the sample index, the last as the channel.
        advice: what the user should do, ending the message.
    """
    first = first_nonfinite(value)
    if first is None:
        return
    where = f"at index {first}"
    if time_dim is not None and value.dim() >= 2:
        tdim = time_dim % value.dim()
        batch = first[:tdim]
        where = f"at time index {first[tdim]}" + (f", sample index {batch}" if batch else "")
        where += f", channel {first[-1]}" if tdim != value.dim() - 1 else ""
    raise InputValidationError(
        f"{label} contains a non-finite value ({value.detach()[first].item()}) {where}; {advice}."
    )


def check_state(
    x, label: str = "x0", *, dtype=None, device=None, min_width: int = 1
) -> torch.Tensor:
    """A state tensor ``(*batch, n)`` of real floating point, finite, ``n >= min_width``.

    Numbers and sequences become tensors of ``dtype`` (float64 when None) on ``device``;
    integer tensors are converted to float64. Complex and boolean values, dtypes other than
    float32 / float64 (:func:`check_state_dtype`), a scalar, a last dimension narrower than
    ``min_width`` and non-finite entries raise InputValidationError naming ``label``.
    """
    if not isinstance(x, torch.Tensor):
        try:
            x = torch.as_tensor(x, dtype=dtype or torch.float64, device=device)
        except (TypeError, ValueError, RuntimeError) as exc:
            raise InputValidationError(f"{label} is not numeric: {exc}") from exc
    if x.is_complex() or x.dtype == torch.bool:
        raise InputValidationError(f"{label} must be real floating point, got dtype {x.dtype}.")
    if not x.is_floating_point():
        x = x.to(torch.float64)
    check_state_dtype(x.dtype, label)
    if x.dim() == 0 or x.shape[-1] < min_width:
        width = f" with n >= {min_width}" if min_width else ""
        raise InputValidationError(
            f"{label} must have shape (*batch, n){width}, got shape {tuple(x.shape)}; for a "
            "scalar state use shape (1,) or (batch, 1)."
        )
    first = first_nonfinite(x)
    if first is not None:
        sample = first[:-1] if len(first) > 1 else "(unbatched)"
        raise InputValidationError(
            f"{label} contains a non-finite value at sample index {sample}, state {first[-1]}."
        )
    return x


def check_times(t, like: torch.Tensor, label: str = "t") -> torch.Tensor:
    """Output times: a finite, strictly increasing ``(T,)`` tensor, ``T >= 2``, in ``like``'s
    dtype and device (a tensor keeps its graph; :func:`refuse_time_gradient` decides whether
    that is allowed). Always a copy, so a solution keeps its times whatever the caller later
    does to the tensor or array passed. Messages name the times ``label``."""
    if isinstance(t, torch.Tensor):
        t = t.to(dtype=like.dtype, device=like.device, copy=True)
    else:
        try:
            t = torch.as_tensor(t, dtype=like.dtype, device=like.device).clone()
        except (TypeError, ValueError, RuntimeError) as exc:
            raise InputValidationError(f"{label} is not numeric: {exc}") from exc
    if t.dim() != 1 or t.shape[0] < 2:
        raise InputValidationError(
            f"{label} must be a 1-D tensor of T >= 2 output times, got shape {tuple(t.shape)}."
        )
    check_finite(t, label, advice="output times must be finite")
    steps = (t[1:] - t[:-1]).detach()
    if bool((steps <= 0).any()):
        k = int(torch.nonzero(steps <= 0)[0])
        raise InputValidationError(
            f"{label} must be strictly increasing, but t[{k + 1}] = {float(t[k + 1])} <= t[{k}] = "
            f"{float(t[k])}. To integrate backwards in time, substitute s = -t "
            "(x'(s) = -f(-s, x))."
        )
    return t
