"""Training of neural continuous-time models by truncated simulation (``sysid.fit`` with
``method="adam"`` or ``"lbfgs"``).

A model is any ``torch.nn.Module`` with ``nx``, ``nu``, ``ny``, ``method``, ``substeps``,
``forward(t, x, u) -> dx/dt`` (1/s), ``output(x, u)``, ``physical_parameters()`` and
``to_physical(name, raw)`` (``NeuralODE``, ``HybridODE``, ``LagrangianNetwork``, or a user
module following the same contract). The criterion ``"truncated"`` is the mean squared output
error of short free-run simulations (windows of ``T`` sample intervals)

    V = 1 / (W (T+1) ny) sum_w sum_{j=0..T} || y_{k_w + j} - yhat_{w, j} ||^2,

each window ``w`` simulated from its own initial state at sample ``k_w`` by the model's
fixed-step Runge-Kutta method (``substeps`` steps per interval), all windows of a minibatch
in one batched simulation through :func:`integrators.odeint` (gradients by autograd through
the explicit stages, by the implicit function theorem through the stage equations of implicit
methods; the course notes (Modelling and Simulation), chapter 8). The input between samples
follows the data's ``intersample`` (:mod:`sysid.continuous.intersample`); windows are
simulated on a local clock ``t = 0, Ts, ..., T Ts`` (the models are time-invariant: ``t`` is
the time since the window's start).

Initial states of the windows (``x0=``): ``"estimate"`` (a free table with one row per
possible window start, trained jointly; started at the measured outputs where the model's
output map returns the leading states, zero elsewhere), ``"encoder"`` (a small MLP from the
``n_init`` samples of outputs and inputs before the window, which then starts at ``k >=
n_init``) or ``"zero"``.

For models with physical parameters, the covariance of their unconstrained values is the
physical block of ``sigma^2 (J'J)^{-1}`` (the eq. 4.101 form) with ``J`` the Jacobian of
the full-record free-run residuals with respect to those values, the network weights and
the records' estimated initial states (``x0="estimate"`` or ``"encoder"``): the network
and the initial states are nuisance parameters.
Computed as ``sigma^2 (J_p' (I - P) J_p)^{-1}`` with ``P`` the projection onto the column
span of the nuisance Jacobian (its numerical rank from an SVD; an over-parameterised network
spans fewer directions than it has weights), and ``sigma^2 = r'r / (M - p - rank)``; ``J``
is never held whole: it is built by forward sensitivities in windows of the record and
folded into its triangular QR factor, which has the same column geometry. A
physical effect the network can imitate thus widens the physical standard errors instead of
hiding in the weights. The result is mapped to physical units by the delta method through
``to_physical``.
"""

from __future__ import annotations

import copy
import math
import os
import warnings
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import nn

from integrators import odeint, sensitivities
from integrators.errors import InputValidationError
from integrators.inputs import CollocationInput
from integrators.jacobians import batch_jacobian
from integrators.methods import resolve_method

from .._progress import progress_bar
from ..data import IOData
from ..errors import UnstableModelWarning
from ..estimation.results import FitResult, inverse_normal_matrix_and_rank
from ..validation import fit_quality
from .intersample import input_between_samples, stage_fractions

__all__ = ["METHODS", "X0_MODES", "TrainingResult", "simulate", "train"]

METHODS = ("adam", "lbfgs")
X0_MODES = ("estimate", "encoder", "zero")
_CONTRACT = ("nx", "nu", "ny", "method", "substeps", "output", "physical_parameters")
_STATUSES = ("completed", "early_stopped", "non_finite", "stopped")


# --------------------------------------------------------------------------- records
class _Records:
    """The experiments of a data set laid end to end: ``u`` (B, Ntot, nu), ``y`` (B, Ntot,
    ny) with the batch flattened to ``B``, the input between samples ``between`` (B, Ntot, q,
    nu) (row ``g`` holds interval ``g``; the last row of every experiment is padding) and the
    offsets of the experiments along time."""

    def __init__(self, data: IOData, model, dtype, device):
        parts = data.experiment_list
        tab = resolve_method(model.method).tableau(None)
        tau = stage_fractions(tab, int(model.substeps))
        #: nodes of the collocation input: the stage fractions and both ends of the
        #: interval, so that the continuous interpolants (foh, cubic, bl) agree at t_k when
        #: the solver looks the input up by time
        self.nodes = np.unique(np.concatenate([tau, [0.0, 1.0]]))
        self.intersample = data.intersample
        self.Ts = data.Ts
        us, ys, bs = [], [], []
        self.offsets, self.lengths = [], []
        off = 0
        for part in parts:
            B = math.prod(part.batch_shape)  # explicit: an input-free record (nu = 0) is empty
            u = part.u.to(dtype=dtype, device=device).reshape(B, part.N, part.nu)
            y = part.y.to(dtype=dtype, device=device).reshape(B, part.N, part.ny)
            us.append(u)
            ys.append(y)
            if self.intersample != "zoh" and part.N >= 2:
                b = input_between_samples(u, self.intersample, self.nodes)
                bs.append(torch.cat([b, b[..., -1:, :, :]], -3))
            self.offsets.append(off)
            self.lengths.append(part.N)
            off += part.N
        self.u = torch.cat(us, -2)
        self.y = torch.cat(ys, -2)
        self.between = torch.cat(bs, -3) if bs else None
        self.B = self.u.shape[0]

    def starts(self, T: int, kmin: int) -> torch.Tensor:
        """(S,) global start indices of the windows of T intervals starting at ``k >= kmin``
        inside one experiment."""
        pieces = [
            off + torch.arange(kmin, N - T, dtype=torch.int64)
            for off, N in zip(self.offsets, self.lengths, strict=True)
        ]
        return torch.cat(pieces)

    def tiling(self, T: int, kmin: int) -> torch.Tensor:
        """(S,) global starts of non-overlapping windows of T intervals covering every
        experiment from ``kmin`` (the last one shifted back to end at the record's end)."""
        pieces = []
        for off, N in zip(self.offsets, self.lengths, strict=True):
            k = torch.arange(kmin, N - T, T, dtype=torch.int64)
            if int(k[-1]) != N - 1 - T:
                k = torch.cat([k, torch.tensor([N - 1 - T])])
            pieces.append(off + k)
        return torch.cat(pieces)


class _Trainable(nn.Module):
    """The model being trained with its initial-state parameterisation (one ``state_dict``
    for checkpoints)."""

    def __init__(self, model, x0_mode, records, n_init, hidden, generator, output_is_state):
        super().__init__()
        self.model, self.x0_mode, self.n_init = model, x0_mode, n_init
        self.x0_table = None
        self.encoder = None
        nx, ny = model.nx, model.ny
        dtype, device = records.u.dtype, records.u.device
        if x0_mode == "estimate":
            table = torch.zeros(records.B, records.u.shape[-2], nx, dtype=dtype, device=device)
            if output_is_state:
                table[..., :ny] = records.y
            self.x0_table = nn.Parameter(table)
        elif x0_mode == "encoder":
            self.encoder = _encoder(n_init * (model.ny + model.nu), hidden, nx, generator)
            self.encoder.to(dtype=dtype, device=device)

    def initial_states(self, records: _Records, b: torch.Tensor, g: torch.Tensor):
        """(W, nx) initial states of the windows starting at sample ``g`` of record ``b``."""
        if self.x0_mode == "estimate":
            return self.x0_table[b, g]
        if self.x0_mode == "encoder":
            return _encode(self.encoder, records, b, g, self.n_init)
        return records.u.new_zeros(b.shape[0], self.model.nx)


def _encode(encoder, records: _Records, b, g, n_init: int) -> torch.Tensor:
    """(W, nx) states at sample ``g`` of record ``b`` from the ``n_init`` outputs and inputs
    before it (samples ``g - n_init, ..., g - 1``)."""
    dev = records.u.device
    idx = g[:, None].to(dev) - n_init + torch.arange(n_init, device=dev)
    bb = b[:, None].to(dev)
    past = torch.cat([records.y[bb, idx], records.u[bb, idx]], -1)
    return encoder(past.flatten(-2))


def _encoder(n_in: int, hidden: int, nx: int, generator: torch.Generator) -> nn.Sequential:
    """A one-hidden-layer tanh MLP (n_in -> hidden -> nx), initialised from ``generator``
    (PyTorch's default uniform bounds, 1/sqrt(fan_in))."""
    net = nn.Sequential(nn.Linear(n_in, hidden), nn.Tanh(), nn.Linear(hidden, nx))
    with torch.no_grad():
        for layer in (net[0], net[2]):
            bound = 1.0 / math.sqrt(layer.in_features)
            layer.weight.uniform_(-bound, bound, generator=generator)
            layer.bias.uniform_(-bound, bound, generator=generator)
    return net


# --------------------------------------------------------------------------- simulation
def _window_inputs(records: _Records, b, g, T: int):
    """The clock ``t`` (T+1,), the input for the integrators (samples held, or a
    :class:`~integrators.inputs.CollocationInput` between them) and the input samples
    (W, T+1, nu) of the windows of T intervals from sample ``g`` of record ``b`` (W,)."""
    dev = records.u.device
    idx = g[:, None].to(dev) + torch.arange(T + 1, device=dev)
    bb = b[:, None].to(dev)
    u_win = records.u[bb, idx]  # (W, T+1, nu)
    t = records.Ts * torch.arange(T + 1, dtype=records.u.dtype, device=dev)
    if records.intersample == "zoh":
        return t, u_win, u_win  # held over the closed step (notes eq. 8.34)
    coeff = records.between[bb, idx[:, :-1]]  # (W, T, q, nu)
    return t, CollocationInput(coeff, t, nodes=records.nodes), u_win


def _simulate_windows(model, records: _Records, x0, b, g, T: int) -> torch.Tensor:
    """Outputs (W, T+1, ny) of the windows of T intervals from sample ``g`` of record ``b``
    (W,), started at ``x0`` (W, nx); one batched fixed-step simulation."""
    t, u, u_win = _window_inputs(records, b, g, T)
    options = {"adaptive": False, "substeps": int(model.substeps)}
    if resolve_method(model.method).tableau(None).is_explicit:
        options["compile"] = False
    sol = odeint(model, x0, t, method=model.method, u=u, **options)
    return model.output(sol.x, u_win)


def simulate(model, data: IOData, *, x0=None, encoder=None, n_init: int = 0) -> torch.Tensor:
    """Free-run outputs of a neural continuous-time model on the inputs of ``data``.

    Args:
        model: a module following the neural-model contract (module docstring).
        data: :class:`IOData`; its ``u``, ``Ts``, ``intersample`` and experiments.
        x0: initial state (nx,) or (*batch, nx) at sample 0 of every experiment (default
            zero); ignored when ``encoder`` is given.
        encoder: the initial-state encoder of a training with ``x0="encoder"``: the states
            at sample ``n_init`` come from the ``n_init`` samples before it.
        n_init: samples before the simulation's start (with ``encoder``).

    Returns:
        (*batch, N, ny) outputs (experiments concatenated along time, like ``data.y``); the
        first ``n_init`` samples of every experiment are NaN when an encoder is used.
    """
    p = next(iter(model.parameters()), None)
    dtype = p.dtype if p is not None else data.dtype
    records = _Records(data, model, dtype, data.device)
    out = []
    with torch.no_grad():
        for off, N in zip(records.offsets, records.lengths, strict=True):
            k0 = n_init if encoder is not None else 0
            b = torch.arange(records.B)
            g = torch.full((records.B,), off + k0, dtype=torch.int64)
            if encoder is not None:
                start = _encode(encoder, records, b, g, n_init)
            elif x0 is None:
                start = records.u.new_zeros(records.B, model.nx)
            else:
                start = _initial_state(x0, data, model.nx, dtype)
            y = _simulate_windows(model, records, start, b, g, N - 1 - k0)
            pad = y.new_full((records.B, k0, model.ny), math.nan)
            out.append(torch.cat([pad, y], -2))
    y = torch.cat(out, -2)
    return y.reshape(*data.batch_shape, records.u.shape[-2], model.ny)


def _initial_state(x0, data: IOData, nx: int, dtype) -> torch.Tensor:
    """``x0`` of :func:`simulate`, (nx,) or (*batch, nx), as (B, nx) with the batch
    flattened."""
    start = torch.as_tensor(x0, dtype=dtype, device=data.device)
    shape = (*data.batch_shape, nx)
    try:
        return start.expand(shape).reshape(-1, nx)
    except RuntimeError:
        raise InputValidationError(
            f"simulate: x0 has shape {tuple(start.shape)}; give one state ({nx},) or one per "
            f"data set {shape} (the model has nx = {nx}, the data batch {tuple(data.batch_shape)})."
        ) from None


# --------------------------------------------------------------------------- result
@dataclass
class TrainingResult(FitResult):
    """:class:`~sysid.estimation.results.FitResult` of a training, with

    Attributes:
        status: ``"completed"`` (every epoch ran), ``"early_stopped"`` (the validation loss
            did not improve for ``patience`` epochs), ``"non_finite"`` (a non-finite loss or
            gradient: the best model so far was restored and the training stopped) or
            ``"stopped"`` (the callback asked to stop).
        converged: status ``"completed"`` or ``"early_stopped"`` and ``stable``.
        stable: whether the free run of the trained model over the training records stays
            finite (its residuals and their sum of squares) and its residuals within 1000
            times the outputs in norm (beyond, the fit is below -99 900 %); where it diverges,
            ``sigma2``, the standard errors and fit percentages are meaningless, a message
            says so and :class:`~sysid.errors.UnstableModelWarning` is issued.
        train_loss: (epochs_run,) training loss of every epoch: ``"adam"``, the mean of its
            minibatch losses (each before its update); ``"lbfgs"``, the criterion on the
            fixed windows after the epoch's step.
        validation_loss: (epochs_run,) free-run validation loss per epoch (NaN without
            ``validation``).
        params: name -> physical value of the physical parameters (empty for a network).
        x0_table: (*batch, Ntot, nx) estimated initial states (``x0="estimate"``) or None.
        encoder: the initial-state encoder (``x0="encoder"``) or None; n_init: its window.
    """

    status: str = "completed"
    train_loss: torch.Tensor | None = None
    validation_loss: torch.Tensor | None = None
    params: dict = field(default_factory=dict)
    x0_table: torch.Tensor | None = None
    encoder: nn.Module | None = None
    n_init: int = 0

    def simulate(self, data: IOData, x0=None) -> torch.Tensor:
        """Free-run outputs (*batch, N, ny) of the trained model on ``data`` (from the
        encoder's state at ``n_init`` where one was trained, else from ``x0``, default
        zero); see :func:`simulate`."""
        return simulate(self.model, data, x0=x0, encoder=self.encoder, n_init=self.n_init)

    def validate(self, data: IOData, skip: int | None = None, x0=None) -> dict:
        """Free-run diagnostics on ``data``, skipping the first ``skip`` samples of every
        experiment (default ``n_init``; an initialisation window that absorbs the transient
        of a wrong initial state).

        Args:
            data: :class:`IOData` with the model's channels.
            skip: an integer in ``[0, N_e - 2]`` for every experiment ``e`` (the rule of
                :meth:`IOData.samples_after`), at least ``n_init`` where an encoder was
                trained (its simulation starts at sample ``n_init``).
            x0: initial state of the free run without an encoder (see :func:`simulate`).

        Returns:
            dict of (*batch, ny) tensors: ``"fit_percent"`` (MATLAB's fit), ``"rmse"`` (output
            units) and ``"r2"`` (coefficient of determination, ``1 - SSE/SST`` per channel),
            from :func:`sysid.validation.fit_quality` over the samples kept.
        """
        _check_data(data, self.model, "validate")
        skip = self.n_init if skip is None else skip
        try:
            keep = data.samples_after(skip)
        except InputValidationError as exc:
            raise InputValidationError(f"validate: {exc}") from None
        if self.encoder is not None and skip < self.n_init:
            raise InputValidationError(
                f"validate: skip = {skip} keeps samples before the encoder's n_init = "
                f"{self.n_init}, where the simulation has not started; use skip >= "
                f"{self.n_init}."
            )
        yhat = self.simulate(data, x0=x0)
        quality = fit_quality(data.y[..., keep, :].to(yhat.dtype), yhat[..., keep, :])
        return {"fit_percent": quality.fit_percent, "rmse": quality.rmse, "r2": quality.r_squared}


# --------------------------------------------------------------------------- checks
def _check_model(model) -> None:
    missing = [a for a in _CONTRACT if not hasattr(model, a)]
    if not isinstance(model, nn.Module) or missing:
        raise InputValidationError(
            f"method 'adam' / 'lbfgs' trains a neural continuous-time model: an nn.Module "
            f"with {', '.join(_CONTRACT)}, forward(t, x, u) and to_physical(name, raw) "
            f"(NeuralODE, HybridODE, LagrangianNetwork); {type(model).__name__} lacks "
            f"{missing or 'being an nn.Module'}."
        )


def _check_data(data, model, where: str) -> None:
    if not isinstance(data, IOData):
        raise InputValidationError(f"{where}: data must be IOData, got {type(data).__name__}.")
    if data.nu != model.nu or data.ny != model.ny:
        raise InputValidationError(
            f"{where}: the data have nu = {data.nu} inputs and ny = {data.ny} outputs but the "
            f"model has nu = {model.nu}, ny = {model.ny}; build the model for these channels."
        )
    for name, x in (("u", data.u), ("y", data.y)):
        bad = ~torch.isfinite(x)
        if bool(bad.any()):
            first = tuple(torch.nonzero(bad)[0].tolist())
            raise InputValidationError(
                f"{where}: {name} contains a non-finite value at index {first} (time index "
                f"{first[-2]}); clean or interpolate the data before training."
            )


def _positive_int(value, name: str) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
        raise InputValidationError(f"{name} must be an integer >= 1, got {value!r}.")
    return int(value)


def _integer(value, name: str) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise InputValidationError(f"{name} must be an integer, got {value!r}.")
    return int(value)


def _real(value, name: str, *, positive: bool) -> float:
    """``value`` as a finite float, > 0 where ``positive``, else >= 0."""
    real = isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, bool)
    if not real or not math.isfinite(value) or value < 0 or (positive and value == 0):
        bound = "> 0" if positive else ">= 0"
        raise InputValidationError(f"{name} must be a finite number {bound}, got {value!r}.")
    return float(value)


def _curriculum(horizon) -> list[tuple[int, int]]:
    """``horizon`` as a sorted list of (first epoch, T)."""
    if isinstance(horizon, (int, np.integer)) and not isinstance(horizon, bool):
        return [(0, _positive_int(horizon, "horizon"))]
    try:
        stages = sorted((int(e), _positive_int(T, "horizon T")) for e, T in horizon)
    except (TypeError, ValueError) as exc:
        raise InputValidationError(
            f"horizon must be an integer T >= 1 or a list of (epoch, T) pairs such as "
            f"[(0, 10), (200, 50)], got {horizon!r}."
        ) from exc
    if not stages or stages[0][0] != 0:
        raise InputValidationError(
            f"horizon: the curriculum {horizon!r} must start at epoch 0, e.g. [(0, 10), ...]."
        )
    return stages


def _horizon_at(stages, epoch: int) -> int:
    return [T for e, T in stages if e <= epoch][-1]


def _output_is_state(model, dtype, device) -> bool:
    """Whether ``model.output(x, u)`` returns the leading ``ny`` states (probed at one
    point)."""
    gen = torch.Generator().manual_seed(0)
    x = torch.randn(2, model.nx, generator=gen, dtype=dtype).to(device)
    u = torch.randn(2, model.nu, generator=gen, dtype=dtype).to(device)
    with torch.no_grad():
        y = model.output(x, u)
    return model.ny <= model.nx and torch.equal(y, x[..., : model.ny])


# --------------------------------------------------------------------------- training
def train(
    model,
    data: IOData,
    *,
    method: str = "adam",
    criterion: str = "truncated",
    horizon=10,
    batch_size: int = 32,
    epochs: int = 100,
    steps_per_epoch: int | None = None,
    lr: float = 1e-2,
    schedule=None,
    weight_decay: float = 0.0,
    clip: float | None = None,
    x0: str = "estimate",
    n_init: int = 10,
    encoder_hidden: int = 32,
    validation: IOData | None = None,
    patience: int | None = None,
    seed: int = 0,
    checkpoint: str | os.PathLike | None = None,
    checkpoint_every: int = 1,
    callback=None,
    lbfgs_max_iter: int = 20,
    progress: bool | None = None,
) -> TrainingResult:
    """Train a neural continuous-time model on ``data`` by the truncated simulation error.

    Args:
        model: an ``nn.Module`` following the neural-model contract (module docstring). It is
            never modified: the trained model is ``result.model``, a deep copy moved to the
            data's device and dtype.
        data: :class:`IOData` ``(*batch, N, nu)`` / ``(*batch, N, ny)``, one or several
            experiments; every batch member and experiment is a record of the same system.
        method: ``"adam"`` (minibatches of random windows; ``torch.optim.Adam``) or
            ``"lbfgs"`` (``torch.optim.LBFGS`` with strong-Wolfe line search, full batch: the
            fixed windows tiling every record, one ``step`` of ``lbfgs_max_iter`` iterations
            per epoch).
        criterion: ``"truncated"`` (the only one for neural models).
        horizon: window length ``T`` in sample intervals, or a curriculum ``[(epoch, T),
            ...]`` (from each listed epoch on, that ``T``; the first at epoch 0).
        batch_size: windows per minibatch (``"adam"``).
        epochs: number of epochs (the total, also when resuming; a checkpoint of a completed
            training trains on to a larger total, without a ``schedule``).
        steps_per_epoch: minibatches per epoch, an integer >= 1; None: ``ceil(B * Ntot /
            (batch_size * T))``, about one pass over the samples.
        lr: learning rate. schedule: None, ``"cosine"`` (cosine annealing to 0 over
            ``epochs``) or a factory ``optimizer -> torch.optim.lr_scheduler.*``, stepped once
            per epoch. weight_decay: Adam's L2 penalty. lr and weight_decay: finite, >= 0.
        clip: clip the gradient to this global norm, finite and > 0 (None: no clipping).
        x0: ``"estimate"``, ``"encoder"`` or ``"zero"`` (module docstring).
        n_init, encoder_hidden: encoder window (samples) and hidden width (integers >= 1).
        validation: :class:`IOData` for early stopping: its loss is the mean squared
            free-run error of every record from its start (from the encoder's state at
            ``n_init`` with ``x0="encoder"``, from zero with ``x0="zero"``, else from the
            states the output selects, zero for the others). With validation the best
            model by validation loss is returned.
        patience: stop after this many epochs (an integer >= 1) without a decrease of the
            validation loss (without validation: of the criterion on the fixed windows tiling
            the records, evaluated after every epoch); None: never.
        seed: an integer; seeds the ``torch.Generator`` that draws the windows and initialises the
            encoder: two runs with the same seed give identical parameters.
        checkpoint: path of a checkpoint file: model, initial states, optimiser, scheduler,
            generator state, history and early-stopping state, written atomically every
            ``checkpoint_every`` epochs and at the end. If the file exists, training resumes
            from it and ends bit-identical to an uninterrupted run with the same arguments.
        callback: ``callback(epoch, result_so_far: dict) -> bool | None`` after every epoch
            (after the checkpoint); True stops the training (status ``"stopped"``). The dict
            holds the history (``"train"``, ``"val"``, ``"best"``, ...) and ``"model"``, the
            model being trained (read it, e.g. to evaluate a metric of your own; do not
            modify it).
        lbfgs_max_iter: L-BFGS iterations per epoch (integer >= 1).
        progress: tqdm bar over the epochs with train / validation loss: None (when stderr
            is a terminal), True or False.

    Returns:
        :class:`TrainingResult`.

    Non-finite guard: a non-finite loss or gradient restores the best model so far (the
    initial one before any finite epoch), stops and sets status ``"non_finite"`` with a
    message naming the epoch and step.

    Raises:
        InputValidationError: a model off the contract, data whose channels do not match the
            model or that hold NaN, an unknown method / criterion / x0 mode, a horizon
            longer than the shortest record allows, bad integer or real options, a checkpoint of
            another configuration.
    """
    _check_model(model)
    if method not in METHODS:
        raise InputValidationError(f"method must be one of {METHODS} for a neural model.")
    if criterion != "truncated":
        raise InputValidationError(
            f"criterion must be 'truncated' for a neural model (windows of `horizon` "
            f"intervals simulated from their own initial states), got {criterion!r}."
        )
    if x0 not in X0_MODES:
        raise InputValidationError(f"x0 must be one of {X0_MODES}, got {x0!r}.")
    _check_data(data, model, "fit")
    if validation is not None:
        _check_data(validation, model, "fit (validation)")
    batch_size = _positive_int(batch_size, "batch_size")
    epochs = _positive_int(epochs, "epochs")
    checkpoint_every = _positive_int(checkpoint_every, "checkpoint_every")
    if steps_per_epoch is not None:
        steps_per_epoch = _positive_int(steps_per_epoch, "steps_per_epoch (or None)")
    lbfgs_max_iter = _positive_int(lbfgs_max_iter, "lbfgs_max_iter")
    encoder_hidden = _positive_int(encoder_hidden, "encoder_hidden")
    if patience is not None:
        patience = _positive_int(patience, "patience (or None: never stop early)")
    seed = _integer(seed, "seed")
    lr = _real(lr, "lr", positive=False)
    weight_decay = _real(weight_decay, "weight_decay", positive=False)
    if clip is not None:
        clip = _real(clip, "clip (the largest gradient norm, or None: no clipping)", positive=True)
    n_init = _positive_int(n_init, "n_init") if x0 == "encoder" else 0
    stages = _curriculum(horizon)
    shortest = min(data.lengths)
    longest_T = max(T for _, T in stages)
    if longest_T > shortest - 1 - n_init:
        after = f" after the encoder's n_init = {n_init}" if n_init else ""
        raise InputValidationError(
            f"horizon T = {longest_T} intervals does not fit the shortest experiment of "
            f"N = {shortest} samples{after}: T must be <= {shortest - 1 - n_init}. Shorten "
            "the horizon."
        )
    if validation is not None and min(validation.lengths) < n_init + 2:
        raise InputValidationError(
            f"validation experiments need more than n_init + 1 = {n_init + 1} samples."
        )

    dtype, device = data.dtype, data.device
    trained = copy.deepcopy(model).to(dtype=dtype, device=device)
    generator = torch.Generator().manual_seed(seed)
    records = _Records(data, trained, dtype, device)
    out_is_state = _output_is_state(trained, dtype, device)
    net = _Trainable(trained, x0, records, n_init, encoder_hidden, generator, out_is_state)
    val_records = None if validation is None else _Records(validation, trained, dtype, device)
    params = [p for p in net.parameters() if p.requires_grad]
    if method == "adam":
        opt = torch.optim.Adam(params, lr=lr, weight_decay=weight_decay)
    else:
        opt = torch.optim.LBFGS(
            params, lr=lr, max_iter=lbfgs_max_iter, line_search_fn="strong_wolfe"
        )
    scheduler = _scheduler(schedule, opt, epochs)

    state = {
        "epoch": 0,
        "train": [],
        "val": [],
        "best": math.inf,
        "best_state": copy.deepcopy(net.state_dict()),
        "bad_epochs": 0,
        "status": None,
        "messages": [],
    }
    # the options a resumed training must share with the one that wrote the checkpoint
    config = dict(
        method=method,
        horizon=stages,
        batch_size=batch_size,
        steps_per_epoch=steps_per_epoch,
        lr=lr,
        weight_decay=weight_decay,
        clip=clip,
        x0=x0,
        n_init=n_init,
        encoder_hidden=encoder_hidden,
        seed=seed,
        lbfgs_max_iter=lbfgs_max_iter,
    )
    if checkpoint is not None and os.path.exists(checkpoint):
        saved = torch.load(checkpoint, map_location=device, weights_only=False)
        if saved["config"] != config:
            differ = sorted(
                k
                for k in config.keys() | saved["config"].keys()
                if config.get(k) != saved["config"].get(k)
            )
            raise InputValidationError(
                f"checkpoint {os.fspath(checkpoint)!r} was written by a training with "
                f"{saved['config']}, not {config} (differing: {', '.join(differ)}); use "
                "another path to start afresh."
            )
        try:
            net.load_state_dict(saved["net"])
            opt.load_state_dict(saved["optimizer"])
        except (RuntimeError, ValueError) as exc:
            raise InputValidationError(
                f"checkpoint {os.fspath(checkpoint)!r} holds the parameters of another model "
                "or of other data (the initial-state table has one row per sample); use "
                f"another path to start afresh. PyTorch: {exc}"
            ) from None
        if scheduler is not None:
            scheduler.load_state_dict(saved["scheduler"])
        generator.set_state(saved["generator"])
        state = saved["state"]
        if state["status"] == "completed" and state["epoch"] < epochs:
            # a finished training asked for more epochs: train on to the new total
            if scheduler is not None:
                raise InputValidationError(
                    f"checkpoint {os.fspath(checkpoint)!r} holds a training completed after "
                    f"{state['epoch']} epochs under a schedule planned for them; epochs="
                    f"{epochs} cannot extend that schedule: use another path to start afresh."
                )
            state["status"] = None

    bar = progress_bar(epochs, "epochs", progress, unit="epoch")
    bar.update(state["epoch"])
    with bar:
        while state["epoch"] < epochs and state["status"] is None:
            epoch = state["epoch"]
            T = _horizon_at(stages, epoch)
            if method == "adam":
                loss, failure = _adam_epoch(
                    net, records, T, n_init, batch_size, steps_per_epoch, opt, clip, generator
                )
            else:
                loss, failure = _lbfgs_epoch(net, records, T, n_init, opt, clip)
            val = watched = math.nan
            if failure is None:
                if val_records is not None:
                    val = watched = _validation_loss(net, val_records)
                elif method == "lbfgs":  # its loss is already this one, after the step
                    watched = loss
                else:
                    watched = _monitor_loss(net, records, T, n_init)
                if not math.isfinite(watched):
                    failure = "the loss after the epoch's updates is non-finite"
            if failure is not None:
                net.load_state_dict(state["best_state"])
                state["status"] = "non_finite"
                state["messages"].append(
                    f"epoch {epoch}, {failure}: training stopped and the best model so far "
                    f"(loss {state['best']:.6g}) was restored; lower lr, set clip=, or "
                    "shorten the horizon."
                )
                break
            state["train"].append(loss)
            state["val"].append(val)
            if watched < state["best"]:
                state["best"], state["bad_epochs"] = watched, 0
                state["best_state"] = copy.deepcopy(net.state_dict())
            else:
                state["bad_epochs"] += 1
            if scheduler is not None:
                scheduler.step()
            state["epoch"] = epoch + 1
            if patience is not None and state["bad_epochs"] >= patience:
                state["status"] = "early_stopped"
                state["messages"].append(
                    f"early stop after epoch {epoch}: no improvement of the "
                    f"{'validation' if val_records is not None else 'training'} loss for "
                    f"{patience} epochs (best {state['best']:.6g})."
                )
            bar.set_postfix(train=f"{loss:.3g}", val=f"{val:.3g}", T=T)
            bar.update(1)
            if checkpoint is not None and (
                state["epoch"] % checkpoint_every == 0 or state["epoch"] == epochs
            ):
                _save(checkpoint, net, opt, scheduler, generator, state, config)
            if callback is not None and callback(epoch, {**state, "model": net.model}):
                state["status"] = "stopped"
                state["messages"].append(f"stopped by the callback after epoch {epoch}.")
    if state["status"] is None:
        state["status"] = "completed"
    if val_records is not None and state["status"] != "non_finite":
        net.load_state_dict(state["best_state"])
    if checkpoint is not None:
        _save(checkpoint, net, opt, scheduler, generator, state, config)
    return _result(net, records, data, method, state)


def _scheduler(schedule, opt, epochs):
    if schedule is None:
        return None
    if schedule == "cosine":
        return torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=epochs)
    if callable(schedule):
        return schedule(opt)
    raise InputValidationError(
        f"schedule must be None, 'cosine' or a factory optimizer -> scheduler, got {schedule!r}."
    )


def _save(path, net, opt, scheduler, generator, state, config) -> None:
    """Write the checkpoint atomically (a temporary file renamed over ``path``)."""
    tmp = f"{os.fspath(path)}.tmp"
    torch.save(
        {
            "net": net.state_dict(),
            "optimizer": opt.state_dict(),
            "scheduler": None if scheduler is None else scheduler.state_dict(),
            "generator": generator.get_state(),
            "state": state,
            "config": config,
        },
        tmp,
    )
    os.replace(tmp, path)


def _window_loss(net: _Trainable, records: _Records, b, g, T: int):
    """Mean squared output error of the windows, or None where the simulation cannot start
    (a non-finite initial state)."""
    x0 = net.initial_states(records, b, g)
    if not bool(torch.isfinite(x0).all()):
        return None
    try:
        yhat = _simulate_windows(net.model, records, x0, b, g, T)
    except InputValidationError as exc:
        if "is non-finite at the initial time" in str(exc):
            return None
        raise
    dev = records.y.device
    idx = g[:, None].to(dev) + torch.arange(T + 1, device=dev)
    e = records.y[b[:, None].to(dev), idx] - yhat
    return (e * e).mean()


def _finite_gradients(params, clip) -> bool:
    norm = torch.nn.utils.clip_grad_norm_(params, math.inf if clip is None else clip)
    return bool(torch.isfinite(norm))


def _adam_epoch(net, records, T, kmin, batch_size, steps_per_epoch, opt, clip, generator):
    starts = records.starts(T, kmin)
    n = records.B * starts.shape[0]
    steps = steps_per_epoch
    if steps is None:
        steps = max(1, math.ceil(records.B * records.u.shape[-2] / (batch_size * T)))
    params = [p for group in opt.param_groups for p in group["params"]]
    total = 0.0
    for step in range(steps):  # sequential optimiser steps
        pick = torch.randint(n, (batch_size,), generator=generator)
        b, g = pick // starts.shape[0], starts[pick % starts.shape[0]]
        opt.zero_grad(set_to_none=True)
        loss = _window_loss(net, records, b, g, T)
        if loss is None or not bool(torch.isfinite(loss)):
            return math.nan, f"step {step}: the loss is non-finite"
        loss.backward()
        if not _finite_gradients(params, clip):
            return math.nan, f"step {step}: the gradient is non-finite"
        opt.step()
        total += float(loss.detach())
    return total / steps, None


def _lbfgs_epoch(net, records, T, kmin, opt, clip):
    starts = records.tiling(T, kmin)
    S = starts.shape[0]
    b = torch.arange(records.B).repeat_interleave(S)
    g = starts.repeat(records.B)
    params = [p for group in opt.param_groups for p in group["params"]]
    failure = []

    def closure():
        opt.zero_grad(set_to_none=True)
        loss = _window_loss(net, records, b, g, T)
        if loss is None or not bool(torch.isfinite(loss)):
            failure.append("the loss is non-finite")
            return torch.tensor(math.nan, dtype=records.u.dtype)
        loss.backward()
        if not _finite_gradients(params, clip):
            failure.append("the gradient is non-finite")
        return loss

    opt.step(closure)  # (returns the loss before the step)
    if failure:
        return math.nan, "L-BFGS: " + failure[0]
    return _monitor_loss(net, records, T, kmin), None


def _monitor_loss(net: _Trainable, records: _Records, T: int, kmin: int) -> float:
    """The truncated criterion on the fixed windows tiling every record (no gradient): the
    loss that tracks the best model when there is no validation data."""
    starts = records.tiling(T, kmin)
    b = torch.arange(records.B).repeat_interleave(starts.shape[0])
    with torch.no_grad():
        loss = _window_loss(net, records, b, starts.repeat(records.B), T)
    return math.nan if loss is None else float(loss)


def _record_start(net: _Trainable, records: _Records, off: int):
    """(B,) record indices, (B,) start samples and (B, nx) initial states of the free-run
    simulation of the experiment at ``off``: from the encoder at ``n_init``, zero for
    ``x0="zero"``, else the measured states where the output selects them and zero for the
    others (the caller takes the state table's first row on training records)."""
    b = torch.arange(records.B)
    k0 = net.n_init if net.x0_mode == "encoder" else 0
    g = torch.full((records.B,), off + k0, dtype=torch.int64)
    if net.x0_mode == "encoder":
        return b, g, net.initial_states(records, b, g)
    x0 = records.u.new_zeros(records.B, net.model.nx)
    if net.x0_mode == "estimate" and _output_is_state(net.model, records.u.dtype, records.u.device):
        x0[:, : net.model.ny] = records.y[:, off]
    return b, g, x0


def _validation_loss(net: _Trainable, records: _Records) -> float:
    """Mean squared free-run error of every validation record from its start."""
    sse, count = 0.0, 0
    with torch.no_grad():
        for off, N in zip(records.offsets, records.lengths, strict=True):
            b, g, x0 = _record_start(net, records, off)
            if not bool(torch.isfinite(x0).all()):
                return math.nan
            T = N - 1 - (int(g[0]) - off)
            e = records.y[:, int(g[0]) :][:, : T + 1] - _simulate_windows(
                net.model, records, x0, b, g, T
            )
            sse += float((e * e).sum())
            count += e.numel()
    return sse / count


def _record_states(net: _Trainable, records: _Records):
    """Per training record: (B,) record indices, (B,) start samples, (B, nx) initial states
    of its free run (the estimated first row, the encoder's state or zero) and the number
    of intervals."""
    out = []
    for off, N in zip(records.offsets, records.lengths, strict=True):
        b, g, x0 = _record_start(net, records, off)
        if net.x0_mode == "estimate":
            x0 = net.x0_table[b, g]
        out.append((b, g, x0.detach(), N - 1 - (int(g[0]) - off)))
    return out


def _full_residuals(net: _Trainable, records: _Records) -> torch.Tensor:
    """(M,) free-run residuals of every training record from its initial state."""
    pieces = []
    with torch.no_grad():
        for b, g, x0, T in _record_states(net, records):
            y = records.y[:, int(g[0]) :][:, : T + 1]
            pieces.append((y - _simulate_windows(net.model, records, x0, b, g, T)).reshape(-1))
    return torch.cat(pieces)


#: output rows differentiated per vectorised reverse pass in
#: :func:`_output_parameter_jacobian`
_ROWS_PER_PASS = 256


def _output_parameter_jacobian(model, x, u_win, columns) -> torch.Tensor | None:
    """``d output / d columns`` (T+1, ny, q) at the states ``x`` (T+1, nx), or None where
    the output map does not depend on the parameters (vectorised reverse passes over
    :data:`_ROWS_PER_PASS` output entries at a time)."""
    with torch.enable_grad():
        y = model.output(x, u_win)
        if not y.requires_grad:
            return None
        n = y.numel()
        pieces = []
        for lo in range(0, n, _ROWS_PER_PASS):
            picked = torch.arange(lo, min(n, lo + _ROWS_PER_PASS), device=y.device)
            rows = y.new_zeros(len(picked), n)
            rows[torch.arange(len(picked), device=y.device), picked] = 1.0
            grads = torch.autograd.grad(
                y,
                columns,
                grad_outputs=rows.unflatten(-1, y.shape),
                is_grads_batched=True,
                retain_graph=True,
                allow_unused=True,
            )
            if all(gr is None for gr in grads):
                return None
            pieces.append(
                torch.cat(
                    [
                        (gr if gr is not None else c.new_zeros(len(rows), *c.shape)).reshape(
                            len(rows), -1
                        )
                        for gr, c in zip(grads, columns, strict=True)
                    ],
                    -1,
                )
            )
    return torch.cat(pieces).unflatten(0, y.shape).detach()


#: samples per window of the covariance's forward sensitivities (:func:`_free_run_jacobian`):
#: the Jacobian is reduced window by window to a triangular factor, so its memory is that of
#: one window, not of the record
_JACOBIAN_WINDOW = 1000


def _free_run_jacobian(
    net: _Trainable, records: _Records, columns: list[torch.Tensor], nuisance_from: int
):
    """``(r, R)``: the free-run residuals (M,) of :func:`_full_residuals` and a triangular
    factor R (k, n) with ``R'R = J'J`` (k <= n), where J (M, n) is their Jacobian with respect
    to the model's parameter tensors ``columns`` (q entries, flattened in order) and then, where
    estimated, the records' initial states (s = records x B x nx entries), with its columns
    rotated so that those from entry ``nuisance_from`` on come first. R spans the same column
    geometry as J (``J = Q R`` for some Q with orthonormal columns): the norms, singular values
    and projections of its columns are J's.

    J comes from forward sensitivities of the model's fixed-step scheme (the course notes
    (Modelling and Simulation), eq. 8.17-8.18 explicit, 8.24-8.28 implicit): a model has few
    states and may have many weights, so ``nx + q`` directions per step beat ``M`` reverse
    passes. Each data set of the batch is one simulation (the weights are shared), run in
    windows of :data:`_JACOBIAN_WINDOW` samples chained by the chain rule
    (``dx/dtheta = A_window B_start + B_window``), each window's rows folded into R by a QR
    factorisation: the memory is one window's, whatever the record length."""
    model = net.model
    names = {id(prm): name for name, prm in model.named_parameters()}
    keys = [names[id(c)] for c in columns]
    sizes = [c.numel() for c in columns]
    theta = torch.cat([c.detach().reshape(-1) for c in columns])
    q = theta.numel()

    def rhs(t, x, u, p):  # the model at the parameter vector p (batch of one)
        values = torch.split(p[0], sizes)
        params = {k: v.reshape(c.shape) for k, v, c in zip(keys, values, columns, strict=True)}
        return torch.func.functional_call(model, params, (t, x, u))

    states = _record_states(net, records)
    nx = model.nx
    n_starts = len(states) * records.B * nx if net.x0_mode != "zero" else 0
    order = torch.cat(
        [torch.arange(nuisance_from, q + n_starts), torch.arange(nuisance_from)]
    )  # nuisance columns first
    residuals, R = [], theta.new_zeros(0, q + n_starts)
    for e, (b, g, x0, T) in enumerate(states):
        for i in range(records.B):
            x_start = x0[i : i + 1]
            dx_dtheta = theta.new_zeros(1, nx, q)
            dx_dx0 = torch.eye(nx, dtype=theta.dtype, device=theta.device)[None]
            for lo in range(0, T, _JACOBIAN_WINDOW):
                L = min(_JACOBIAN_WINDOW, T - lo)
                g_lo = g[i : i + 1] + lo
                t, u, u_win = _window_inputs(records, b[i : i + 1], g_lo, L)
                sens = sensitivities(
                    rhs,
                    x_start,
                    t,
                    theta[None],
                    method=model.method,
                    u=u,
                    substeps=int(model.substeps),
                    input_sensitivities=False,
                    compile=False,
                )
                first = 0 if lo == 0 else 1  # a window's first sample ends the previous one
                x, u_k = sens.x[0, first:], u_win[0, first:]
                A, B = sens.A[0, first:], sens.B[0, first:]
                y, dy_dx = batch_jacobian(lambda xx, uu=u_k: model.output(xx, uu), x)
                dy = dy_dx @ (A @ dx_dtheta + B)  # (L', ny, q)
                direct = _output_parameter_jacobian(model, x, u_k, columns)
                if direct is not None:
                    dy = dy + direct
                rows = [dy]
                if n_starts:
                    start = x.new_zeros(*dy.shape[:-1], n_starts)
                    at = (e * records.B + i) * nx
                    start[..., at : at + nx] = dy_dx @ (A @ dx_dx0)
                    rows.append(start)
                k0 = int(g_lo[0]) + first
                residuals.append((records.y[b[i], k0 : k0 + len(y)] - y).reshape(-1))
                J = -torch.cat(rows, -1).flatten(0, 1)[:, order]
                R = torch.linalg.qr(torch.cat([R, J]), mode="r").R
                x_start = sens.x[:, -1]
                dx_dtheta = sens.A[:, -1] @ dx_dtheta + sens.B[:, -1]
                dx_dx0 = sens.A[:, -1] @ dx_dx0
    return torch.cat(residuals), R


def _project_out(J: torch.Tensor, nuisance: torch.Tensor, rows: int):
    """``(J_perp, rank)``: the part of the columns of ``J`` (k, p) orthogonal to the column
    span of ``nuisance`` (k, q), whose numerical rank (singular values above
    ``max(rows, q) eps`` times the largest, ``rows`` the length of the columns they stand for)
    is ``rank``. A column the nuisance explains to ``sqrt(eps)`` of its norm comes back zero
    (its parameter is not identifiable)."""
    if nuisance.shape[-1] == 0:
        return J, 0
    U, s, _ = torch.linalg.svd(nuisance, full_matrices=False)
    eps = torch.finfo(s.dtype).eps
    U = U[:, s > s[0] * max(rows, nuisance.shape[-1]) * eps]
    J_perp = J - U @ (U.T @ J)
    explained = J_perp.norm(dim=0) <= math.sqrt(eps) * J.norm(dim=0)
    return torch.where(explained, torch.zeros_like(J_perp), J_perp), U.shape[-1]


def _physical_statistics(net: _Trainable, records: _Records):
    """Names, physical values (p,), covariance (p, p), sigma^2 and residuals (M,) of the
    physical parameters, marginal over the network weights and initial states (see the
    module docstring)."""
    model = net.model
    raw = dict(model.physical_parameters())
    names, columns, values = [], [], []
    for name, p in raw.items():
        phys = model.to_physical(name, p.detach()).reshape(-1)
        for i in range(p.numel()):
            names.append(name if p.numel() == 1 else f"{name}[{i}]")
        values.append(phys)
        columns.append(p)
    if not names:
        r = _full_residuals(net, records)
        return names, r.new_zeros(0), r.new_zeros(0, 0), (r**2).sum() / r.numel(), r
    weights = [
        q for q in model.parameters() if q.requires_grad and all(q is not c for c in columns)
    ]
    p = sum(c.numel() for c in columns)
    # R'R = J'J of d r / d (weights, initial states, raw physical values), in that order
    r, R = _free_run_jacobian(net, records, columns + weights, p)
    M = r.numel()
    J_physical, rank = _project_out(R[:, -p:], R[:, :-p], M)
    P, rank_physical = inverse_normal_matrix_and_rank(J_physical)
    sigma2 = (r * r).sum() / max(M - int(rank_physical) - rank, 1)
    cov_raw = sigma2 * P
    blocks = [  # d physical / d raw, one block per named parameter (delta method)
        torch.autograd.functional.jacobian(
            lambda z, n=name, s=prm.shape: model.to_physical(n, z.reshape(s)).reshape(-1),
            prm.detach().reshape(-1),
        )
        for name, prm in raw.items()
    ]
    G = torch.block_diag(*blocks)
    # inf rows/columns (parameters the data do not determine) stay inf and only there
    unknown = ~torch.isfinite(torch.diagonal(cov_raw))
    cov = G @ torch.where(torch.isfinite(cov_raw), cov_raw, 0.0) @ G.T
    affected = (G.abs() @ unknown.to(G.dtype)) > 0
    cov = torch.where(affected.unsqueeze(-1) | affected.unsqueeze(-2), math.inf, cov)
    return names, torch.cat(values), cov, sigma2, r


#: a free run whose residuals exceed this many times the outputs in norm (so that its fit is
#: below -99 900 %) counts as diverged, even where it stays finite
_DIVERGED = 1e3


def _result(net: _Trainable, records: _Records, data: IOData, method: str, state):
    names, theta, cov, sigma2, r = _physical_statistics(net, records)
    se = torch.diagonal(cov).clamp_min(0).sqrt()
    status = state["status"]
    messages = list(state["messages"])
    rss, yss = float((r * r).sum()), float((records.y * records.y).sum())
    stable = math.isfinite(rss) and bool(torch.isfinite(sigma2))
    stable = stable and not (yss > 0 and rss > _DIVERGED**2 * yss)
    if not stable:
        messages.append(
            f"the free run of the trained model over the training records diverges (residual "
            f"sum of squares {rss:.6g}, outputs' {yss:.6g}): sigma2, the standard errors and fit "
            "percentages are meaningless; train longer, lengthen the horizon (short windows do "
            "not constrain the long free run) or start from a stable model."
        )
        warnings.warn(f"fit: {messages[-1]}", UnstableModelWarning, stacklevel=3)
    train_loss = torch.tensor(state["train"], dtype=torch.float64)
    table = None
    if net.x0_table is not None:
        table = net.x0_table.detach().reshape(*data.batch_shape, records.u.shape[-2], -1)
    model = net.model
    model.zero_grad(set_to_none=True)
    return TrainingResult(
        theta=theta.detach(),
        covariance=cov.detach(),
        standard_errors=se.detach(),
        sigma2=sigma2.detach(),
        loss_history=train_loss,
        iterations=torch.tensor(len(state["train"])),
        converged=torch.tensor(stable and status in ("completed", "early_stopped")),
        method=method,
        loss="gaussian",
        parameter_names=names,
        n_samples=r.numel(),
        residuals=r,
        model=model,
        info={"criterion": "truncated", "best_loss": state["best"]},
        messages=messages,
        stable=torch.tensor(stable),
        status=status,
        train_loss=train_loss,
        validation_loss=torch.tensor(state["val"], dtype=torch.float64),
        params={n: float(v) for n, v in zip(names, theta, strict=True)},
        x0_table=table,
        encoder=net.encoder,
        n_init=net.n_init,
    )
