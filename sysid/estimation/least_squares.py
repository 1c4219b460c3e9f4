"""Direct (non-iterative) estimates for models linear in their parameters (the course notes
(Modelling and Simulation), §4.5, eq. 4.101 and 4.111-4.112).

* ``method="lls"`` (FIR, ARX): the prediction-error method is a linear least-squares problem,
  ``theta = argmin 1/2 ||M theta - y||^2`` with the regressor ``M`` of eq. 4.111 (eq. 4.112),
  solved by :func:`sysid.lls.lls` with covariance ``sigma^2 (M'M)^{-1}`` (eq. 4.101 form).
* ``method="iv"`` (ARX structure): instrumental variables. The instruments are the regressors
  built from the noise-free simulated output ``x = B/A u`` of a previous estimate instead of
  the measured ``y``, so they are uncorrelated with coloured equation errors; the estimate is
  consistent where least squares is biased (e.g. white output noise). Covariance
  ``sigma^2 (Z'M)^{-1} Z'Z (Z'M)^{-T}``.
"""

from __future__ import annotations

import warnings

import torch

from integrators.errors import SingularMatrixError

from ..data import IOData
from ..errors import PoorExcitationWarning
from ..lls import _condition_estimate, accurate_normal_equations, lls
from ..models import PolynomialModel
from ._data import _regression_rows, _with_outputs
from .results import FitResult


def _stable_denominator(b_parts: list[torch.Tensor], a: torch.Tensor, model, batch) -> torch.Tensor:
    """``a`` with roots outside the unit circle reflected inside (via an output-error model)."""
    na = a.shape[-1]
    if na == 0:
        return a
    oe = PolynomialModel(
        nb=[bp.shape[-1] for bp in b_parts],
        nf=[na] * len(b_parts),
        nk=model.nk,
        n_inputs=model.n_inputs,
        batch_shape=batch,
        dtype=a.dtype,
        device=a.device,
    )
    oe.set_parameter_vector(torch.cat([*b_parts, *([a] * len(b_parts))], dim=-1))
    oe.stabilize()
    return oe.parameter_vector()[..., -na:].detach()


def _instrumental_variables(aux: PolynomialModel, data: IOData, n_iter: int = 2):
    """ARX estimate by instrumental variables; returns ``(theta, Z, Phi, target)``.

    Start: least squares. Then ``n_iter`` times: simulate the noise-free output ``x = B/A u``
    of the current (stabilised) estimate, build the instruments ``Z`` = the ARX regressors with
    ``x`` in place of ``y``, and solve ``(Z'Phi) theta = Z' target``.
    """
    Phi, target = aux.regression(data)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", PoorExcitationWarning)
        theta = lls(Phi, target).theta
    if aux.na == 0:
        return theta, Phi, Phi, target
    batch = theta.shape[:-1]
    na = aux.na
    Z = Phi
    for _ in range(n_iter):
        b_parts = list(torch.split(theta[..., na:], aux.nb, dim=-1))
        a = _stable_denominator(b_parts, theta[..., :na], aux, batch)
        x = aux.simulate(data, theta=torch.cat([a, theta[..., na:]], dim=-1))
        Z, _ = aux.regression(_with_outputs(data, x))
        ZtPhi = Z.transpose(-1, -2) @ Phi
        sol, info = torch.linalg.solve_ex(ZtPhi, (Z.transpose(-1, -2) @ target.unsqueeze(-1)))
        if bool((info != 0).any()):
            idx = tuple(int(i) for i in torch.nonzero(info)[0])
            raise SingularMatrixError(
                f"instrumental variables: Z'Phi is singular at batch index {idx}; the input "
                "does not excite the model (or the orders are too high)."
            )
        theta = sol.squeeze(-1)
    return theta, Z, Phi, target


def _fit_lls(model, data, w, method) -> FitResult:
    """Least squares of eq. 4.112. Unweighted: the normal equations from the Gram matrix of
    :meth:`~sysid.models.PolynomialModel.normal_equations` (no regressor matrix) wherever
    :func:`~sysid.lls.accurate_normal_equations` finds them accurate (every data set's
    rounding-error bound ``eps cond <= 1e-10``); otherwise, and with weights, :func:`lls`
    (QR of the regressor of eq. 4.111)."""
    if w is None:
        G, M = model.normal_equations(data)
        p = G.shape[-1] - 1
        solved = accurate_normal_equations(G[..., :p, :p], G[..., :p, p]) if M > p else None
        if solved is not None:
            theta, normal_inverse, scaled_condition = solved
            residuals = model.regression_residuals(data, theta)
            rss = (residuals * residuals).sum(-1)
            sigma2 = rss / (M - p)
            covariance = sigma2[..., None, None] * normal_inverse
            info = {
                "condition_number": _condition_estimate(G[..., :p, :p], normal_inverse),
                "scaled_condition_number": scaled_condition(),
            }
            return _lls_result(theta, covariance, sigma2, residuals, 0.5 * rss, method, info)
    Phi, target = model.regression(data)
    W = None
    if w is not None:
        W = torch.cat([w[..., sl] for sl in _regression_rows(data, target.shape[-1])], dim=-1)
    res = lls(Phi, target, W=W)
    f = 0.5 * (res.residuals**2 * (1 if W is None else W)).sum(-1)
    info = {
        "condition_number": res.condition_number,
        "scaled_condition_number": res.scaled_condition_number,
    }
    return _lls_result(res.theta, res.covariance, res.sigma2, res.residuals, f, method, info)


def _lls_result(
    theta, covariance, sigma2, residuals, f, method, info=None, iterations=0
) -> FitResult:
    """The :class:`FitResult` of a closed-form least-squares solve (repeated ``iterations``
    times by instrumental variables): converged, loss ``f``, extra statistics ``info``."""
    batch = theta.shape[:-1]
    return FitResult(
        theta=theta,
        covariance=covariance,
        standard_errors=torch.diagonal(covariance, dim1=-2, dim2=-1).clamp_min(0).sqrt(),
        sigma2=sigma2,
        loss_history=f.unsqueeze(0),
        iterations=torch.full(batch, iterations, dtype=torch.int64, device=f.device),
        converged=torch.ones(batch, dtype=torch.bool, device=f.device),
        method=method,
        loss="gaussian",
        parameter_names=[],
        n_samples=residuals.shape[-1],
        residuals=residuals,
        info={} if info is None else info,
    )


def _fit_iv(model, data, iv_iterations) -> FitResult:
    theta, Z, Phi, target = _instrumental_variables(model, data, max(1, iv_iterations))
    r = target - (Phi @ theta.unsqueeze(-1)).squeeze(-1)
    M, p = Phi.shape[-2], Phi.shape[-1]
    sigma2 = (r * r).sum(-1) / (M - p)
    ZtPhi = Z.transpose(-1, -2) @ Phi
    # (Z'Phi)^{-1} Z'Z (Z'Phi)^{-T} by two solves
    left = torch.linalg.solve(ZtPhi, Z.transpose(-1, -2) @ Z)
    cov = sigma2[..., None, None] * torch.linalg.solve(ZtPhi, left.transpose(-1, -2))
    cov = 0.5 * (cov + cov.transpose(-1, -2))
    f = 0.5 * (r * r).sum(-1)
    return _lls_result(theta, cov, sigma2, r, f, "iv", iterations=max(1, iv_iterations))
