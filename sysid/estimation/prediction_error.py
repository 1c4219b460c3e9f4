"""Prediction-error and maximum-likelihood estimates by Levenberg–Marquardt (the course notes
(Modelling and Simulation), §3.6 and §4.6).

``method="gauss_newton"``: Levenberg–Marquardt (Gauss–Newton with the regularisation
``alpha I`` of eq. 3.61 and an Armijo line search, :func:`integrators.newton.minimize` with
``method="levenberg_marquardt"``) on the prediction errors (eq. 4.130–4.132; for OE these are
the simulation errors, eq. 4.133). Jacobians by forward-mode autograd, all parameter directions
in one pass (by filtering for models without noise model, :class:`_OutputError`);
per-data-set damping, step acceptance and convergence. The iteration evaluates only the data
sets still iterating (``minimize(compact=True)``: the criterion takes ``members``), so a batch
costs the work of its slowest fits, not the batch size times the most iterations. Steps that
make the predictor unstable are rejected. Asymptotic covariance ``sigma^2 (J'J)^{-1}``.

``method="mle"``: the same iteration minimises ``sum_k rho(r_k)`` for a loss of
:mod:`sysid.estimation.losses` (eq. 4.64, 4.73), started from the Gaussian estimate and scaled
to its residuals; linear-in-theta models use the regression form.
"""

from __future__ import annotations

import functools
import math
import warnings

import torch
import torch.nn.functional as F

from integrators.errors import InputValidationError
from integrators.jacobians import batch_jacobian
from integrators.newton import NewtonStatus, minimize

from ..data import IOData
from ..errors import PoorExcitationWarning
from ..filters import iir_filter
from ..models import PolynomialModel
from ._data import _check_broadcast, _groups, _regression_rows
from .initial import _initial_estimate
from .least_squares import _least_squares
from .losses import GaussianLoss, make_loss
from .results import STATIONARY_TOL, FitResult, covariance, remaining_step


def _max_root_modulus(theta: torch.Tensor, blocks: list[list[int]]) -> torch.Tensor:
    """Largest root modulus of the monic polynomials ``1 + t_1 z^-1 + ...`` (``(*batch,)``)."""
    out = torch.zeros(theta.shape[:-1], dtype=theta.dtype, device=theta.device)
    for idx in blocks:  # loop over polynomials (a handful), never over samples
        n = len(idx)
        tail = theta[..., idx]
        comp = torch.zeros(*theta.shape[:-1], n, n, dtype=theta.dtype, device=theta.device)
        comp[..., 0, :] = -tail
        if n > 1:
            k = torch.arange(n - 1, device=theta.device)
            comp[..., k + 1, k] = 1.0
        out = torch.maximum(out, torch.linalg.eigvals(comp).abs().amax(dim=-1))
    return out


def _select(x, members: torch.Tensor | None, n_batch: int):
    """The data sets ``members`` ((k,) indices into the flattened batch; None: all of them)
    of ``x``: a ``(*batch, *tail)`` tensor with ``n_batch`` batch dimensions, giving
    ``(k, *tail)``, or an :class:`IOData` of that batch shape, giving one of batch ``(k,)``."""
    if members is None:
        return x
    if isinstance(x, IOData):
        return x._map(lambda u, y: (_select(u, members, n_batch), _select(y, members, n_batch)))
    return x.reshape(-1, *x.shape[n_batch:])[members]


def _same_members(a: torch.Tensor | None, b: torch.Tensor | None) -> bool:
    """Whether two ``members`` arguments (index tensors, or None for all) name the same data
    sets."""
    if a is None or b is None:
        return a is b
    return torch.equal(a, b)


class _OutputError:
    """Simulation errors and their exact Jacobian for models without A, C, D
    (``y = sum_i q^-nk_i B_i/F_i u_i + e``, eq. 4.133), by filtering, no autograd.

    With ``v_i = u_i / F_i`` and ``x_i = B_i / F_i u_i`` (the response to input i),
    ``d yhat / d b_ij = v_i(t - nk_i - j)`` and ``d yhat / d f_ij = -x_i(t - j) / F_i``
    (``d(1/F)/df_j = -q^-j / F^2``); so one more pass of the filter ``1/F_i`` over the two
    signals ``u_i`` and ``x_i`` (one batched call) gives every column; ``J = -d yhat/d theta``
    is then a stack of delayed copies. Zero initial conditions in each experiment,
    experiments concatenated in time; ``sw`` (``(*batch, M)`` or None) weights the rows.
    Both methods take ``members``, the data sets to evaluate (:func:`_select`).

    :meth:`linearise` reuses the responses ``x_i`` of the last :meth:`residuals` call when
    ``theta`` and ``members`` are the same (in Levenberg-Marquardt, the accepted line-search
    point).
    """

    def __init__(self, model: PolynomialModel, data: IOData, sw: torch.Tensor | None):
        self.model, self.data, self.sw = model, data, sw
        # rows of J' in theta order, by blocks (signal, input, first lag, count): b_i from
        # -v_i (signal 0) delayed by nk_i, nk_i + 1, ..; then f_i from x_i / F_i (signal 1)
        # delayed by 1, 2, ..
        self.blocks = [
            (0, i, k, n) for i, (k, n) in enumerate(zip(model.nk, model.nb, strict=True))
        ]
        self.blocks += [(1, i, 1, n) for i, n in enumerate(model.nf)]
        self.blocks = [block for block in self.blocks if block[3]]
        self.top = max((first + n - 1 for _, _, first, n in self.blocks), default=0)
        self._last: tuple[torch.Tensor, torch.Tensor | None, list[torch.Tensor]] | None = None

    def _responses(self, theta: torch.Tensor, B, den, data: IOData, members) -> list[torch.Tensor]:
        """Per experiment, the responses ``x_i`` ``(*batch, nu, N)`` to the inputs of ``data``
        (the data sets ``members``)."""
        last = self._last
        if last is not None and torch.equal(last[0], theta) and _same_members(last[1], members):
            return last[2]
        out = [
            iir_filter(B, den, part.u.to(theta.dtype).transpose(-1, -2))
            for part in data.experiment_list  # loop over experiments (usually one)
        ]
        if not out[0].requires_grad:
            self._last = (theta.detach().clone(), members, out)
        return out

    def _errors(self, theta: torch.Tensor, responses, data: IOData, sw) -> torch.Tensor:
        parts = [
            part.y[..., 0].to(theta.dtype) - x.sum(-2)
            for part, x in zip(data.experiment_list, responses, strict=True)
        ]
        r = parts[0] if len(parts) == 1 else torch.cat(parts, dim=-1)
        r = r.expand(*theta.shape[:-1], r.shape[-1])
        return r if sw is None else r * sw

    def _members(self, members) -> tuple[IOData, torch.Tensor | None]:
        """The data and the row weights of the data sets ``members``."""
        n_batch = len(self.data.batch_shape)
        sw = None if self.sw is None else _select(self.sw, members, n_batch)
        return _select(self.data, members, n_batch), sw

    def residuals(self, theta: torch.Tensor, members=None) -> torch.Tensor:
        """Weighted simulation errors ``(*batch, M)`` (those of ``model.simulation_errors``)."""
        data, sw = self._members(members)
        B, den = self.model._transfer_polys(theta)
        return self._errors(theta, self._responses(theta, B, den, data, members), data, sw)

    def linearise(self, theta: torch.Tensor, members=None) -> tuple[torch.Tensor, torch.Tensor]:
        """``(r, J)``; ``J`` is the transpose of a contiguous ``(*batch, p, M)`` tensor (a
        faster ``J'J``)."""
        data, sw = self._members(members)
        with torch.no_grad():
            B, den = self.model._transfer_polys(theta)  # (*b, nu, width), (*b, nu, nf)
            ones = den.new_ones(*den.shape[:-1], 1)  # numerator 1 (den may be empty: nf = 0)
            responses = self._responses(theta, B, den, data, members)
            jacobians = []
            for part, x in zip(data.experiment_list, responses, strict=True):
                u = part.u.to(theta.dtype).transpose(-1, -2)
                both = torch.stack(torch.broadcast_tensors(-u, x), dim=-3)
                both = iir_filter(ones.unsqueeze(-3), den.unsqueeze(-3), both)  # -v_i, x_i/F_i
                N = both.shape[-1]
                windows = F.pad(both, (self.top, 0)).unfold(-1, N, 1)  # window j: top - j
                # each block is a slice of consecutive windows in decreasing delay: take the
                # blocks in reverse order, then one flip restores theta order
                last = [
                    windows[..., s, i, self.top - first - n + 1 : self.top - first + 1, :]
                    for s, i, first, n in reversed(self.blocks)  # loop over inputs (2 nu)
                ]
                empty = both.new_zeros(*both.shape[:-3], 0, N)  # a model without parameters
                jacobians.append(torch.cat(last, dim=-2).flip(-2) if last else empty)
            Jt = jacobians[0] if len(jacobians) == 1 else torch.cat(jacobians, dim=-1)
            Jt = Jt.expand(*theta.shape[:-1], *Jt.shape[-2:])
            if sw is not None:
                Jt = Jt * sw.unsqueeze(-2)
            return self._errors(theta, responses, data, sw), Jt.transpose(-1, -2)


def _admissible_fn(model: PolynomialModel, criterion: str):
    """Candidates must give a stable predictor: roots of C and F_i (prediction errors,
    eq. 4.132 divides by C F) or of A and F_i (simulation errors) inside the unit circle."""
    g = _groups(model)
    letters = ("c", "f") if criterion == "prediction" else ("a", "f")
    blocks = [ix for letter in letters for ix in g[letter] if len(ix)]
    if not blocks:
        return None
    return lambda th, members=None: _max_root_modulus(th, blocks) < 1.0


def _bad_init(init, model) -> InputValidationError:
    """The error for an ``init`` that is none of the forms :func:`sysid.fit` accepts."""
    return InputValidationError(
        f"init must be None (the automatic start), 'model' (the model's current parameters) "
        f"or starting parameters, a tensor (*batch, p) or (p,) with p = {model.n_params} "
        f"({', '.join(model.parameter_names())}), got {init!r}."
    )


def _fit_iterative(
    model, data, method, loss, alpha, w, criterion, init, linear, max_iter, xtol, ftol
) -> FitResult:
    batch = data.batch_shape
    n_batch = len(batch)
    p = model.n_params
    sw = None if w is None else w.sqrt()
    # the criterion of the data sets ``members`` (indices into the flattened batch; None: all)
    if linear:
        Phi, target = model.regression(data)
        if sw is not None:
            rows = _regression_rows(data, target.shape[-1])
            swr = torch.cat([sw[..., sl] for sl in rows], dim=-1)
            Phi, target = Phi * swr.unsqueeze(-1), target * swr
        Phi = Phi.expand(*batch, *Phi.shape[-2:])
        target = target.expand(*batch, target.shape[-1])

        def residual_fn(th, members=None):
            regressors = _select(Phi, members, n_batch)
            return _select(target, members, n_batch) - (regressors @ th.unsqueeze(-1)).squeeze(-1)

        def jacobian_fn(th, members=None):
            return residual_fn(th, members), -_select(Phi, members, n_batch)

        admissible = None
    else:
        errors = model.prediction_errors if criterion == "prediction" else model.simulation_errors

        def residual_fn(th, members=None):
            e = errors(_select(data, members, n_batch), theta=th)[..., 0]
            return e if sw is None else e * _select(sw, members, n_batch)

        jacobian_fn = None
        if model.na == model.nc == model.nd == 0:  # H = 1: prediction errors = simulation errors
            output_error = _OutputError(model, data, sw)
            residual_fn, jacobian_fn = output_error.residuals, output_error.linearise
        admissible = _admissible_fn(model, criterion)

    if init is None and linear:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", PoorExcitationWarning)
            theta0 = _least_squares(Phi, target)[0]
    elif init is None:
        try:
            theta0 = _initial_estimate(model, data)
        except InputValidationError as exc:
            raise InputValidationError(
                f"fit: the automatic starting estimate of {type(model).__name__} (an ARX "
                f"least-squares / instrumental-variable fit) cannot be formed from these data "
                f"({exc}); or give init= (starting parameters of your own)."
            ) from None
    elif isinstance(init, str) and init == "model":
        theta0 = model.parameter_vector().detach().expand(*batch, p).clone()
    elif isinstance(init, str):
        raise _bad_init(init, model)
    else:
        try:
            theta0 = torch.as_tensor(init, dtype=data.dtype, device=data.device)
        except (TypeError, ValueError, RuntimeError):
            raise _bad_init(init, model) from None
        _check_broadcast("init", theta0, (*batch, p), "(*batch, p) or (p,)")
        theta0 = theta0.expand(*batch, p).clone()
    if admissible is not None and not bool(admissible(theta0).all()):
        idx = tuple(int(i) for i in torch.nonzero(~admissible(theta0))[0])
        raise InputValidationError(
            f"the initial model gives an unstable predictor at batch index {idx}; start from a "
            "stable model (e.g. init=None for the automatic start)."
        )
    if jacobian_fn is not None:
        linearise = jacobian_fn
    else:  # residuals (M entries) against a few parameters: columns by forward mode

        def linearise(th, members=None):
            fn = functools.partial(residual_fn, members=members)
            return batch_jacobian(fn, th, strategy="forward")

    gauss = GaussianLoss()
    lm = _minimize_criterion(
        residual_fn, theta0, gauss, linearise, admissible, max_iter, xtol, ftol
    )
    history, iterations = lm.loss_history, lm.iterations
    the_loss = gauss
    if loss != "gaussian":
        the_loss = make_loss(loss, lm.residual, alpha)
        budget = max(max_iter, 500) if loss == "laplace" else max_iter
        lm = _minimize_criterion(
            residual_fn, lm.theta, the_loss, linearise, admissible, budget, xtol, ftol
        )
        history = lm.loss_history
        iterations = iterations + lm.iterations
    failed = lm.status == NewtonStatus.LINE_SEARCH_FAILED
    cov, sigma2, factor = covariance(lm.J, lm.residual, the_loss)
    # converged: at a stationary point to within STATIONARY_TOL standard errors (or, for
    # noise-free data where the standard errors vanish, to within sqrt(eps) relative)
    d, z = remaining_step(lm.J, lm.residual, the_loss, factor)
    tiny_step = d.norm(dim=-1) <= math.sqrt(torch.finfo(d.dtype).eps) * (1 + lm.theta.norm(dim=-1))
    converged = (z <= STATIONARY_TOL) | tiny_step
    # where the step to the stationary point would leave the stable models, the optimum of
    # the criterion lies beyond the stability boundary (e.g. an unstable plant)
    beyond = torch.zeros_like(converged) if admissible is None else ~admissible(lm.theta + d)
    return FitResult(
        theta=lm.theta,
        covariance=cov,
        standard_errors=torch.diagonal(cov, dim1=-2, dim2=-1).clamp_min(0).sqrt(),
        sigma2=sigma2,
        loss_history=history,
        iterations=iterations,
        converged=converged,
        method=method,
        loss=loss,
        parameter_names=[],
        n_samples=lm.residual.shape[-1],
        residuals=lm.residual,
        info={
            "damping": lm.damping,
            "initial_theta": theta0,
            "step_in_standard_errors": z,
            "line_search_failed": failed,
            "stationary_point_unstable": beyond,
            "iteration_limit_reached": ~(lm.converged | failed),
            "max_iter": max_iter,
        },
    )


def _minimize_criterion(residual_fn, theta0, loss, linearise, admissible, max_iter, xtol, ftol):
    """:func:`integrators.newton.minimize` by Levenberg–Marquardt on ``sum rho(r(theta))``
    with the given Jacobian, compacted (``residual_fn``, ``linearise``, ``admissible`` and
    ``loss`` take ``members``); raises where the criterion is not finite at ``theta0``."""
    result = minimize(
        residual_fn,
        theta0,
        method="levenberg_marquardt",
        jacobian=linearise,
        loss=None if loss.name == "gaussian" else loss,  # the same, without the unit weights
        admissible=admissible,
        max_iter=max_iter,
        xtol=xtol,
        ftol=ftol,
        compact=True,
    )
    bad = result.status == NewtonStatus.NON_FINITE
    if bool(bad.any()):
        idx = tuple(int(i) for i in torch.nonzero(bad)[0])
        k = int(result.iterations[idx])
        where = "at the initial parameters" if k == 0 else f"after {k} iterations"
        raise InputValidationError(
            f"the criterion is not finite {where} at batch index {idx} (unstable initial model "
            "or non-finite data); start from a stable model."
        )
    return result
