"""Initial estimates for the iterative prediction-error fits (the course notes (Modelling and
Simulation), §4.6): least squares for models linear in their parameters, instrumental
variables on an auxiliary ARX model for OE, ARMAX and BJ, an AR fit of the residual for the
noise model of BJ, all stabilised so that the first predictor is stable (eq. 4.132 divides by
``C F``)."""

from __future__ import annotations

import warnings

import torch

from ..data import IOData
from ..errors import PoorExcitationWarning
from ..models import ARX, PolynomialModel
from ._data import _copy_model, _groups, _with_outputs
from .least_squares import _instrumental_variables, _least_squares


def _aux_arx(model: PolynomialModel, na: int, nb, nk, batch) -> ARX:
    """An auxiliary ARX model (``nb = 0`` allowed: an AR model of a residual)."""
    return ARX(
        na,
        nb,
        nk,
        n_inputs=model.n_inputs,
        batch_shape=batch,
        dtype=model.a.dtype,
        device=model.a.device,
        Ts=model.Ts,
    )


def _initial_estimate(model: PolynomialModel, data: IOData) -> torch.Tensor:
    """A stable, consistent-ish starting point ``(*batch, p)``.

    ARX/FIR: least squares. OE and the G-part of BJ: an ARX model with ``na = nf`` fitted by
    instrumental variables (``F = A``). ARMAX: A, B by instrumental variables, ``C = 1``.
    BJ: then ``D`` from an AR(nd) least-squares fit to the residual ``y - B/F u``, ``C = 1``.
    Finally roots of C, D, F outside the unit circle are reflected inside.

    Two cases get no data-based start: a general model with both A and some F_i starts from
    the model's current parameters (zeros unless set), and a model without B parameters
    (no input part) starts from zeros.
    """
    batch = data.batch_shape
    g = _groups(model)
    theta0 = torch.zeros(*batch, model.n_params, dtype=data.dtype, device=data.device)
    has_f = any(len(ix) for ix in g["f"])
    if model.na and has_f:
        return model.parameter_vector().detach().expand(*batch, model.n_params).clone()
    if model.is_linear_in_parameters:
        Phi, target = model.regression(data)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", PoorExcitationWarning)
            return _least_squares(Phi, target)[0]
    nb = [len(ix) for ix in g["b"]]
    if not any(nb):
        return theta0
    na_aux = model.na if model.na else max(model.nf)
    aux = _aux_arx(model, na_aux, nb, model.nk, batch)
    th_aux, *_ = _instrumental_variables(aux, data)
    a_aux, b_aux = th_aux[..., :na_aux], th_aux[..., na_aux:]
    if model.na:
        theta0[..., g["a"][0]] = a_aux
    for ix, bpart in zip(g["b"], torch.split(b_aux, nb, dim=-1), strict=True):
        theta0[..., ix] = bpart
    for ix in g["f"]:
        theta0[..., ix] = a_aux[..., : len(ix)]
    if g["d"] and len(g["d"][0]):
        nd = len(g["d"][0])
        v = data.y - model.simulate(data, theta=theta0)
        ar = _aux_arx(model, nd, 0, 0, batch)
        ar_data = _with_outputs(data, v)
        Phi, target = ar.regression(ar_data)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", PoorExcitationWarning)
            theta0[..., g["d"][0]] = _least_squares(Phi, target)[0][..., :nd]
    holder = _copy_model(model, batch)
    holder.set_parameter_vector(theta0)
    holder.stabilize()
    return holder.parameter_vector().detach()
