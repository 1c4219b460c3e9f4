"""Model validation: fit percentage, residual whiteness/independence tests, AIC, FPE.

All functions take sequences in the project convention ``(*batch, N, channels)`` (a 1-D
tensor is one single-channel sequence) and reduce over the time axis, so a Monte-Carlo
batch of data sets is validated in one call. ``fit_percent``, ``aic``, ``fpe`` and
``residual_test`` also take a fitted model and data, ``f(model, data)`` with ``data`` an
:class:`sysid.IOData` and ``model`` one of

* a :class:`sysid.PolynomialModel` or its :class:`sysid.FitResult`: ``fit_percent`` scores
  the free-run simulation (MATLAB's ``compare``); the residuals of the others are the
  one-step prediction errors (the simulation errors for an OE model), ``d = model.n_params``;
* the :class:`sysid.FitResult` of a :class:`sysid.GreyBoxModel` (an output-error model):
  the free run ``result.model.simulate(data)`` from the initial states the fit used (the
  estimated ones for ``x0="estimate"``) both for ``fit_percent`` and as the residuals
  ``y - yhat``, ``d = result.theta.shape[-1]`` (the free parameters and estimated initial
  states);
* the :class:`~sysid.continuous.training.TrainingResult` of a neural or hybrid model
  (``fit_percent`` and ``residual_test`` only): the free run ``result.simulate(data)``, its
  residuals ``y - yhat`` from sample ``result.n_init`` of every experiment on (where the
  simulation starts). ``aic`` and ``fpe`` refuse it: their penalty assumes identifiable
  parameters at the maximum-likelihood optimum, which network weights are not.

The model is evaluated without gradient. Any other argument types raise
:class:`~integrators.errors.InputValidationError` naming the expected signature.

Formulas (``N`` samples, ``d`` estimated parameters, residuals ``e_k``,
``V = (1/N) sum_k e_k^2`` the mean squared residual, i.e. the maximum-likelihood estimate of
the noise variance):

* ``fit_percent``: ``100 (1 - ||y - yhat|| / ||y - mean(y)||)`` per output channel (MATLAB's
  ``compare``: 100 is a perfect fit, 0 is no better than the mean, negative is worse).
* ``fit_quality``: that fit with the root-mean-square error ``sqrt(mean (y - yhat)^2)`` and
  the coefficient of determination ``R^2 = 1 - ||y - yhat||^2 / ||y - mean(y)||^2``
  (``= 1 - (1 - fit/100)^2``), all computed after leaving out the first ``skip`` samples
  (the transient of an unknown initial state).
* ``aic``: ``N log V + 2 d + N (log 2 pi + 1)`` = ``-2 log L + 2 d`` for Gaussian residuals
  with the maximised log-likelihood ``log L = -N/2 (log(2 pi V) + 1)`` (Akaike 1974; the
  constant term matches MATLAB's raw AIC for a single output).
* ``fpe``: ``V (1 + d/N) / (1 - d/N)`` (Akaike's final prediction error).
* ``residual_test``: sample autocorrelation ``rho_e(tau)`` of the (demeaned) residuals,
  ``tau = 0..m``, and cross-correlation ``rho_eu(tau) = sum_k e_{k+tau} u_k / (N s_e s_u)``,
  ``tau = -m..m``, with the band ``+/- z_{1-alpha/2} / sqrt(N)`` valid for white residuals;
  the Ljung–Box statistic ``Q = N (N + 2) sum_{tau=1}^{m} rho_e(tau)^2 / (N - tau)``, which is
  ``chi^2(m - n_params)`` for white residuals, and the independence statistic
  ``S = N rho' Rbar_u^-1 rho`` of ``rho = (rho_eu(0), .., rho_eu(m))`` with ``Rbar_u`` the
  ``(m + 1) x (m + 1)`` Toeplitz matrix of the input's autocorrelation (Ljung, System
  Identification, 1999, eq. 16.66; ``S = N sum rho_eu(tau)^2`` for a white input),
  ``chi^2(m + 1)`` per input when the residuals are white and independent of past inputs
  (``chi^2`` of the rank of ``Rbar_u`` where the input excites fewer directions).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import scipy.stats
import torch

from integrators.errors import InputValidationError

from . import models
from .continuous.greybox import GreyBoxModel
from .data import IOData
from .estimation import FitResult, fit
from .models import PolynomialModel

__all__ = [
    "FitQuality",
    "OrderSelection",
    "ResidualTestResult",
    "aic",
    "fit_percent",
    "fit_quality",
    "fpe",
    "residual_test",
    "select_order",
]


_MODEL_FORM = (
    "with a fitted polynomial model, its FitResult, a grey-box FitResult or a "
    "neural/hybrid TrainingResult, and IOData"
)
_USAGE = {
    "fit_quality": "fit_quality(y, yhat, skip=0) with tensors/arrays (*batch, N, ny)",
    "fit_percent": "fit_percent(y, yhat) with tensors/arrays (*batch, N, ny), or "
    f"fit_percent(model, data) {_MODEL_FORM}",
    "aic": "aic(residuals, n_params) with residuals (*batch, N, ny) and an int, or "
    "aic(model, data) with a fitted polynomial model, its FitResult or a grey-box FitResult, "
    "and IOData",
    "fpe": "fpe(residuals, n_params) with residuals (*batch, N, ny) and an int, or "
    "fpe(model, data) with a fitted polynomial model, its FitResult or a grey-box FitResult, "
    "and IOData",
    "residual_test": "residual_test(residuals, u=None, ...) with tensors/arrays (*batch, N, 1) "
    f"and (*batch, N, nu), or residual_test(model, data, ...) {_MODEL_FORM}",
}


def _model_and_data(first, second, func: str) -> tuple[object, IOData] | None:
    """``(fitted, data)`` when ``func`` was called in its model form, None for the array form.

    ``fitted`` is a :class:`PolynomialModel`, a :class:`FitResult` holding a polynomial or
    grey-box model, or a :class:`~sysid.continuous.training.TrainingResult`. Raises
    :class:`InputValidationError` with the expected signature when a model, a result or an
    :class:`IOData` appears anywhere else.
    """
    from .continuous.training import TrainingResult

    if isinstance(second, IOData):
        if isinstance(first, TrainingResult):
            return first, second
        model = first.model if isinstance(first, FitResult) else first
        if isinstance(model, PolynomialModel):
            if model.Ts not in (models.DEFAULT_TS, second.Ts):
                raise InputValidationError(
                    f"{func}: the model has Ts = {model.Ts} s but the data Ts = {second.Ts} s: "
                    "a discrete-time model describes one sampling; compare it on data sampled "
                    "as its estimation data were."
                )
            return first, second
        if isinstance(first, FitResult) and isinstance(model, GreyBoxModel):
            return first, second
    model_like = (PolynomialModel, FitResult, IOData, GreyBoxModel, torch.nn.Module)
    if isinstance(first, model_like) or isinstance(second, model_like):
        raise InputValidationError(
            f"{func}: got ({type(first).__name__}, {type(second).__name__}); expected "
            f"{_USAGE[func]}."
        )
    return None


def _free_run(fitted, data: IOData) -> torch.Tensor:
    """Free-run (simulated) output ``(*batch, N, ny)`` of a polynomial or grey-box
    ``fitted`` (see :func:`_model_and_data`) on ``data``, without gradient."""
    model = fitted.model if isinstance(fitted, FitResult) else fitted
    with torch.no_grad():
        if isinstance(model, GreyBoxModel):
            return model.simulate(data).to(data.y)
        return model.predict(data, horizon=math.inf)


def _model_residuals(
    fitted, data: IOData, func: str
) -> tuple[torch.Tensor, torch.Tensor, int | None]:
    """Residuals ``(*batch, M, ny)`` of ``fitted`` on ``data``, the inputs ``(*batch, M, nu)``
    of the same samples and the number ``d`` of estimated parameters.

    Polynomial models: the one-step prediction errors of all ``M = N`` samples,
    ``d = model.n_params``. Grey-box results: ``data.y`` minus the free run from the fit's
    initial states, all ``N`` samples, ``d = theta.shape[-1]``. Training results: ``data.y``
    minus ``result.simulate(data)`` from sample ``n_init`` of every experiment on; ``d`` is
    None (no count of estimated parameters suits AIC/FPE).
    """
    from .continuous.training import TrainingResult, _check_data

    if isinstance(fitted, TrainingResult):
        _check_data(data, fitted.model, func)
        keep = data.samples_after(fitted.n_init)
        e = data.y - fitted.simulate(data).to(data.y)
        return e.index_select(-2, keep), data.u.index_select(-2, keep), None
    model = fitted.model if isinstance(fitted, FitResult) else fitted
    if isinstance(model, GreyBoxModel):
        return data.y - _free_run(fitted, data), data.u, fitted.theta.shape[-1]
    with torch.no_grad():
        return model.prediction_errors(data), data.u, model.n_params


def _as_sequences(x, name: str, func: str) -> torch.Tensor:
    """Canonical ``(*batch, N, channels)`` view (1-D input becomes ``(N, 1)``)."""
    try:
        x = torch.as_tensor(x)
    except (TypeError, ValueError, RuntimeError) as exc:
        raise InputValidationError(
            f"{func}: {name} is a {type(x).__name__}, not an array of numbers; expected "
            f"{_USAGE[func]}."
        ) from exc
    if not x.is_floating_point():
        x = x.to(torch.get_default_dtype())
    if x.dim() == 0:
        raise InputValidationError(
            f"{func}: {name} must be a sequence (*batch, N, channels), got a scalar."
        )
    if x.dim() == 1:
        x = x.unsqueeze(-1)
    bad = ~torch.isfinite(x)
    if bool(bad.any()):
        idx = tuple(int(i) for i in torch.nonzero(bad)[0])
        raise InputValidationError(
            f"{func}: {name} contains a non-finite value at index {idx} (time index {idx[-2]})."
        )
    return x


def fit_percent(y, yhat, skip: int | None = None) -> torch.Tensor:
    """MATLAB's fit: ``100 (1 - ||y - yhat|| / ||y - mean(y)||)`` per output channel.

    Call as ``fit_percent(y, yhat)`` or ``fit_percent(model, data)``.

    Args:
        y: measured outputs ``(*batch, N, ny)`` (or ``(N,)``); or a fitted
            :class:`sysid.PolynomialModel` / its :class:`sysid.FitResult`, a grey-box
            :class:`sysid.FitResult` or a :class:`~sysid.continuous.training.TrainingResult`.
        yhat: model outputs (simulated or predicted), ``(*batch, N, ny)`` with the ``N`` and
            ``ny`` of ``y`` (batch dimensions broadcast);
            or, with a model as first argument, the :class:`sysid.IOData` to compare on: the
            fit is then that of the model's noise-free simulated output to ``data.y``
            (MATLAB's ``compare``), computed without gradient: ``model.simulate(data)`` of a
            polynomial model (from rest), ``result.model.simulate(data)`` of a grey-box result
            (from the initial states the fit used), ``result.validate(data, skip)`` of a
            training result.
        skip: samples left out at the start (``0 <= skip <= N - 2``; with a model and data,
            at the start of every experiment, the rule of :meth:`sysid.IOData.samples_after`),
            e.g. the transient of an unknown initial state; the mean of ``y`` is that of the
            remaining samples. None: 0, except ``result.n_init`` for a training result (its
            ``validate`` default, where the simulation starts).

    Returns:
        Fit in percent, shape ``(*batch, ny)``.

    Raises:
        InputValidationError: other argument types (the message states the signature),
            shapes do not match, non-finite values, a bad ``skip``, or a constant ``y`` (the
            normalisation ``||y - mean(y)||`` is zero).
    """
    from .continuous.training import TrainingResult

    pair = _model_and_data(y, yhat, "fit_percent")
    if pair is None:
        return _quality(y, yhat, 0 if skip is None else skip, "fit_percent").fit_percent
    fitted, data = pair
    if isinstance(fitted, TrainingResult):
        return fitted.validate(data, skip)["fit_percent"]
    keep = data.samples_after(0 if skip is None else skip)  # the start of every experiment out
    yhat = _free_run(fitted, data).index_select(-2, keep)
    return _quality(data.y.index_select(-2, keep), yhat, 0, "fit_percent").fit_percent


@dataclass
class FitQuality:
    """Fit statistics of model outputs against measured ones, per data set and output channel.

    Attributes:
        fit_percent: MATLAB's fit ``100 (1 - ||y - yhat|| / ||y - mean(y)||)``, (*batch, ny).
        rmse: root-mean-square error ``sqrt(mean_k (y_k - yhat_k)^2)`` (output units),
            (*batch, ny).
        r_squared: ``1 - ||y - yhat||^2 / ||y - mean(y)||^2``, (*batch, ny).
        skip: samples left out at the start of each experiment.
        n_samples: samples per channel that entered the statistics.
    """

    fit_percent: torch.Tensor
    rmse: torch.Tensor
    r_squared: torch.Tensor
    skip: int
    n_samples: int


def fit_quality(y, yhat, skip: int = 0) -> FitQuality:
    """Fit percentage, RMSE and R^2 of ``yhat`` against ``y`` after ``skip`` samples.

    Args:
        y: measured outputs ``(*batch, N, ny)`` (or ``(N,)``).
        yhat: model outputs (e.g. a free-run simulation), ``(*batch, N, ny)`` with the ``N``
            and ``ny`` of ``y`` (batch dimensions broadcast).
        skip: samples left out at the start (``0 <= skip <= N - 2``), e.g. the transient of
            an unknown initial state.

    Returns:
        :class:`FitQuality` with ``(*batch, ny)`` tensors.

    Raises:
        InputValidationError: shapes do not match, non-finite values, a bad ``skip``, or a
            constant ``y`` after the skipped samples.
    """
    return _quality(y, yhat, skip, "fit_quality")


def _quality(y, yhat, skip, func: str, check: bool = True) -> FitQuality:
    """The statistics of :class:`FitQuality` (formulas in the module docstring); ``check``
    False skips the argument checks and gives NaN/inf where the numbers are undefined."""
    if check:
        y = _as_sequences(y, "y", func)
        yhat = _as_sequences(yhat, "yhat", func).to(dtype=y.dtype, device=y.device)
        if y.shape[-2:] != yhat.shape[-2:]:
            raise InputValidationError(
                f"{func}: y {tuple(y.shape)} and yhat {tuple(yhat.shape)} must have the same "
                f"number of samples N and channels (the last two dimensions, (N, ny); a 1-D "
                "signal is (N, 1)); only their batch dimensions may broadcast. Compare the "
                "model output over the same samples as y."
            )
        try:
            torch.broadcast_shapes(y.shape, yhat.shape)
        except RuntimeError as exc:
            raise InputValidationError(
                f"{func}: the batch shapes of y {tuple(y.shape[:-2])} and yhat "
                f"{tuple(yhat.shape[:-2])} do not broadcast."
            ) from exc
        N = y.shape[-2]
        if isinstance(skip, bool) or int(skip) != skip or not 0 <= skip <= N - 2:
            raise InputValidationError(
                f"{func}: skip must be an integer in [0, N - 2] = [0, {N - 2}] (samples left "
                f"out at the start), got {skip!r}."
            )
    skip = int(skip)
    y, yhat = y[..., skip:, :], yhat[..., skip:, :]
    e2 = ((y - yhat) ** 2).sum(-2)
    d2 = ((y - y.mean(dim=-2, keepdim=True)) ** 2).sum(-2)
    if check and bool((d2 == 0).any()):
        raise InputValidationError(
            f"{func}: y is constant in time for some batch member/channel (after the first "
            f"{skip} samples), so the fit is undefined; compare on a data set with a varying "
            "output."
        )
    n = y.shape[-2]
    return FitQuality(
        fit_percent=100.0 * (1.0 - e2.sqrt() / d2.sqrt()),
        rmse=(e2 / n).sqrt(),
        r_squared=1.0 - e2 / d2,
        skip=skip,
        n_samples=n,
    )


def _residuals_and_size(residuals, n_params, func: str) -> tuple[torch.Tensor, int]:
    """Residuals ``(*batch, N, ny)`` and ``d`` of ``func(residuals, n_params)`` or of
    ``func(model, data)`` (see :func:`_model_residuals`)."""
    pair = _model_and_data(residuals, n_params, func)
    if pair is not None:
        e, _, d = _model_residuals(*pair, func)
        if d is None:
            raise InputValidationError(
                f"{func}: a TrainingResult has no parameter count that suits {func}: its "
                "penalty assumes few identifiable parameters at the maximum-likelihood "
                "optimum, and network weights are neither (symmetries, over-parameterisation, "
                "training stopped early on windows). Compare neural models on validation "
                f"data (fit_percent(result, data)), or call {func}(residuals, n_params) with "
                "the residuals data.y - result.simulate(data) of the samples "
                "data.samples_after(result.n_init) and a count you can justify."
            )
    else:
        if isinstance(n_params, bool) or not isinstance(n_params, (int, np.integer)):
            raise InputValidationError(
                f"{func}: n_params must be an int, got {type(n_params).__name__}; expected "
                f"{_USAGE[func]}."
            )
        e, d = _as_sequences(residuals, "residuals", func), int(n_params)
    N = e.shape[-2]
    if d < 0:
        raise InputValidationError(f"{func}: n_params must be >= 0, got d = {d}.")
    if func == "fpe" and d >= N:
        raise InputValidationError(
            f"fpe: need n_params < N (its factor (1 + d/N) / (1 - d/N) is infinite or "
            f"negative otherwise), got d = {d}, N = {N}; use more data or a smaller model."
        )
    return e, d


def _loss_function(e: torch.Tensor) -> torch.Tensor:
    """``V = det(E'E / N)`` (the mean squared residual for one output), ``(*batch,)``."""
    if e.shape[-1] == 1:
        return (e * e).mean(dim=(-2, -1))
    return torch.linalg.det(e.transpose(-1, -2) @ e / e.shape[-2])


def aic(residuals, n_params) -> torch.Tensor:
    """Akaike's information criterion ``N log V + 2 d + N ny (log 2 pi + 1)`` (Gaussian).

    Call as ``aic(residuals, n_params)`` or ``aic(model, data)``.

    Args:
        residuals: prediction errors ``(*batch, N, ny)`` of the model on the estimation data;
            or a fitted :class:`sysid.PolynomialModel` / its :class:`sysid.FitResult`, or a
            grey-box :class:`sysid.FitResult` (a
            :class:`~sysid.continuous.training.TrainingResult` is refused: see the module
            docstring).
        n_params: number ``d >= 0`` of estimated parameters; or, with a model
            as first argument, the :class:`sysid.IOData` on which its residuals are taken
            (all ``N`` samples, without gradient): a polynomial model's one-step prediction
            errors with ``d = model.n_params``, a grey-box model's simulation errors
            ``y - result.model.simulate(data)`` with ``d = result.theta.shape[-1]``.

    Returns:
        AIC, shape ``(*batch,)``; smaller is better.
    """
    e, d = _residuals_and_size(residuals, n_params, "aic")
    N, ny = e.shape[-2:]
    return N * torch.log(_loss_function(e)) + 2 * d + N * ny * (math.log(2 * math.pi) + 1)


def fpe(residuals, n_params) -> torch.Tensor:
    """Akaike's final prediction error ``V (1 + d/N) / (1 - d/N)``.

    Call as ``fpe(residuals, n_params)`` or ``fpe(model, data)``.

    Args:
        residuals: prediction errors ``(*batch, N, ny)`` on the estimation data; or a fitted
            model or result, as for :func:`aic`.
        n_params: number ``d`` of estimated parameters (``0 <= d < N``); or, with a model as
            first argument, the :class:`sysid.IOData` on which its residuals are taken, as
            for :func:`aic`.

    Returns:
        FPE, shape ``(*batch,)``; an estimate of the prediction-error variance on fresh data.
    """
    e, d = _residuals_and_size(residuals, n_params, "fpe")
    N = e.shape[-2]
    return _loss_function(e) * (1 + d / N) / (1 - d / N)


def _correlate(a: torch.Tensor, b: torch.Tensor, max_lag: int) -> torch.Tensor:
    """``c(tau) = sum_k a_{k+tau} b_k`` for ``tau = 0..max_lag`` along dim -1, via FFT."""
    N = a.shape[-1]
    n = 1 << (2 * N - 1).bit_length()
    fa = torch.fft.rfft(a, n=n)
    fb = torch.fft.rfft(b, n=n)
    c = torch.fft.irfft(fa * fb.conj(), n=n)
    return c[..., : max_lag + 1]


@dataclass
class ResidualTestResult:
    """Result of :func:`residual_test` (batch dims ``*batch`` of the residuals).

    Attributes:
        lags: ``0..max_lag``.
        autocorrelation: ``rho_e(tau)``, ``(*batch, max_lag + 1)`` (``rho_e(0) = 1``).
        bound: half-width ``z_{1-alpha/2} / sqrt(N)`` of the confidence band.
        whiteness_statistic: Ljung–Box ``Q``, ``(*batch,)``.
        whiteness_dof: degrees of freedom of ``Q``'s chi-square law.
        whiteness_pvalue: ``P[chi^2 >= Q]``, ``(*batch,)``.
        white: ``whiteness_pvalue >= alpha``, ``(*batch,)`` bool.
        fraction_outside: fraction of lags ``1..max_lag`` with ``|rho_e| > bound``.
        cross_lags: ``-max_lag..max_lag`` (None without input).
        cross_correlation: ``rho_eu(tau)``, ``(*batch, nu, 2 max_lag + 1)`` or None.
        independence_statistic: ``S`` per input, ``(*batch, nu)`` or None.
        independence_pvalue: ``P[chi^2(max_lag + 1) >= S]`` (degrees of freedom: the rank
            of the input's autocorrelation matrix), ``(*batch, nu)`` or None.
        independent: all inputs pass, ``(*batch,)`` bool or None.
        alpha: significance level used.
    """

    lags: torch.Tensor
    autocorrelation: torch.Tensor
    bound: float
    whiteness_statistic: torch.Tensor
    whiteness_dof: int
    whiteness_pvalue: torch.Tensor
    white: torch.Tensor
    fraction_outside: torch.Tensor
    alpha: float
    cross_lags: torch.Tensor | None = None
    cross_correlation: torch.Tensor | None = None
    independence_statistic: torch.Tensor | None = None
    independence_pvalue: torch.Tensor | None = None
    independent: torch.Tensor | None = field(default=None)

    @property
    def passed(self) -> torch.Tensor:
        """Whiteness passed and, when an input was given, independence passed too."""
        if self.independent is None:
            return self.white
        return self.white & self.independent


#: relative singular-value threshold of the rank of an input's autocorrelation matrix
_RANK_RTOL = 1e-10


def residual_test(
    residuals, u=None, max_lag: int = 25, alpha: float = 0.01, n_params: int = 0
) -> ResidualTestResult:
    """Whiteness of residuals and their independence from past inputs (MATLAB ``resid``).

    Call as ``residual_test(residuals, u=None, ...)`` or ``residual_test(model, data, ...)``.

    Args:
        residuals: prediction errors ``(*batch, N, 1)`` (or ``(N,)``); one output. Or a
            fitted model, whose residuals on ``data`` are tested (without gradient) against
            ``data.u`` of the same samples: a :class:`sysid.PolynomialModel` / its
            :class:`sysid.FitResult` (one-step prediction errors, all samples), a grey-box
            :class:`sysid.FitResult` (simulation errors ``y - result.model.simulate(data)``,
            all samples) or a :class:`~sysid.continuous.training.TrainingResult`
            (simulation errors ``y - result.simulate(data)`` from sample ``n_init`` of every
            experiment on).
        u: inputs ``(*batch, N, nu)`` of the same data set, or None; with a model as first
            argument, the :class:`sysid.IOData` (required).
        max_lag: largest lag ``m`` (``1 <= m < N``).
        alpha: significance level of the bands and tests.
        n_params: number of noise-model parameters fitted to the residuals (reduces the
            Ljung–Box degrees of freedom to ``m - n_params``; 0 for a plain whiteness test).

    Returns:
        :class:`ResidualTestResult`.

    Raises:
        InputValidationError: other argument types (the message states the signature),
            more than one output, bad ``max_lag``/``n_params``, or constant signals.
    """
    pair = _model_and_data(residuals, u, "residual_test")
    if pair is not None:
        residuals, u, _ = _model_residuals(*pair, "residual_test")
    e = _as_sequences(residuals, "residuals", "residual_test")
    if e.shape[-1] != 1:
        raise InputValidationError(
            f"residual_test: expected one output channel, got {e.shape[-1]}."
        )
    N = e.shape[-2]
    if isinstance(max_lag, bool) or int(max_lag) != max_lag or not 1 <= max_lag < N:
        raise InputValidationError(
            f"residual_test: max_lag must be an integer with 1 <= max_lag < N = {N}, got "
            f"{max_lag!r}."
        )
    max_lag = int(max_lag)
    if not 0 < alpha < 1:
        raise InputValidationError(f"residual_test: alpha must be in (0, 1), got {alpha!r}.")
    if not 0 <= n_params < max_lag:
        raise InputValidationError(
            f"residual_test: need 0 <= n_params < max_lag, got {n_params} and {max_lag}."
        )
    x = e[..., 0]
    x = x - x.mean(dim=-1, keepdim=True)
    c = _correlate(x, x, max_lag)
    if bool((c[..., 0] <= 0).any()):
        raise InputValidationError("residual_test: residuals are identically zero.")
    rho = c / c[..., :1]
    z = float(scipy.stats.norm.ppf(1 - alpha / 2))
    bound = z / math.sqrt(N)
    taus = torch.arange(1, max_lag + 1, dtype=x.dtype, device=x.device)
    Q = N * (N + 2) * (rho[..., 1:] ** 2 / (N - taus)).sum(-1)
    dof = max_lag - n_params
    pval = torch.as_tensor(
        scipy.stats.chi2.sf(Q.detach().cpu().numpy(), dof), dtype=x.dtype, device=x.device
    )
    result = ResidualTestResult(
        lags=torch.arange(max_lag + 1, device=x.device),
        autocorrelation=rho,
        bound=bound,
        whiteness_statistic=Q,
        whiteness_dof=dof,
        whiteness_pvalue=pval,
        white=pval >= alpha,
        fraction_outside=(rho[..., 1:].abs() > bound).to(x.dtype).mean(-1),
        alpha=alpha,
    )
    if u is None:
        return result
    uu = _as_sequences(u, "u", "residual_test").to(dtype=x.dtype, device=x.device)
    if uu.shape[-2] != N:
        raise InputValidationError(
            f"residual_test: u has {uu.shape[-2]} samples but the residuals have {N}."
        )
    try:
        torch.broadcast_shapes(uu.shape[:-2], e.shape[:-2])
    except RuntimeError as exc:
        raise InputValidationError(
            f"residual_test: the batch shapes of the residuals {tuple(e.shape[:-2])} and of u "
            f"{tuple(uu.shape[:-2])} do not broadcast."
        ) from exc
    uu = uu.transpose(-1, -2)  # (*batch, nu, N)
    uu = uu - uu.mean(dim=-1, keepdim=True)
    su = torch.linalg.vector_norm(uu, dim=-1)
    if bool((su == 0).any()):
        raise InputValidationError("residual_test: an input channel is constant.")
    xs = x.unsqueeze(-2)
    scale = (su * c[..., :1].sqrt()).unsqueeze(-1)
    pos = _correlate(xs, uu, max_lag) / scale  # e_{k+tau} u_k, tau >= 0
    neg = _correlate(uu, xs, max_lag) / scale  # e_{k-tau} u_k
    cross = torch.cat([neg[..., 1:].flip(-1), pos], dim=-1)
    # S = N rho' Rbar_u^-1 rho with the Toeplitz autocorrelation matrix of each input, from
    # one eigendecomposition: its pseudo-inverse and rank where the input excites fewer than
    # max_lag + 1 directions
    rho_u = _correlate(uu, uu, max_lag) / (su**2).unsqueeze(-1)  # (*batch, nu, m + 1)
    lag = torch.arange(max_lag + 1, device=x.device)
    Ru = rho_u[..., (lag[:, None] - lag).abs()]  # (*batch, nu, m + 1, m + 1)
    values, vectors = torch.linalg.eigh(Ru)
    kept = values > _RANK_RTOL * values.amax(-1, keepdim=True)
    along = (vectors.transpose(-1, -2) @ pos.unsqueeze(-1))[..., 0]  # rho in the eigenbasis
    S = N * torch.where(kept, along**2 / torch.where(kept, values, 1.0), 0.0).sum(-1)
    rank = kept.sum(-1)
    ipval = torch.as_tensor(
        scipy.stats.chi2.sf(S.detach().cpu().numpy(), rank.cpu().numpy()),
        dtype=x.dtype,
        device=x.device,
    )
    result.cross_lags = torch.arange(-max_lag, max_lag + 1, device=x.device)
    result.cross_correlation = cross
    result.independence_statistic = S
    result.independence_pvalue = ipval
    result.independent = (ipval >= alpha).all(dim=-1)
    return result


def _after(data, skip: int):
    """``data`` without the first ``skip`` samples of every experiment."""
    if skip == 0:
        return data
    return IOData.experiments(
        [
            IOData(p.u[..., skip:, :], p.y[..., skip:, :], p.Ts, intersample=p.intersample)
            for p in data.experiment_list
        ]
    )


_STRUCTURES = {
    "fir": (("nb",), [(nb,) for nb in range(1, 11)]),
    "arx": (("na", "nb"), [(na, nb) for na in range(1, 5) for nb in range(1, 5)]),
    "oe": (("nb", "nf"), [(nb, nf) for nb in range(1, 4) for nf in range(1, 4)]),
    "armax": (("na", "nb", "nc"), [(n, n, c) for n in range(1, 4) for c in range(0, 3)]),
}


@dataclass
class OrderSelection:
    """Result of :func:`select_order`.

    Attributes:
        orders: the candidate orders (tuples, named by ``order_names``).
        order_names: e.g. ``("na", "nb")``.
        n_params: parameters per candidate.
        aic, fpe: ``(n_candidates, *batch)`` criteria on the estimation data.
        validation_loss: ``(n_candidates, *batch)`` mean squared one-step prediction error on
            the validation data (None unless ``criterion="validation"``).
        criterion: the criterion used.
        best_index: ``(*batch,)`` index of the chosen candidate per data set.
        best: chosen orders of the first data set (or of the only one).
        table: one dict per candidate (criteria averaged over the batch), ready for
            ``experiments._common.write_table``.
    """

    orders: list[tuple[int, ...]]
    order_names: tuple[str, ...]
    n_params: list[int]
    aic: torch.Tensor
    fpe: torch.Tensor
    validation_loss: torch.Tensor | None
    criterion: str
    best_index: torch.Tensor
    best: tuple[int, ...]
    table: list[dict]


def select_order(
    data,
    structure: str = "arx",
    orders=None,
    criterion: str = "aic",
    *,
    nk: int = 1,
    validation_data=None,
    tolerance: float = 0.01,
) -> OrderSelection:
    """Pick the smallest model structure the data support ("model only what is needed").

    Every candidate is fitted with :func:`sysid.fit` (batched over the data sets) and scored
    on one-step prediction errors over the same samples (the first ``max lag`` samples of
    the largest candidate are left out of every experiment for all, so every candidate sees
    the same ``N``). FIR and ARX candidates are fitted by least squares on exactly those
    samples (the earlier ones serve only as lagged regressors), so their ``aic`` is the
    Gaussian AIC of that least-squares fit, as an ordinary-least-squares package reports it
    for the same rows; OE and ARMAX candidates are fitted on all samples from zero initial
    conditions.

    * ``"aic"`` / ``"fpe"``: the minimum of the criterion (their ``2 d`` and
      ``(1 + d/N)/(1 - d/N)`` penalties trade fit against size); ties go to fewer parameters.
    * ``"validation"``: the mean squared one-step prediction error on ``validation_data``
      (default: the second half of ``data``, the first half being used for estimation); the
      smallest candidate within ``1 + tolerance`` of the best loss is chosen.

    Args:
        data: :class:`sysid.IOData` (one output; a batch of data sets is allowed).
        structure: ``"fir"``, ``"arx"``, ``"oe"`` or ``"armax"``.
        orders: candidate order tuples (``(nb,)``, ``(na, nb)``, ``(nb, nf)``,
            ``(na, nb, nc)``); default: a small grid (see ``_STRUCTURES``).
        criterion: ``"aic"``, ``"fpe"`` or ``"validation"``.
        nk: input delay of every candidate.

    Returns:
        :class:`OrderSelection` with the table of criteria.
    """
    if structure not in _STRUCTURES:
        raise InputValidationError(f"structure must be one of {tuple(_STRUCTURES)}.")
    if criterion not in ("aic", "fpe", "validation"):
        raise InputValidationError("criterion must be 'aic', 'fpe' or 'validation'.")
    names, default = _STRUCTURES[structure]
    try:
        orders = [tuple(o) for o in (default if orders is None else orders)]
    except TypeError:
        orders = []
    if not orders or any(len(o) != len(names) for o in orders):
        raise InputValidationError(f"orders must be tuples {names} for structure {structure!r}.")
    for o in orders:
        if not all(models._is_integer(v) for v in o):
            raise InputValidationError(
                f"select_order: the candidate orders {names} = {o} are not all integers; "
                "orders count coefficients, so give whole numbers (a float such as 1.7 is "
                "refused, not rounded)."
            )
    orders = [tuple(int(v) for v in o) for o in orders]
    cls = {"fir": models.FIR, "arx": models.ARX, "oe": models.OE, "armax": models.ARMAX}[structure]
    if criterion == "validation" and validation_data is None:
        estimation, validation_data = data.split(0.5)
    else:
        estimation = data
    skip = max(max(o) for o in orders) + nk  # the longest lag, left out of every experiment
    kept = estimation.samples_after(skip)
    kept_val = validation_data.samples_after(skip) if criterion == "validation" else None
    kw = dict(n_inputs=estimation.nu, dtype=estimation.dtype, device=estimation.device)
    aics, fpes, vals, n_params = [], [], [], []
    for order in orders:  # loop over candidate structures (each fit is batched)
        model = cls(*order, nk=nk, **kw)
        if model.is_linear_in_parameters:
            # least squares over exactly the scored rows: the Gaussian AIC of the fit
            result = fit(model, _after(estimation, skip - model._max_lag()))
        else:
            result = fit(model, estimation)
        with torch.no_grad():  # criteria to compare, not to differentiate
            e = result.model.prediction_errors(estimation).index_select(-2, kept)
            d = result.model.n_params
            n_params.append(d)
            aics.append(aic(e, d))
            fpes.append(fpe(e, d))
            if criterion == "validation":
                ev = result.model.prediction_errors(validation_data).index_select(-2, kept_val)
                vals.append((ev * ev).mean(dim=(-2, -1)))
    A, Fp = torch.stack(aics), torch.stack(fpes)
    V = torch.stack(vals) if vals else None
    size = torch.tensor(n_params, dtype=A.dtype, device=A.device).reshape(
        -1, *([1] * (A.dim() - 1))
    )
    if criterion == "validation":
        ok = V <= V.min(dim=0).values * (1 + tolerance)
    else:
        score = A if criterion == "aic" else Fp
        ok = score <= score.min(dim=0).values
    # among acceptable candidates, the fewest parameters (then the first listed)
    rank = torch.where(ok, size, torch.full_like(size.expand_as(ok), math.inf))
    best_index = rank.argmin(dim=0)
    table = []
    for i, order in enumerate(orders):
        row = dict(zip(names, order, strict=True))
        row.update(n_params=n_params[i], aic=A[i].mean().item(), fpe=Fp[i].mean().item())
        if V is not None:
            row["validation_mse"] = V[i].mean().item()
        row["chosen_fraction"] = (best_index == i).to(A.dtype).mean().item()
        table.append(row)
    first = int(best_index.reshape(-1)[0])
    return OrderSelection(
        orders=orders,
        order_names=names,
        n_params=n_params,
        aic=A,
        fpe=Fp,
        validation_loss=V,
        criterion=criterion,
        best_index=best_index,
        best=orders[first],
        table=table,
    )
