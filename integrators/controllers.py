"""Step-size control for embedded Runge-Kutta pairs (notes §6.5), batched per sample.

The solver measures each trial step with the weighted RMS norm of the local error estimate
``err = x_{k+1} - xhat_{k+1} = dt sum_i (b_i - bhat_i) K_i`` (notes eq. 6.44a-b)::

    ||err|| = sqrt(mean_j (err_j / (atol + rtol max(|x_k,j|, |x_{k+1},j|)))^2),

one number per sample. A step is accepted when ``||err|| <= 1``. The controllers below map
that norm (and the norm of the previous accepted step) to a new step size with
``dt_new = dt * factor``, where for an error estimator of order ``q`` the local error
behaves like ``C dt^(q+1)``, so ``factor = ||err||^(-1/(q+1))`` would hit the tolerance
exactly. Every function works on (B,) tensors: each sample has its own error, decision and
step size. They are meant to be called on detached values (step-size decisions are not
differentiated).
"""

from __future__ import annotations

import math

import numpy as np
import torch

from ._per_sample import ArrayOps, ScalarOps
from .errors import InputValidationError

_TINY_ERR = 1e-10  # error norms below this are treated as this (factor capped anyway)
#: Newton contraction rate above which (after more than two iterations) an implicit step
#: re-evaluates the Jacobian (scipy's rule).
REUSE_THETA = 1e-3


def error_norm(err, x_old, x_new, rtol, atol) -> torch.Tensor:
    """Hairer's weighted RMS norm of a local error estimate, per sample.

    Args:
        err: (B, n) local error estimates.
        x_old, x_new: (B, n) states at the start and the end of the step.
        rtol, atol: floats or tensors broadcastable to (B, n).

    Returns:
        (B,) norms; inf/nan entries flag non-finite trials.
    """
    scale = atol + rtol * torch.maximum(x_old.abs(), x_new.abs())
    return torch.linalg.vector_norm(err / scale, dim=-1) / math.sqrt(err.shape[-1])


def _number(value, name: str) -> float:
    """A finite real number (not a bool or a string) as a float."""
    real = isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(
        value, (bool, np.bool_)
    )
    if not real or not math.isfinite(value):
        raise InputValidationError(f"{name} must be a finite number, got {value!r}.")
    return float(value)


def _check_factors(safety, min_factor, max_factor) -> tuple[float, float, float]:
    """The factors as floats, checked: 0 < safety <= 1 and 0 < min_factor < 1 < max_factor."""
    safety, min_factor, max_factor = (
        _number(v, n)
        for v, n in ((safety, "safety"), (min_factor, "min_factor"), (max_factor, "max_factor"))
    )
    if not 0.0 < safety <= 1.0:
        raise InputValidationError(f"safety must lie in (0, 1], got {safety}.")
    if not 0.0 < min_factor < 1.0 < max_factor:
        raise InputValidationError(
            f"need 0 < min_factor < 1 < max_factor, got min_factor={min_factor}, "
            f"max_factor={max_factor}."
        )
    return safety, min_factor, max_factor


class IController:
    """Integral (elementary) controller: ``factor = safety * ||err||^(-1/(q+1))``.

    Args:
        safety: fraction of the optimal factor actually used (0.9: aim a bit below tolerance).
        min_factor, max_factor: bounds on ``dt_new / dt``. After a rejection the step may not
            grow (Hairer, Nørsett & Wanner, §II.4), so the bound is 1 there.
    """

    def __init__(self, safety: float = 0.9, min_factor: float = 0.2, max_factor: float = 10.0):
        self.safety, self.min_factor, self.max_factor = _check_factors(
            safety, min_factor, max_factor
        )

    def _grow_factor(self, err, err_prev, shrink, k) -> torch.Tensor:
        """The factor after an accepted step (the I controller reuses ``shrink``)."""
        return shrink

    def propose(self, err_norm, err_prev, dt, order, after_reject=None):
        """Decide acceptance and the next step size for every sample.

        Args:
            err_norm: (B,) error norm of the trial step (:func:`error_norm`); inf/nan
                (a non-finite trial) means reject and shrink by ``min_factor``.
            err_prev: (B,) error norm of the last accepted step (1.0 before the first).
            dt: (B,) size of the trial step.
            order: order ``q`` of the error estimator (the lower order of the pair, 4 for
                Dormand-Prince 5(4)); the exponents use ``k = q + 1``.
            after_reject: optional (B,) bool, True where the previous trial was rejected
                (the factor is then capped at 1).

        Returns:
            (accept (B,) bool, dt_new (B,)): ``dt_new`` is the next trial step, whether this
            one is accepted (advance, then try ``dt_new``) or rejected (retry with it).
        """
        k = float(order) + 1.0
        # non-finite norms become +inf (maximal shrink), tiny ones a floor (no 0^-a)
        err = torch.nan_to_num(err_norm, nan=math.inf, posinf=math.inf).clamp_min(_TINY_ERR)
        accept = err <= 1.0
        shrink = self.safety * err.pow(-1.0 / k)
        factor = torch.where(accept, self._grow_factor(err, err_prev, shrink, k), shrink)
        if after_reject is None:
            factor = factor.clamp(self.min_factor, self.max_factor)
        else:
            factor = torch.where(
                after_reject, factor.clamp_max(1.0), factor.clamp_max(self.max_factor)
            ).clamp_min(self.min_factor)
        return accept, dt * factor

    def radau_step_sizes(self, h, err, finite, err_old, h_old, first, iters, theta, max_iter, expo):
        """The next step sizes of adaptive Radau IIA (the torch driver of
        :mod:`integrators.radau`) from this controller, on host arrays (*batch,): the
        arguments and results of :meth:`GustafssonController.radau_step_sizes`. The error
        estimator of Radau IIA with ``s`` stages has order ``q = s = 1 / expo - 1``;
        ``err_old`` is the previous accepted step's error. The step after acceptance and the
        retry after rejection are both :meth:`propose`'s step (a non-finite trial shrinks by
        ``min_factor``); the Newton matrix is refactorised whenever the step changes."""
        err_c = np.maximum(err, _TINY_ERR)
        _, h_new = self.propose(
            torch.from_numpy(np.where(finite, err, np.inf)),
            torch.from_numpy(np.asarray(err_old, dtype=np.float64)),
            torch.from_numpy(np.asarray(h, dtype=np.float64)),
            round(1.0 / expo) - 1,
        )
        h_new = h_new.numpy()
        return err_c, h_new, h_new, slow_contraction(theta, iters)

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(safety={self.safety}, min_factor={self.min_factor}, "
            f"max_factor={self.max_factor})"
        )


class PIController(IController):
    """Proportional-integral controller (Gustafsson 1991; Söderlind's notation).

    After an accepted step,
    ``factor = safety * ||err_n||^(-beta1/k) * ||err_{n-1}||^(-beta2/k)``, ``k = q + 1``,
    where ``err_{n-1}`` is the norm of the previous accepted step. ``beta1 = 1, beta2 = 0`` is
    the I controller. The defaults ``beta1 = 0.85, beta2 = -0.2`` are the usual gains for
    order-5 pairs (Hairer's DOPRI5 with his ``beta = 0.04``: exponents 0.17 and 0.04 for
    k = 5); Gustafsson's ``beta1 = 0.7, beta2 = -0.4`` damps the step-size oscillation more
    strongly where stability rather than accuracy limits the step, at a few more steps. A
    rejected step falls back to the I formula (the history says nothing about the failed
    step).
    """

    def __init__(
        self,
        beta1: float = 0.85,
        beta2: float = -0.2,
        safety: float = 0.9,
        min_factor: float = 0.2,
        max_factor: float = 10.0,
    ):
        super().__init__(safety, min_factor, max_factor)
        beta1, beta2 = _number(beta1, "beta1"), _number(beta2, "beta2")
        if beta1 <= 0.0:
            raise InputValidationError(f"beta1 must be positive, got {beta1}.")
        self.beta1, self.beta2 = beta1, beta2

    def _grow_factor(self, err, err_prev, shrink, k) -> torch.Tensor:
        prev = err_prev.clamp_min(_TINY_ERR)
        return self.safety * err.pow(-self.beta1 / k) * prev.pow(-self.beta2 / k)

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(beta1={self.beta1}, beta2={self.beta2}, safety={self.safety}, "
            f"min_factor={self.min_factor}, max_factor={self.max_factor})"
        )


def slow_contraction(theta, iters):
    """Whether a Newton solve contracted so slowly (rate ``theta > REUSE_THETA`` after more
    than two iterations) that the Jacobian must be re-evaluated; arrays or Python numbers."""
    return (theta > REUSE_THETA) & (iters > 2)


class GustafssonController:
    """Gustafsson's predictive controller of adaptive Radau IIA (Hairer & Wanner, §IV.8;
    scipy's and RADAU5's rule), the default of the implicit adaptive methods.

    With ``k`` the Newton iterations of the step (``k_max`` allowed) and ``q = s`` the order
    of the error estimate,
    ``h_new = h * min(max_factor, safety * min(1, pred) * err^(-1/(q+1)))`` where
    ``safety = 0.9 (2 k_max + 1) / (2 k_max + k)`` and the predictive factor
    ``pred = (h / h_old) (err_old / err)^(1/(q+1))`` uses the previous accepted step. A
    rejected step shrinks by at least ``min_factor`` (by 4 where not finite); the
    factorisation of the Newton matrix is kept (``h_new = h``) when the step would grow by
    less than 20 % and Newton contracted fast.

    Args:
        min_factor, max_factor: bounds on ``h_new / h`` after a rejection / an acceptance.
    """

    def __init__(self, min_factor: float = 0.2, max_factor: float = 10.0):
        _, self.min_factor, self.max_factor = _check_factors(1.0, min_factor, max_factor)

    def radau_step_sizes(self, h, err, finite, err_old, h_old, first, iters, theta, max_iter, expo):
        """The rule above, per sample: on host arrays (*batch,), or on Python floats and bools
        for one trajectory (the representations of :mod:`integrators._per_sample`; the same
        results up to the rounding of ``**``).

        Args:
            h: float64 step just attempted; err: its scaled error norm (inf where not finite);
            finite: whether the step's state and error are finite; err_old, h_old: error (floored
            at 1e-2) and size of the sample's last accepted step (h_old <= 0: none yet); first:
            no step accepted yet; iters, theta: Newton iterations and contraction rate;
            max_iter: Newton iteration limit; expo: ``1 / (s + 1)``.

        Returns:
            ``(err_c, h_accept, h_reject, slow)``: the error floored at 1e-10, the next step after
            acceptance (``h`` itself when the factorisation is kept: growth in [1, 1.2) and fast
            Newton), the retry step after rejection (``h / 4`` where non-finite) and whether
            Newton contracted so slowly that the Jacobian must be re-evaluated.
        """
        ops = ScalarOps if isinstance(h, float) else ArrayOps
        where, minimum, maximum = ops.where, ops.minimum, ops.maximum
        with ops.errstate():
            safety = 0.9 * (2 * max_iter + 1) / (2 * max_iter + iters)
            err_c = maximum(err, 1e-10)
            pred = h / maximum(h_old, 1e-300) * (err_old / err_c) ** expo
            pred = where(first | (h_old <= 0), 1.0, minimum(pred, 1.0))
            scaled = safety * pred * err_c**-expo
            h_rej = where(finite, h * minimum(maximum(scaled, self.min_factor), 1.0), 0.25 * h)
            grow = minimum(scaled, self.max_factor)
        slow = slow_contraction(theta, iters)
        keep_lu = ops.not_(slow) & (grow < 1.2) & (grow >= 1.0)
        return err_c, where(keep_lu, h, h * grow), h_rej, slow

    def __repr__(self) -> str:
        return f"{type(self).__name__}(min_factor={self.min_factor}, max_factor={self.max_factor})"


def check_controller(controller, method: str, adaptive: bool) -> None:
    """Refuse a ``controller`` that is not a controller object of this module, or one given
    to a run at fixed steps (``adaptive`` False) of ``method``."""
    if controller is None:
        return
    if not isinstance(controller, IController | GustafssonController):
        raise InputValidationError(
            f"controller must be an IController, PIController or GustafssonController "
            f"(integrators.controllers), got {type(controller).__name__}."
        )
    if not adaptive:
        raise InputValidationError(
            f"controller applies to adaptive methods only; {method!r} runs at fixed steps "
            "here (set their number per output interval with substeps)."
        )


@torch.no_grad()
def initial_step(rhs, t0, x0, f0, order, rtol, atol, span) -> torch.Tensor:
    """Per-sample starting step (Hairer, Nørsett & Wanner, §II.4, algorithm of ``hinit``).

    With ``sc = atol + rtol |x0|`` and RMS norms ``d0 = ||x0/sc||``, ``d1 = ||f0/sc||``:
    a probe step ``h0 = 0.01 d0/d1`` (1e-6 when either is tiny) gives one explicit Euler
    point ``x1 = x0 + h0 f0``; with ``d2 = ||(f(t0 + h0, x1) - f0)/sc|| / h0`` the step
    ``h1 = (0.01 / max(d1, d2))^(1/(q+1))`` makes the leading error term about 1 % of the
    tolerance. The result is ``min(100 h0, h1, span)``.

    Args:
        rhs: ``rhs(t, x)`` on (*batch,) times and (*batch, n) states (one batched call here),
            or None: no probe, the result is ``min(h0, span)`` (DAEs: an Euler probe of the
            differential states alone would leave the algebraic constraints).
        t0: (*batch,) or scalar start times.  x0, f0: (*batch, n) state and derivative at
            ``t0``.
        order: order ``q`` of the error estimator.
        rtol, atol: tolerances broadcastable to (*batch, n).
        span: (*batch,) or float, length of the integration interval (an upper bound).

    Returns:
        (*batch,) positive step sizes.
    """
    n = x0.shape[-1]
    scale = atol + rtol * x0.abs()

    def rms(v):
        return torch.linalg.vector_norm(v / scale, dim=-1) / math.sqrt(n)

    d0, d1 = rms(x0), rms(f0)
    small = (d0 < 1e-5) | (d1 < 1e-5)
    h0 = torch.where(small, torch.full_like(d0, 1e-6), 0.01 * d0 / torch.where(small, 1.0, d1))
    h0 = torch.minimum(h0, torch.as_tensor(span, dtype=h0.dtype, device=h0.device))
    if rhs is None:
        return h0
    f1 = rhs(t0 + h0, x0 + h0[..., None] * f0)
    d2 = rms(f1 - f0) / h0
    dmax = torch.maximum(d1, d2)
    flat = dmax <= 1e-15
    h1 = torch.where(
        flat,
        torch.clamp_min(h0 * 1e-3, 1e-6),
        (0.01 / torch.where(flat, 1.0, dmax)).pow(1.0 / (order + 1.0)),
    )
    h = torch.minimum(100.0 * h0, h1)
    h = torch.where(torch.isfinite(h) & (h > 0), h, h0)
    return torch.minimum(h, torch.as_tensor(span, dtype=h.dtype, device=h.device))
