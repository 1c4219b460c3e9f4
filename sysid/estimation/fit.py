"""The single entry point of parameter estimation for the polynomial model structures (the
course notes (Modelling and Simulation), §4.2–4.6): model → data → estimate →
:class:`FitResult`.

:func:`fit` checks its arguments, dispatches to the direct solves of
:mod:`~sysid.estimation.least_squares` (``"lls"``, eq. 4.111–4.112; ``"iv"``) or to the
Levenberg–Marquardt iteration of :mod:`~sysid.estimation.prediction_error` (``"gauss_newton"``,
eq. 4.130–4.133; ``"mle"`` with a loss of :mod:`~sysid.estimation.losses`, eq. 4.64, 4.73),
and reports data sets whose estimate did not converge or is unstable.
"""

from __future__ import annotations

import inspect
import warnings

import torch

from integrators.errors import InputValidationError

from ..data import IOData
from ..errors import ConvergenceWarning, UnstableModelWarning
from ..models import DEFAULT_TS, PolynomialModel
from ._data import _batched_model, _weights
from .least_squares import _fit_iv, _fit_lls
from .losses import LOSSES
from .prediction_error import _fit_iterative
from .results import STATIONARY_TOL, FitResult

__all__ = ["METHODS", "fit"]

METHODS = ("lls", "gauss_newton", "mle", "iv")

#: Largest pole modulus above which a non-converged estimate is reported as sitting on the
#: stability boundary (the Levenberg–Marquardt steps keep it strictly inside), as is one
#: whose step to the stationary point leads to an unstable predictor.
_BOUNDARY_MODULUS = 0.99


def fit(
    model: PolynomialModel,
    data: IOData,
    method: str | None = None,
    loss: str = "gaussian",
    *,
    alpha: float | None = None,
    weights=None,
    criterion: str = "prediction",
    init=None,
    max_iter: int = 100,
    xtol: float | None = None,
    ftol: float | None = None,
    iv_iterations: int = 2,
    x0=None,
    segment_length: int | None = None,
    progress: bool | None = None,
    **training,
) -> FitResult:
    """Estimate the parameters of ``model`` from ``data`` (batched over data sets).

    The one entry point for every model: polynomial models (below) and continuous-time
    grey-box models (:class:`~sysid.continuous.GreyBoxModel`, fitted through the Runge-Kutta
    layers by :mod:`sysid.continuous.fit`; ``criterion``, ``x0``, ``segment_length`` apply).

    Args:
        model: FIR, ARX, OE, ARMAX, BJ, a general :class:`PolynomialModel` or a
            :class:`~sysid.continuous.GreyBoxModel`. A polynomial model's batch shape
            must equal the data's or be empty. It only gives the structure (and, for
            ``init="model"``, the start): it is never modified. The fitted model is
            ``result.model``, a copy batched like the data with the estimate as parameters.
        data: :class:`IOData` (one output), ``(*batch, N, nu)`` / ``(*batch, N, 1)``.
        method: ``"lls"`` (FIR/ARX, eq. 4.111–4.112), ``"iv"`` (ARX structure),
            ``"gauss_newton"`` (Levenberg–Marquardt on prediction errors) or ``"mle"`` (with
            ``loss``). Default: ``"lls"`` for FIR/ARX, ``"gauss_newton"`` otherwise, and
            ``"mle"`` whenever ``loss`` is not Gaussian.
        loss: noise model of ``"mle"``: ``"gaussian"`` (weighted LS, eq. 4.64), ``"fair"``
            (eq. 4.73), ``"laplace"`` or ``"huber"`` (Huber's least-favourable density,
            :class:`~sysid.estimation.losses.HuberLoss`).
        alpha: the loss' tuning constant: for ``"fair"`` its ``alpha`` (1/output units),
            default ``1 / s``; for ``"huber"`` the threshold ``c`` (output units) where the
            loss turns linear, default ``1.345 s``; ``s`` is a robust (MAD) scale of the
            least-squares residuals (:func:`~sysid.estimation.losses.make_loss`).
        weights: per-sample weights ``1/sigma_k^2`` of the Gaussian loss, ``(*batch, N)``.
        criterion: ``"prediction"`` (one-step prediction errors, eq. 4.130; the simulation
            error for OE) or ``"simulation"`` (free-run errors for any structure). Grey-box
            models: ``"simulation"`` (the default), ``"multiple_shooting"`` or ``"one_step"``
            (see :mod:`sysid.continuous.fit`).
        init: starting parameters ``(*batch, p)``, ``"model"`` (the model's current values) or
            ``None`` (automatic: ARX least squares / instrumental variables, stabilised; a
            model with both A and F starts from its current values, one without B from 0).
        max_iter, xtol, ftol: iteration limit and step / relative-decrease tolerances of the
            iterative fits (None: 1e-8 and 1e-10 for polynomial models, 1e-10 and 1e-12 for
            grey-box models).
        iv_iterations: instrument refinements of ``"iv"`` (and of the automatic start).
        x0: grey-box models: the initial state, ``"zero"``, ``"estimate"`` (one per
            experiment), a tensor (nx,) / (*batch, nx) for every experiment or a list of
            such tensors, one per experiment; default the model's ``x0``. With the
            one-step criterion every step starts from the measured state, so ``"estimate"``
            gives the measured first states.
        segment_length: grey-box multiple shooting: sample intervals per segment (default
            10, longer where a record would have more than 100 segments). Short segments
            widen the basin of attraction; each adds ``nx`` node states to the fit.
        **training: neural continuous-time models (an ``nn.Module`` with ``nx``, ``nu``,
            ``ny``, ``method``, ``substeps``, ``output``, ``physical_parameters``, e.g.
            ``NeuralODE``), or ``method="adam"`` / ``"lbfgs"``: the options of
            :func:`sysid.continuous.training.train` (``horizon``, ``batch_size``,
            ``epochs``, ``lr``, ``validation``, ``patience``, ``seed``, ``checkpoint``, ...);
            ``criterion`` is ``"truncated"`` and ``x0`` is ``"estimate"`` (default),
            ``"encoder"`` or ``"zero"``.
        progress: grey-box models: a tqdm bar over the Levenberg-Marquardt iterations with
            the current loss; neural models: over the epochs with the training and validation
            losses (None: only when stderr is a terminal). A Ctrl-C during a grey-box fit
            returns the last accepted iterate, flagged not converged and interrupted (see
            :func:`sysid.continuous.fit.fit_greybox`). Polynomial fits are short and show no
            bar.

    Returns:
        :class:`FitResult`; ``result.model`` is the fitted model (a copy with the data's
        ``Ts``), the input model is left as it was.

    Raises:
        InputValidationError: among others, a polynomial model whose ``Ts`` was set to
            another value than the data's, an option that does not apply to the model or the
            method (e.g. ``x0`` for a polynomial model, ``weights`` for a grey-box one,
            ``alpha`` with a loss that has no tuning constant).
    """
    from ..continuous.greybox import GreyBoxModel  # the continuous package builds on this one

    neural = not isinstance(model, (GreyBoxModel, PolynomialModel)) and isinstance(
        model, torch.nn.Module
    )
    given = {
        "alpha": alpha is not None,
        "weights": weights is not None,
        "init": init is not None,
        "max_iter": max_iter != 100,
        "xtol": xtol is not None,
        "ftol": ftol is not None,
        "iv_iterations": iv_iterations != 2,
        "x0": x0 is not None,
        "segment_length": segment_length is not None,
    }
    if neural or method in ("adam", "lbfgs"):
        kind = "training a neural model (sysid.continuous.training.train)"
        _refuse_options(given, {"x0"}, kind)
    elif isinstance(model, GreyBoxModel):
        applies = {"alpha", "max_iter", "xtol", "ftol", "x0"}
        if criterion == "multiple_shooting":
            applies.add("segment_length")
        _refuse_options(
            given,
            applies,
            f"a grey-box fit with criterion={criterion!r} (it starts from the model's "
            "parameter values)",
        )
    if alpha is not None and loss not in ("fair", "huber"):
        raise InputValidationError(
            f"alpha tunes the fair and Huber losses; loss={loss!r} has no tuning constant: "
            "leave alpha out."
        )
    if neural or method in ("adam", "lbfgs"):
        from ..continuous.training import train

        if loss != "gaussian":
            raise InputValidationError(
                f"training a neural model minimises squared errors; loss={loss!r} is not "
                "available: use loss='gaussian'."
            )
        own = {"model", "data", "method", "criterion", "x0", "progress"}  # passed below
        options = sorted(set(inspect.signature(train).parameters) - own)
        unknown = sorted(set(training) - set(options))
        if unknown:
            raise InputValidationError(
                f"unexpected option(s) {unknown} for training a neural model: the options of "
                f"sysid.continuous.training.train are {options} (with fit's own method, "
                "criterion, x0 and progress)."
            )
        return train(
            model,
            data,
            method="adam" if method is None else method,
            criterion="truncated" if criterion == "prediction" else criterion,
            x0="estimate" if x0 is None else x0,
            progress=progress,
            **training,
        )
    if training:
        raise InputValidationError(
            f"unexpected option(s) {sorted(training)}: they apply to the training of neural "
            "models (method='adam' or 'lbfgs') only."
        )
    if isinstance(model, GreyBoxModel):
        from ..continuous.fit import fit_greybox

        return fit_greybox(
            model,
            data,
            method=method,
            loss=loss,
            alpha=alpha,
            criterion="simulation" if criterion == "prediction" else criterion,
            x0=x0,
            segment_length=segment_length,
            max_iter=max_iter,
            progress=progress,
            **{
                name: value for name, value in (("xtol", xtol), ("ftol", ftol)) if value is not None
            },
        )
    if not isinstance(model, PolynomialModel):
        raise InputValidationError(f"model must be a sysid model, got {type(model).__name__}.")
    if not isinstance(data, IOData):
        raise InputValidationError(f"data must be IOData, got {type(data).__name__}.")
    if loss not in LOSSES:
        raise InputValidationError(f"loss must be one of {LOSSES}, got {loss!r}.")
    if criterion not in ("prediction", "simulation"):
        raise InputValidationError(
            f"criterion must be 'prediction' or 'simulation', got {criterion!r}."
        )
    if alpha is not None:
        _check_alpha(alpha, loss)
    linear = model.is_linear_in_parameters and criterion == "prediction"
    if method is None:
        method = "mle" if loss != "gaussian" else ("lls" if linear else "gauss_newton")
    if method not in METHODS:
        raise InputValidationError(f"method must be one of {METHODS}, got {method!r}.")
    applies = {"alpha", "weights", "init", "max_iter", "xtol", "ftol", "iv_iterations"}
    if method in ("lls", "iv") or (method == "mle" and linear and loss == "gaussian"):  # direct
        applies = {"weights"} | ({"iv_iterations"} if method == "iv" else set())
    _refuse_options(given, applies, f"a polynomial model with method={method!r}")
    if method in ("lls", "iv", "gauss_newton") and loss != "gaussian":
        raise InputValidationError(
            f"method {method!r} minimises squared errors; use method='mle' for loss={loss!r}."
        )
    if method in ("lls", "iv") and criterion == "simulation":
        raise InputValidationError(
            f"method {method!r} minimises one-step prediction errors (a direct solve); "
            "criterion='simulation' (free-run errors) needs an iterative fit: use "
            "method='gauss_newton' or 'mle', or criterion='prediction' with this method."
        )
    if method in ("lls", "iv") and not model.is_linear_in_parameters:
        raise InputValidationError(
            f"method {method!r} needs a model linear in its parameters (FIR, ARX); "
            f"{type(model).__name__} is not: use method='gauss_newton'."
        )
    if model.Ts not in (DEFAULT_TS, data.Ts):
        raise InputValidationError(
            f"the model has Ts = {model.Ts} s but the data Ts = {data.Ts} s: a model fitted to "
            "these data describes their sampling. Build the model with Ts=data.Ts (or without "
            "Ts: the fitted model takes the data's)."
        )
    data = model._check_data(data)  # one output, matching number of inputs
    if data.dtype != model.a.dtype:
        data = data.to(dtype=model.a.dtype)
    batch = data.batch_shape
    model = _batched_model(model, batch)  # a copy: the caller's model is never modified
    model.Ts = data.Ts
    w = _weights(weights, data)
    names = model.parameter_names()

    if method == "lls" or (method == "mle" and linear and loss == "gaussian"):
        result = _fit_lls(model, data, w, method)
    elif method == "iv":
        result = _fit_iv(model, data, iv_iterations)
    else:
        result = _fit_iterative(
            model,
            data,
            method,
            loss,
            alpha,
            w,
            criterion,
            init,
            linear,
            max_iter,
            1e-8 if xtol is None else xtol,
            1e-10 if ftol is None else ftol,
        )
    result.parameter_names = names
    model.set_parameter_vector(result.theta)
    result.model = model
    _diagnose(result, model)
    return result


def _diagnose(result: FitResult, model: PolynomialModel) -> None:
    """Set ``result.stable`` and ``result.messages``; warn about the data sets whose estimate
    did not converge (:class:`ConvergenceWarning`) or is unstable
    (:class:`UnstableModelWarning`)."""
    poles = model.poles()
    modulus = poles.abs().amax(dim=-1) if poles.shape[-1] else torch.zeros(model.batch_shape)
    modulus = modulus.to(result.theta.device)
    result.info["max_pole_modulus"] = modulus
    result.stable = modulus < 1
    info = result.info
    not_converged, unstable = [], []
    singular = info.get("singular", torch.zeros_like(result.converged))
    for idx in _indices(singular):
        not_converged.append(
            f"batch index {idx}: no instrumental-variable estimate (NaN): Z'Phi (instruments "
            "times regressors) is singular: the input does not excite the model (e.g. a "
            "constant or zero input) or the orders are too high. Use a persistently exciting "
            "input, lower the orders, or method='lls'."
        )
    for idx in _indices(~result.converged & ~singular):  # the iterative fits' failures
        m = float(modulus[idx])
        if bool(info["line_search_failed"][idx]):
            why = "the line search found no decrease (damping grew past 1e10)"
        elif bool(info["iteration_limit_reached"][idx]):
            why = f"the iteration limit max_iter = {info['max_iter']} was reached"
        else:
            why = "the iteration stopped away from a stationary point"
        why += (
            f"; a Newton step from the estimate would still move it by "
            f"{float(info['step_in_standard_errors'][idx]):.3g} standard errors "
            f"(converged means <= {STATIONARY_TOL})"
        )
        if bool(info["stationary_point_unstable"][idx]) or m > _BOUNDARY_MODULUS:
            why += (
                f". That step would leave the stable models (the estimate's largest pole "
                f"modulus is {m:.4g}): the data look like the response of an unstable "
                "system, which a model simulated in free run (output error) cannot follow; "
                "fit an ARX or "
                "ARMAX model (their predictors are stable for any A) or use closed-loop data"
            )
        else:
            why += "; raise max_iter, start closer (init=...), or use float64"
        not_converged.append(f"batch index {idx}: did not converge: {why}.")
    for idx in _indices(~result.stable & ~singular):
        unstable.append(
            f"batch index {idx}: the estimated model is unstable (largest pole modulus "
            f"{float(modulus[idx]):.6g} >= 1): its free-run simulation diverges, so "
            "simulation errors and fit percentages are meaningless; the data may come from an "
            "unstable system (or a closed loop): use one-step predictions, not simulations."
        )
    result.messages = not_converged + unstable
    for lines, category, what in (
        (not_converged, ConvergenceWarning, "did not converge"),
        (unstable, UnstableModelWarning, "gave an unstable model"),
    ):
        if lines:
            shown = "\n  ".join(lines[:5])
            more = f"\n  ... and {len(lines) - 5} more" if len(lines) > 5 else ""
            warnings.warn(
                f"fit: {len(lines)} of {result.converged.numel()} data sets {what}:"
                f"\n  {shown}{more}\n(result.messages lists them all; result.converged and "
                "result.stable flag them.)",
                category,
                stacklevel=3,
            )


def _refuse_options(given: dict[str, bool], applies: set[str], kind: str) -> None:
    """Raise naming the options of ``given`` (name -> set by the caller) that ``kind`` does not
    use (``applies``): they would be ignored."""
    unused = sorted(name for name, set_ in given.items() if set_ and name not in applies)
    if unused:
        raise InputValidationError(
            f"fit: {', '.join(unused)} do(es) not apply to {kind} and would be ignored; leave "
            f"{'it' if len(unused) == 1 else 'them'} out (its options here: "
            f"{', '.join(sorted(applies)) or 'none of these'})."
        )


def _indices(mask: torch.Tensor) -> list[tuple[int, ...]]:
    """Batch multi-indices of the True entries of ``mask`` (``()`` for an unbatched one)."""
    return [tuple(int(i) for i in row) for row in torch.nonzero(mask).tolist()]


def _check_alpha(alpha, loss: str) -> None:
    """Raise unless the loss' tuning constant ``alpha`` is finite and > 0 (scalar or per data
    set)."""
    a = torch.as_tensor(alpha, dtype=torch.float64)
    if not bool((torch.isfinite(a) & (a > 0)).all()):
        bad = a.reshape(-1)[~(torch.isfinite(a) & (a > 0)).reshape(-1)][0].item()
        if loss == "huber":
            raise InputValidationError(
                f"alpha of the Huber loss (its threshold c, output units) must be finite and "
                f"> 0, got {bad}: the loss is r^2/2 for |r| <= c and linear beyond. A typical "
                "value is 1.345 sigma with sigma the noise standard deviation; alpha=None uses "
                "1.345 s with s a robust (MAD) scale of the least-squares residuals."
            )
        raise InputValidationError(
            f"alpha of the fair loss must be finite and > 0, got {bad}. alpha (1/output units) "
            "sets where rho(r) = r^2 / (2 (1 + alpha |r|)) (eq. 4.73) turns from quadratic to "
            "linear: at |r| ~ 1/alpha. alpha <= 0 makes the loss non-convex and its standard "
            "errors wrong. A typical value is 1/sigma with sigma the noise standard deviation; "
            "alpha=None uses 1/s with s a robust (MAD) scale of the least-squares residuals."
        )
