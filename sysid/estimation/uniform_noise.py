"""Maximum-likelihood estimates of a linear-in-theta model with uniform noise (the course
notes (Modelling and Simulation), §4.3, eq. 4.43-4.45 and 4.58): the set of estimates is a
polytope, bounded per parameter by linear programs."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.optimize
import torch

from integrators.errors import InputValidationError

__all__ = ["UniformNoiseSet", "uniform_noise_mle_set"]


@dataclass
class UniformNoiseSet:
    """The maximum-likelihood set ``{theta : |y - A theta| <= a}`` (eq. 4.58) of a linear model.

    Attributes:
        A, y, a: the problem (``(*batch, M, p)``, ``(*batch, M)``, noise bound).
        lower, upper: per-parameter bounds of the polytope, ``(*batch, p)`` (``+-inf`` where
            unbounded, ``nan`` only for an empty set).
        feasible: whether the set is non-empty, ``(*batch,)`` bool (empty: every theta has
            likelihood 0, so every theta is an MLE, eq. 4.58 remark).
        center: Chebyshev centre (centre of the largest inscribed ball), ``(*batch, p)``.
        radius: radius of that ball, ``(*batch,)``.
    """

    A: torch.Tensor
    y: torch.Tensor
    a: float
    lower: torch.Tensor
    upper: torch.Tensor
    feasible: torch.Tensor
    center: torch.Tensor
    radius: torch.Tensor

    def contains(self, theta: torch.Tensor, tol: float = 1e-9) -> torch.Tensor:
        """Whether ``theta`` (``(*batch, p)``) lies in the set (``(*batch,)`` bool)."""
        theta = torch.as_tensor(theta, dtype=self.A.dtype, device=self.A.device)
        r = self.y - (self.A @ theta.unsqueeze(-1)).squeeze(-1)
        return (r.abs() <= self.a * (1 + tol) + tol).all(dim=-1)


def uniform_noise_mle_set(A: torch.Tensor, y: torch.Tensor, a: float) -> UniformNoiseSet:
    """Set of maximum-likelihood estimates for ``y = A theta + e``, ``e ~ U[-a, a]`` i.i.d.

    The likelihood (eq. 4.44–4.45, scaled to ``[-a, a]``) is ``(2a)^-M`` where every residual
    satisfies ``|y_k - A_k theta| <= a`` and 0 elsewhere, so its maximisers form the polytope
    ``{theta : -a <= y - A theta <= a}`` (eq. 4.58). Each bound ``min/max theta_j`` over the
    polytope is one linear program (scipy HiGHS); the Chebyshev centre is one more.

    Args:
        A: ``(*batch, M, p)`` regressors; y: ``(*batch, M)`` (batch shapes broadcast), both
            finite; a: noise half-width (a finite number > 0, or a one-element tensor).

    Returns:
        :class:`UniformNoiseSet`.
    """
    a_shape = tuple(torch.as_tensor(a).shape)
    if math.prod(a_shape) != 1:
        raise InputValidationError(f"the noise half-width a must be a number, got shape {a_shape}.")
    a = float(a)
    if not 0 < a < math.inf:
        raise InputValidationError(f"the noise half-width a must be finite and > 0, got {a}.")
    A = torch.as_tensor(A)
    y = torch.as_tensor(y, dtype=A.dtype, device=A.device)
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
    lower = np.full((len(An), p), np.nan)
    upper = np.full((len(An), p), np.nan)
    center = np.full((len(An), p), np.nan)
    radius = np.full(len(An), np.nan)
    feasible = np.zeros(len(An), dtype=bool)
    free = [(None, None)] * p
    for b in range(len(An)):  # one small LP per data set and bound (scipy has no batch)
        G = np.vstack([An[b], -An[b]])
        h = np.concatenate([yn[b] + a, a - yn[b]])
        norms = np.linalg.norm(G, axis=1, keepdims=True)
        cheb = scipy.optimize.linprog(
            np.r_[np.zeros(p), -1.0],
            A_ub=np.hstack([G, norms]),
            b_ub=h,
            bounds=free + [(0, None)],
            method="highs",
        )
        if cheb.status == 2:  # infeasible
            continue
        feasible[b] = True
        if cheb.status == 0:
            center[b], radius[b] = cheb.x[:p], cheb.x[p]
        else:
            radius[b] = np.inf
        for j in range(p):
            for sign, store in ((1.0, lower), (-1.0, upper)):
                c = np.zeros(p)
                c[j] = sign
                res = scipy.optimize.linprog(c, A_ub=G, b_ub=h, bounds=free, method="highs")
                if res.status == 3:
                    store[b, j] = -sign * np.inf
                else:
                    store[b, j] = res.x[j]
    to = dict(dtype=A.dtype, device=A.device)
    return UniformNoiseSet(
        A=A,
        y=y,
        a=a,
        lower=torch.as_tensor(lower, **to).reshape(*batch, p),
        upper=torch.as_tensor(upper, **to).reshape(*batch, p),
        feasible=torch.as_tensor(feasible, device=A.device).reshape(batch),
        center=torch.as_tensor(center, **to).reshape(*batch, p),
        radius=torch.as_tensor(radius, **to).reshape(batch),
    )
