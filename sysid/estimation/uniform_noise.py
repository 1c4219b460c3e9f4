"""Maximum-likelihood estimates of a linear-in-theta model with uniform noise (the course
notes (Modelling and Simulation), §4.3, eq. 4.43-4.45 and 4.58): the set of estimates is a
polytope, bounded per parameter by linear programs."""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import numpy as np
import scipy.optimize
import torch

from integrators.errors import InputValidationError

from ..errors import ConvergenceWarning

__all__ = ["UniformNoiseSet", "uniform_noise_mle_set"]


@dataclass
class UniformNoiseSet:
    """The maximum-likelihood set ``{theta : |y - A theta| <= a}`` (eq. 4.58) of a linear model.

    Attributes:
        A, y, a: the problem (``(*batch, M, p)``, ``(*batch, M)``, noise bound).
        lower, upper: per-parameter bounds of the polytope, ``(*batch, p)`` (``+-inf`` where
            unbounded, ``nan`` for an empty set or an unsolved data set).
        feasible: whether the set is non-empty, ``(*batch,)`` bool (empty: every theta has
            likelihood 0, so every theta is an MLE, eq. 4.58 remark; False also where not
            ``solved``).
        center: Chebyshev centre (centre of the largest inscribed ball), ``(*batch, p)``.
        radius: radius of that ball, ``(*batch,)``.
        solved: whether every linear program of the data set ended with an answer (optimal,
            infeasible or unbounded), ``(*batch,)`` bool; where not, its bounds, centre and
            radius are ``nan`` and ``message`` says why.
        message: ``""`` when every data set is solved, else the unsolved data sets and the
            solver's message.
    """

    A: torch.Tensor
    y: torch.Tensor
    a: float
    lower: torch.Tensor
    upper: torch.Tensor
    feasible: torch.Tensor
    center: torch.Tensor
    radius: torch.Tensor
    solved: torch.Tensor
    message: str = ""

    def contains(self, theta: torch.Tensor, tol: float = 1e-9) -> torch.Tensor:
        """Whether ``theta`` (``(*batch, p)``) lies in the set, every residual within
        ``a (1 + tol)`` (``(*batch,)`` bool)."""
        theta = torch.as_tensor(theta, dtype=self.A.dtype, device=self.A.device)
        r = self.y - (self.A @ theta.unsqueeze(-1)).squeeze(-1)
        return (r.abs() <= self.a * (1 + tol)).all(dim=-1)


def _linprog(c, G, h, bounds):
    return scipy.optimize.linprog(c, A_ub=G, b_ub=h, bounds=bounds, method="highs")


def _polytope(A: np.ndarray, y: np.ndarray, a: float):
    """``(feasible, lower, upper, center, radius, failure)`` of the set
    ``{theta : |y - A theta| <= a}`` of one data set (A (M, p), y (M,)): bounds and centre
    (p,), radius a float, ``failure`` the solver's message where a program ended without an
    answer (then everything else is NaN and ``feasible`` False), else None.

    The programs are posed in units of the set: about the least-squares estimate ``theta0``
    (residuals ``r0`` of the order of ``a``), constraints divided by ``a``, and parameter
    ``j`` in units of ``a / d_j`` (``d_j`` the RMS of column ``j``; one common ``d`` for the
    Chebyshev ball, whose radius is Euclidean): the solver's absolute tolerances then mean
    the same whatever the units of the data.
    """
    p = A.shape[1]
    theta0 = np.linalg.lstsq(A, y, rcond=None)[0]
    r0 = (y - A @ theta0) / a
    h = np.concatenate([1.0 + r0, 1.0 - r0])  # G delta / a <= h, delta = theta - theta0
    col = np.sqrt((A**2).mean(axis=0))
    d = np.where(col > 0, col, 1.0)  # a zero column: an unbounded parameter, any unit
    d_ball = float(np.sqrt((col**2).mean())) or 1.0
    free = [(None, None)] * p
    G_ball = np.vstack([A, -A]) / d_ball
    cheb = _linprog(
        np.r_[np.zeros(p), -1.0],
        np.hstack([G_ball, np.linalg.norm(G_ball, axis=1, keepdims=True)]),
        h,
        free + [(0, None)],
    )
    nan = np.full(p, np.nan)
    if cheb.status == 2:  # infeasible: an empty set
        return False, nan, nan, nan, np.nan, None
    if cheb.status not in (0, 3):
        return False, nan, nan, nan, np.nan, cheb.message
    if cheb.status == 0:
        center, radius = theta0 + a * cheb.x[:p] / d_ball, a * cheb.x[p] / d_ball
    else:
        center, radius = nan, np.inf
    G = np.vstack([A, -A]) / d
    lower, upper = np.empty(p), np.empty(p)
    for j in range(p):
        for sign, store in ((1.0, lower), (-1.0, upper)):
            res = _linprog(sign * np.eye(p)[j], G, h, free)
            if res.status == 3:
                store[j] = -sign * np.inf
            elif res.status == 0:
                store[j] = theta0[j] + a * res.x[j] / d[j]
            else:
                return False, nan, nan, nan, np.nan, res.message
    return True, lower, upper, center, radius, None


def uniform_noise_mle_set(A: torch.Tensor, y: torch.Tensor, a: float) -> UniformNoiseSet:
    """Set of maximum-likelihood estimates for ``y = A theta + e``, ``e ~ U[-a, a]`` i.i.d.

    The likelihood (eq. 4.44–4.45, scaled to ``[-a, a]``) is ``(2a)^-M`` where every residual
    satisfies ``|y_k - A_k theta| <= a`` and 0 elsewhere, so its maximisers form the polytope
    ``{theta : -a <= y - A theta <= a}`` (eq. 4.58). Each bound ``min/max theta_j`` over the
    polytope is one linear program (scipy HiGHS); the Chebyshev centre is one more. The
    programs are scaled to the set (see :func:`_polytope`), so the answer scales with the
    data: ``A, c y, c a`` gives ``c`` times the set of ``A, y, a``.

    Args:
        A: ``(*batch, M, p)`` regressors; y: ``(*batch, M)`` (batch shapes broadcast), both
            finite real; a: noise half-width (a finite number > 0, or a one-element tensor).

    Returns:
        :class:`UniformNoiseSet` in the promoted dtype of ``A`` and ``y`` (float64 where both
        are integer). A data set whose linear programs fail is ``nan`` with
        ``solved`` False, named in ``message`` and in a :class:`ConvergenceWarning`.
    """
    a_shape = tuple(torch.as_tensor(a).shape)
    if math.prod(a_shape) != 1:
        raise InputValidationError(f"the noise half-width a must be a number, got shape {a_shape}.")
    a = float(a)
    if not 0 < a < math.inf:
        raise InputValidationError(f"the noise half-width a must be finite and > 0, got {a}.")
    A, y = torch.as_tensor(A), torch.as_tensor(y)
    dtype = torch.promote_types(A.dtype, y.dtype)
    if not dtype.is_floating_point:
        dtype = torch.float64
    A, y = A.to(dtype), y.to(dtype=dtype, device=A.device)
    if A.dim() < 2 or y.dim() < 1 or y.shape[-1] != A.shape[-2]:
        raise InputValidationError(
            f"A must be (*batch, M, p) and y (*batch, M); got {tuple(A.shape)}, {tuple(y.shape)}."
        )
    try:
        batch = torch.broadcast_shapes(A.shape[:-2], y.shape[:-1])
    except RuntimeError:
        raise InputValidationError(
            f"the batch shapes of A {tuple(A.shape)} and y {tuple(y.shape)} do not broadcast: "
            "give A (*batch, M, p) and y (*batch, M) with matching (or size-1) batch dimensions."
        ) from None
    if not (bool(torch.isfinite(A).all()) and bool(torch.isfinite(y).all())):
        raise InputValidationError(
            "A and y must be finite (a NaN or inf has no residual bound); remove or "
            "interpolate the non-finite samples."
        )
    M, p = A.shape[-2:]
    An = A.expand(*batch, M, p).detach().cpu().double().numpy().reshape(-1, M, p)
    yn = y.expand(*batch, M).detach().cpu().double().numpy().reshape(-1, M)
    # one small set of LPs per data set (scipy has no batch)
    sets = [_polytope(An[b], yn[b], a) for b in range(len(An))]
    failed = [(b, s[-1]) for b, s in enumerate(sets) if s[-1] is not None]
    message = ""
    if failed:
        message = (
            f"uniform_noise_mle_set: the linear programs of data sets {[b for b, _ in failed][:5]} "
            f"failed ({failed[0][1]}); their bounds, centres and radii are nan."
        )
        warnings.warn(message, ConvergenceWarning, stacklevel=2)
    feasible, lower, upper, center, radius, _ = zip(*sets, strict=True)
    to = dict(dtype=dtype, device=A.device)
    return UniformNoiseSet(
        A=A,
        y=y,
        a=a,
        lower=torch.as_tensor(np.array(lower), **to).reshape(*batch, p),
        upper=torch.as_tensor(np.array(upper), **to).reshape(*batch, p),
        feasible=torch.as_tensor(feasible, device=A.device).reshape(batch),
        center=torch.as_tensor(np.array(center), **to).reshape(*batch, p),
        radius=torch.as_tensor(np.array(radius), **to).reshape(batch),
        solved=torch.tensor([s[-1] is None for s in sets], device=A.device).reshape(batch),
        message=message,
    )
