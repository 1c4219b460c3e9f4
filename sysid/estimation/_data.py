"""Data and model plumbing shared by the estimators of :mod:`sysid.estimation`: output
substitution, regression rows, weights, broadcasting checks, parameter groups and model
copies."""

from __future__ import annotations

import torch

from integrators.errors import InputValidationError

from ..data import IOData
from ..models import PolynomialModel


def _with_outputs(data: IOData, y: torch.Tensor) -> IOData:
    """Same inputs and experiment split as ``data`` but outputs ``y`` (``(*batch, N, 1)``)."""
    if data.n_experiments == 1:
        return IOData(data.u, y, data.Ts)
    parts, start = [], 0
    for part in data.experiment_list:
        parts.append(IOData(part.u, y[..., start : start + part.N, :], data.Ts))
        start += part.N
    return IOData.experiments(parts)


def _regression_rows(data: IOData, M: int) -> list[slice]:
    """Slices of the concatenated samples used by a regression with ``M`` rows in all."""
    skip = (data.N - M) // data.n_experiments
    rows, start = [], 0
    for part in data.experiment_list:
        rows.append(slice(start + skip, start + part.N))
        start += part.N
    return rows


def _weights(weights, data: IOData) -> torch.Tensor | None:
    if weights is None:
        return None
    w = torch.as_tensor(weights, dtype=data.dtype, device=data.device)
    if w.dim() >= 2 and w.shape[-1] == 1 and w.shape[-2] == data.N:
        w = w[..., 0]
    if w.shape[-1] != data.N:
        raise InputValidationError(
            f"weights must have shape (*batch, N) with N = {data.N} samples; got {tuple(w.shape)}."
        )
    if bool((~torch.isfinite(w) | (w <= 0)).any()):
        raise InputValidationError("weights must be finite and positive (1 / noise variance).")
    _check_broadcast("weights", w, (*data.batch_shape, data.N), "(*batch, N) or (N,)")
    return w.expand(*data.batch_shape, data.N)


def _check_broadcast(name: str, x: torch.Tensor, shape: tuple, expected: str) -> None:
    """Raise unless ``x`` broadcasts to ``shape`` (the data's batch shape and one more size)."""
    try:
        torch.broadcast_shapes(x.shape, shape)
        ok = x.dim() <= len(shape) and torch.broadcast_shapes(x.shape, shape) == shape
    except RuntimeError:
        ok = False
    if not ok:
        raise InputValidationError(
            f"{name} has shape {tuple(x.shape)}, which does not broadcast to {tuple(shape)}: "
            f"it must be {expected} for data of batch shape {tuple(shape[:-1])}."
        )


def _groups(model: PolynomialModel) -> dict[str, list[list[int]]]:
    """Indices into ``theta`` of each polynomial, by letter (one list per input for b, f)."""
    out: dict[str, list[list[int]]] = {}
    for j, name in enumerate(model.parameter_names()):
        letter = name[0]
        suffix = name.split("_")[1] if "_" in name else ""
        key = letter + suffix
        out.setdefault(key, []).append(j)
    grouped: dict[str, list[list[int]]] = {k: [] for k in "abcdf"}
    for key, idx in out.items():
        grouped[key[0]].append(idx)
    return grouped


def _copy_model(model: PolynomialModel, batch) -> PolynomialModel:
    new = PolynomialModel(
        model.na,
        model.nb,
        model.nc,
        model.nd,
        model.nf,
        model.nk,
        n_inputs=model.n_inputs,
        batch_shape=batch,
        dtype=model.a.dtype,
        device=model.a.device,
        Ts=model.Ts,
    )
    new.__class__ = model.__class__
    return new


def _batched_model(model: PolynomialModel, batch_shape: torch.Size) -> PolynomialModel:
    """A copy of ``model`` with the data's batch shape and the model's parameters (an
    unbatched model's broadcast to every data set); ``model`` itself is not modified."""
    if model.batch_shape not in (batch_shape, torch.Size([])):
        raise InputValidationError(
            f"the model's batch shape {tuple(model.batch_shape)} does not match the data's "
            f"{tuple(batch_shape)}; build the model with batch_shape={tuple(batch_shape)} or "
            "without a batch shape."
        )
    new = _copy_model(model, batch_shape)
    new.set_parameter_vector(model.parameter_vector().detach())
    return new
