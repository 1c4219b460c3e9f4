"""Direct (non-iterative) estimates for models linear in their parameters (the course notes
(Modelling and Simulation), §4.5, eq. 4.101 and 4.111-4.112).

* ``method="lls"`` (FIR, ARX): the prediction-error method is a linear least-squares problem,
  ``theta = argmin 1/2 ||M theta - y||^2`` with the regressor ``M`` of eq. 4.111 (eq. 4.112),
  solved by :func:`sysid.lls.lls` with covariance ``sigma^2 (M'M)^{-1}`` (eq. 4.101 form).
  Where a data set's regressors are linearly dependent (``M'M`` numerically singular, e.g. a
  zero input) its estimate is the least-squares solution of minimum norm in the column-scaled
  parameters and the parameters the data do not determine get an infinite covariance, as in
  the iterative fits (:func:`~sysid.estimation.results.inverse_normal_matrix_and_rank`), with a
  :class:`PoorExcitationWarning` naming the data sets; the others are as if fitted alone.
* ``method="iv"`` (ARX structure): instrumental variables. The instruments are the regressors
  built from the noise-free simulated output ``x = B/A u`` of a previous estimate instead of
  the measured ``y``, so they are uncorrelated with coloured equation errors; the estimate is
  consistent where least squares is biased (e.g. white output noise). Covariance
  ``sigma^2 (Z'M)^{-1} Z'Z (Z'M)^{-T}``. A data set whose ``Z'M`` is singular has no IV
  estimate: NaN, not converged, ``info["singular"]`` and a message in the result.
"""

from __future__ import annotations

import math
import warnings

import torch

from ..data import IOData
from ..errors import PoorExcitationWarning
from ..lls import _condition_estimate, _fill_members, accurate_normal_equations, lls
from ..models import PolynomialModel
from ._data import _regression_rows, _with_outputs
from .results import FitResult, inverse_normal_matrix_and_rank


def _least_squares(Phi: torch.Tensor, target: torch.Tensor, W: torch.Tensor | None = None):
    """:func:`~sysid.lls.lls` of ``(Phi, target)`` (diagonal weights ``W``), batched over data
    sets; where a data set's ``Phi'W Phi`` is numerically singular (:func:`~sysid.lls.lls`'s
    test), its least-squares solution of minimum norm in the column-scaled parameters.

    That solution comes from the pseudo-inverse of the column-scaled
    ``W^{1/2} Phi`` with the null space of :func:`inverse_normal_matrix_and_rank` (scaled
    eigenvalues below ``eps M`` times the largest), whose covariance is ``inf`` for the
    parameters with a component along it; ``sigma^2 = r'Wr / (M - rank)``. Warns
    (:class:`PoorExcitationWarning`) naming those data sets.

    Returns ``theta, covariance, sigma2, residuals`` (the singular data sets' entries
    replaced) and the :class:`~sysid.lls.LLSResult`.
    """
    res = lls(Phi, target, W=W, singular="nan")
    theta, cov, sigma2, residuals = res.theta, res.covariance, res.sigma2, res.residuals
    bad = res.singular
    if bool(bad.any()):
        batch, (M, p) = bad.shape, Phi.shape[-2:]
        A = Phi.expand(*batch, M, p)[bad]
        y = target.expand(*batch, M)[bad]
        sw = torch.ones_like(y) if W is None else W.expand(*batch, M)[bad].sqrt()
        Aw = A * sw.unsqueeze(-1)
        scale = torch.linalg.vector_norm(Aw, dim=-2)
        scale = torch.where(scale == 0, 1.0, scale)
        rtol = (torch.finfo(A.dtype).eps * M) ** 0.5  # singular values: sqrt of eigenvalues
        pinv = torch.linalg.pinv(Aw / scale.unsqueeze(-2), rtol=rtol)
        th = (pinv @ (y * sw).unsqueeze(-1)).squeeze(-1) / scale
        with warnings.catch_warnings():  # warned below, with the data sets' batch indices
            warnings.simplefilter("ignore", PoorExcitationWarning)
            P, rank = inverse_normal_matrix_and_rank(Aw)
        r = y - (A @ th.unsqueeze(-1)).squeeze(-1)
        s2 = ((r * sw) ** 2).sum(-1) / (M - rank).to(A.dtype)
        theta, sigma2, residuals = theta.clone(), sigma2.clone(), residuals.clone()
        cov = cov.clone()
        theta[bad], cov[bad], sigma2[bad], residuals[bad] = th, s2[:, None, None] * P, s2, r
        where = [tuple(int(i) for i in row) for row in torch.nonzero(bad).tolist()]
        shown = ", ".join(str(i) for i in where[:5]) + (" ..." if len(where) > 5 else "")
        warnings.warn(
            f"least squares: the regressors are linearly dependent for {len(where)} of "
            f"{bad.numel()} data sets (batch index {shown}): the input does not excite the "
            "model (e.g. a constant or zero input) or the orders are too high for the data. "
            "Their estimate is the minimum-norm least-squares solution; the parameters the "
            "data do not determine have an infinite covariance. Use a persistently exciting "
            "input or lower the orders.",
            PoorExcitationWarning,
            stacklevel=4,
        )
    return theta, cov, sigma2, residuals, res


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
        theta = _least_squares(Phi, target)[0]
    singular = torch.zeros(theta.shape[:-1], dtype=torch.bool, device=theta.device)
    if aux.na == 0:
        return theta, Phi, Phi, target, singular
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
        singular = info != 0
        # a singular Z'Phi keeps the member's previous estimate for the next refinement
        theta = torch.where(singular.unsqueeze(-1), theta, sol.squeeze(-1))
    return theta, Z, Phi, target, singular


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
    theta, covariance, sigma2, residuals, res = _least_squares(Phi, target, W)
    f = 0.5 * (residuals**2 * (1 if W is None else W)).sum(-1)
    info = {
        "condition_number": res.condition_number,
        "scaled_condition_number": res.scaled_condition_number,
    }
    return _lls_result(theta, covariance, sigma2, residuals, f, method, info)


def _lls_result(
    theta, covariance, sigma2, residuals, f, method, info=None, iterations=0, singular=None
) -> FitResult:
    """The :class:`FitResult` of a closed-form least-squares solve (repeated ``iterations``
    times by instrumental variables): loss ``f``, extra statistics ``info``; converged except
    where ``singular`` (``(*batch,)`` bool or None), which is ``info["singular"]``."""
    batch = theta.shape[:-1]
    if singular is None:
        singular = torch.zeros(batch, dtype=torch.bool, device=f.device)
    info = {} if info is None else info
    info["singular"] = singular
    return FitResult(
        theta=theta,
        covariance=covariance,
        standard_errors=torch.diagonal(covariance, dim1=-2, dim2=-1).clamp_min(0).sqrt(),
        sigma2=sigma2,
        loss_history=f.unsqueeze(0),
        iterations=torch.full(batch, iterations, dtype=torch.int64, device=f.device),
        converged=~singular,
        method=method,
        loss="gaussian",
        parameter_names=[],
        n_samples=residuals.shape[-1],
        residuals=residuals,
        info=info,
    )


def _fit_iv(model, data, iv_iterations) -> FitResult:
    theta, Z, Phi, target, singular = _instrumental_variables(model, data, max(1, iv_iterations))
    theta = _fill_members(singular, math.nan, theta)
    r = target - (Phi @ theta.unsqueeze(-1)).squeeze(-1)
    M, p = Phi.shape[-2], Phi.shape[-1]
    sigma2 = (r * r).sum(-1) / (M - p)
    ZtPhi = Z.transpose(-1, -2) @ Phi
    eye = torch.eye(p, dtype=ZtPhi.dtype, device=ZtPhi.device)
    ZtPhi = torch.where(singular[..., None, None], eye, ZtPhi)  # their covariance is NaN
    # (Z'Phi)^{-1} Z'Z (Z'Phi)^{-T} by two solves
    left = torch.linalg.solve(ZtPhi, Z.transpose(-1, -2) @ Z)
    cov = sigma2[..., None, None] * torch.linalg.solve(ZtPhi, left.transpose(-1, -2))
    cov = 0.5 * (cov + cov.transpose(-1, -2))
    f = 0.5 * (r * r).sum(-1)
    return _lls_result(
        theta, cov, sigma2, r, f, "iv", iterations=max(1, iv_iterations), singular=singular
    )
