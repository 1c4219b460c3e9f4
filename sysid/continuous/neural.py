"""Continuous-time models with learned parts, simulated through the Runge-Kutta layers.

Three model structures share one interface (:class:`ContinuousTimeModel`): attributes ``nx``,
``nu``, ``ny``, ``method`` (a fixed-step method name of :mod:`integrators.methods`) and
``substeps`` (steps per sample interval); ``forward(t, x, u)`` is the right-hand side
``dx/dt`` in physical time units (1/s), ``output(x, u)`` the output map,
``physical_parameters()`` the named physical parameters in unconstrained coordinates and
``to_physical(name, raw)`` their value in physical units.

* :class:`NeuralODE`: ``x' = f_theta(x, u)`` with an MLP ``f_theta``;
* :class:`HybridODE`: ``x' = f_phys(t, x, u, p) + r_theta(x, u)``, the right-hand side of a
  :class:`~sysid.continuous.GreyBoxModel` with its named :class:`~sysid.continuous.Param` s
  plus a residual network on chosen state components;
* :class:`LagrangianNetwork`: a :class:`~sysid.mechanics.LagrangianSystem` whose mass matrix
  ``M(q) = L(q) L(q)^T + eps I``, potential ``V(q)``, Rayleigh dissipation and input map are
  learned, so that the learned model obeys the Lagrange equation (the course notes
  (Modelling and Simulation), eq. 2.40 / 2.112) by construction.

Conventions of the networks (the deepSI / torchid convention):

* normalisation: a network sees ``(x - x_offset) / x_scale`` and ``(u - u_offset) / u_scale``
  (per-channel scales, e.g. the standard deviations of the data);
* time scale: a derivative network predicts the change of the normalised state over one
  sample interval ``Ts``, ``dx/dt = x_scale * net(...) / Ts``, so its outputs are of order one
  while the derivatives are of order ``x_scale / Ts``; ``Ts=None`` takes ``Ts = 1``;
* the last layer starts small (:class:`NeuralODE`: the initial model is close to ``x' = 0``) or
  zero (:class:`HybridODE`: the initial model is exactly the physics);
* initialisation is drawn from a ``torch.Generator`` seeded by ``seed``: two models with the
  same arguments and seed are bit-identical.

float64 by default (``dtype=``); every tensor follows the model's device; states and inputs
carry arbitrary leading batch dimensions (broadcast against each other).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import nn

from integrators._options import check_positive
from integrators.errors import InputValidationError
from integrators.methods import resolve_method

from ..mechanics import LagrangianSystem, _local_graph
from .greybox import GreyBoxModel

__all__ = ["ContinuousTimeModel", "HybridODE", "LagrangianNetwork", "NeuralODE"]

_ACTIVATIONS = {
    "tanh": nn.Tanh,
    "relu": nn.ReLU,
    "softplus": nn.Softplus,
    "elu": nn.ELU,
    "silu": nn.SiLU,
    "gelu": nn.GELU,
    "sigmoid": nn.Sigmoid,
}
#: standard deviation scale of the last layer of a derivative network at initialisation
_SMALL_LAST_LAYER = 1e-2
#: softplus^-1(1): the bias that starts the diagonal of L(q) at one
_SOFTPLUS_INV_ONE = math.log(math.e - 1.0)


# ----------------------------------------------------------------------------- checks
def _check_count(value, name: str, where: str, minimum: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
        raise InputValidationError(
            f"{where}: {name} must be an integer >= {minimum}, got {value!r}."
        )
    return int(value)


def _check_hidden(hidden, where: str) -> tuple[int, ...]:
    if isinstance(hidden, int) and not isinstance(hidden, bool):
        hidden = (hidden,)
    if not isinstance(hidden, Sequence) or isinstance(hidden, str):
        raise InputValidationError(
            f"{where}: hidden must be a sequence of layer widths, e.g. (64, 64), got {hidden!r}."
        )
    widths = tuple(hidden)
    if any(isinstance(w, bool) or not isinstance(w, int) or w < 1 for w in widths):
        raise InputValidationError(
            f"{where}: every hidden layer width must be an integer >= 1, got {widths!r} "
            "(use () for a network without hidden layers)."
        )
    return widths


def _check_activation(activation, where: str):
    if activation not in _ACTIVATIONS:
        raise InputValidationError(
            f"{where}: unknown activation {activation!r}; use one of {sorted(_ACTIVATIONS)}."
        )
    return _ACTIVATIONS[activation]


def _check_method(method, substeps, where: str) -> tuple:
    if method == "auto":
        raise InputValidationError(
            f"{where}: method='auto' chooses an adaptive solver; a model trained through the "
            "Runge-Kutta layers needs a fixed-step method, e.g. 'rk4' or 'radau_iia'."
        )
    resolve_method(method)  # TableauError (an InputValidationError) for an unknown name
    return method, _check_count(substeps, "substeps", where, 1)


def _check_dtype(dtype, where: str) -> torch.dtype:
    if not isinstance(dtype, torch.dtype) or not dtype.is_floating_point:
        raise InputValidationError(
            f"{where}: dtype must be a floating-point torch.dtype, got {dtype!r}."
        )
    return dtype


def _channel_vector(value, n: int, name: str, where: str, default: float, positive: bool, like):
    """A (n,) tensor from None (``default``), a number or n values; finite, > 0 if positive."""
    if value is None:
        return torch.full((n,), default, dtype=like.dtype, device=like.device)
    v = torch.as_tensor(value, dtype=like.dtype, device=like.device).detach().clone()
    if v.dim() > 1 or (v.dim() == 1 and v.shape[0] != n):
        raise InputValidationError(
            f"{where}: {name} must be a number or have shape ({n},) (one per channel), got "
            f"shape {tuple(v.shape)}."
        )
    v = v.expand(n).clone()
    bad = ~torch.isfinite(v) | ((v <= 0) if positive else torch.zeros_like(v, dtype=torch.bool))
    if bool(bad.any()):
        idx = torch.nonzero(bad).reshape(-1).tolist()
        need = "finite and > 0" if positive else "finite"
        raise InputValidationError(
            f"{where}: {name} must be {need}, got {v[idx].tolist()} at channel(s) {idx}."
        )
    return v


def _generator(seed, device) -> torch.Generator | None:
    """A generator seeded by ``seed`` (an int, or a ``torch.Generator`` used as given);
    None draws from torch's global generator."""
    if seed is None or isinstance(seed, torch.Generator):
        return seed
    if isinstance(seed, bool) or not isinstance(seed, int):
        raise InputValidationError(f"seed must be an int, a torch.Generator or None, got {seed!r}.")
    return torch.Generator(device=device).manual_seed(seed)


def _mlp(n_in, n_out, hidden, activation, *, generator, dtype, device, last="default"):
    """An MLP ``n_in -> hidden... -> n_out``; Glorot-uniform weights (gain of the activation
    where torch knows one) and zero biases drawn from ``generator``. ``last``: "default",
    "small" (last weights times :data:`_SMALL_LAST_LAYER`) or "zero" (output exactly 0)."""
    layers, widths = [], (n_in, *hidden, n_out)
    for i in range(len(widths) - 1):
        lin = nn.Linear(widths[i], widths[i + 1], dtype=dtype, device=device)
        with torch.no_grad():
            name = activation.__name__.lower()
            gain = nn.init.calculate_gain(name) if name in ("tanh", "relu", "sigmoid") else 1.0
            nn.init.xavier_uniform_(lin.weight, gain=gain, generator=generator)
            lin.bias.zero_()
        layers.append(lin)
        if i < len(widths) - 2:
            layers.append(activation())
    with torch.no_grad():
        if last == "small":
            layers[-1].weight.mul_(_SMALL_LAST_LAYER)
        elif last == "zero":
            layers[-1].weight.zero_()
    return nn.Sequential(*layers)


# ----------------------------------------------------------------------------- base
class ContinuousTimeModel(nn.Module):
    """The interface of the continuous-time models with learned parts (see the module
    docstring): ``nx``, ``nu``, ``ny``, ``method``, ``substeps``, ``forward(t, x, u)``,
    ``output(x, u)``, ``physical_parameters()``, ``to_physical(name, raw)``."""

    nx: int
    nu: int
    ny: int
    method: str
    substeps: int

    def _states_inputs(self, x, u, where: str):
        """x (*batch, nx) and u (*batch, nu) broadcast to one batch (u None: zeros, nu = 0
        only); InputValidationError for other shapes."""
        name = type(self).__name__
        if not isinstance(x, torch.Tensor) or x.dim() < 1 or x.shape[-1] != self.nx:
            got = tuple(x.shape) if isinstance(x, torch.Tensor) else type(x).__name__
            raise InputValidationError(
                f"{name}.{where}: the state must have shape (*batch, nx) = (*batch, {self.nx}), "
                f"got {got}."
            )
        if u is None:
            if self.nu > 0:
                raise InputValidationError(
                    f"{name}.{where}: the model has nu = {self.nu} inputs; pass u of shape "
                    f"(*batch, {self.nu})."
                )
            return x, x.new_zeros(*x.shape[:-1], 0)
        if not isinstance(u, torch.Tensor) or u.dim() < 1 or u.shape[-1] != self.nu:
            got = tuple(u.shape) if isinstance(u, torch.Tensor) else type(u).__name__
            raise InputValidationError(
                f"{name}.{where}: the input must have shape (*batch, nu) = (*batch, {self.nu}), "
                f"got {got}."
            )
        batch = torch.broadcast_shapes(x.shape[:-1], u.shape[:-1])
        return x.expand(*batch, self.nx), u.to(x).expand(*batch, self.nu)

    def physical_parameters(self) -> dict[str, nn.Parameter]:
        """Name -> the physical parameter in unconstrained coordinates (empty: none)."""
        return {}

    def to_physical(self, name: str, raw: torch.Tensor) -> torch.Tensor:
        """The physical value of parameter ``name`` at the unconstrained value ``raw``."""
        raise InputValidationError(
            f"{type(self).__name__}.to_physical: unknown physical parameter {name!r}; the model "
            f"has {sorted(self.physical_parameters())}."
        )

    def output(self, x, u=None) -> torch.Tensor:
        """``y = x[..., :ny]``, (*batch, ny)."""
        x, _ = self._states_inputs(x, u, "output")
        return x[..., : self.ny]


class _Normalizer(nn.Module):
    """``z = [(x - x_offset) / x_scale, (u - u_offset) / u_scale]``, (*batch, nx + nu); the
    offsets and scales are buffers (per channel)."""

    def __init__(self, nx, nu, x_scale, u_scale, x_offset, u_offset, where, like):
        super().__init__()
        self.register_buffer(
            "x_scale", _channel_vector(x_scale, nx, "x_scale", where, 1.0, True, like)
        )
        self.register_buffer(
            "u_scale", _channel_vector(u_scale, nu, "u_scale", where, 1.0, True, like)
        )
        self.register_buffer(
            "x_offset", _channel_vector(x_offset, nx, "x_offset", where, 0.0, False, like)
        )
        self.register_buffer(
            "u_offset", _channel_vector(u_offset, nu, "u_offset", where, 0.0, False, like)
        )

    def forward(self, x, u):
        return torch.cat(
            [(x - self.x_offset) / self.x_scale, (u - self.u_offset) / self.u_scale], -1
        )


def _time_scale(Ts, where: str) -> float:
    if Ts is None:
        return 1.0
    return 1.0 / check_positive(Ts, f"{where}: Ts", " (the sample time, in s) or None")


# ----------------------------------------------------------------------------- NeuralODE
class NeuralODE(ContinuousTimeModel):
    """A black-box continuous-time model ``x' = x_scale * net(z) / Ts``, ``y = x[..., :ny]``
    or ``y = y_offset + y_scale * g(z)``, with ``z = [(x - x_offset) / x_scale,
    (u - u_offset) / u_scale]``.

    Args:
        nx, nu: numbers of states (>= 1) and inputs (>= 0).
        ny: number of outputs (default ``nx``; at most ``nx`` without an output network).
        hidden: widths of the hidden layers of ``net`` (and ``g``), e.g. (64, 64).
        activation: "tanh" (default), "relu", "softplus", "elu", "silu", "gelu", "sigmoid".
        Ts: time scale in s (the sample time of the data; None: 1): ``net`` predicts the change
            of the normalised state over ``Ts``, so ``dx/dt`` is of order ``x_scale / Ts``.
        x_scale, u_scale, x_offset, u_offset: per-channel normalisation, numbers or (nx,) /
            (nu,) (scales finite and > 0; defaults 1 and 0).
        output_network: learn the output map ``g`` instead of selecting ``x[..., :ny]``;
            ``y_scale``, ``y_offset`` (ny,) de-normalise its output.
        method, substeps: the fixed-step Runge-Kutta method and steps per sample interval.
        seed: int or ``torch.Generator`` of the initialisation (None: torch's global one).
        dtype, device: of the parameters (float64 by default).

    The last layer of ``net`` starts at 1/100 of its Glorot scale, so the initial model is
    close to ``x' = 0``.

    Raises:
        InputValidationError: bad sizes, hidden widths, activation, scales, Ts, method or seed.
    """

    def __init__(
        self,
        nx: int,
        nu: int,
        ny: int | None = None,
        hidden=(64, 64),
        activation: str = "tanh",
        Ts: float | None = None,
        x_scale=None,
        u_scale=None,
        output_network: bool = False,
        method: str = "rk4",
        substeps: int = 1,
        seed=None,
        *,
        x_offset=None,
        u_offset=None,
        y_scale=None,
        y_offset=None,
        dtype: torch.dtype = torch.float64,
        device=None,
    ):
        super().__init__()
        where = "NeuralODE"
        self.nx = _check_count(nx, "nx", where, 1)
        self.nu = _check_count(nu, "nu", where, 0)
        self.ny = self.nx if ny is None else _check_count(ny, "ny", where, 1)
        if not output_network and self.ny > self.nx:
            raise InputValidationError(
                f"{where}: ny = {self.ny} outputs but y = x[..., :ny] has at most nx = {self.nx}; "
                "pass output_network=True for a learned output map."
            )
        hidden = _check_hidden(hidden, where)
        act = _check_activation(activation, where)
        dtype = _check_dtype(dtype, where)
        self.method, self.substeps = _check_method(method, substeps, where)
        self.time_scale = _time_scale(Ts, where)
        self.Ts = Ts
        like = torch.empty(0, dtype=dtype, device=device)
        self.normalizer = _Normalizer(
            self.nx, self.nu, x_scale, u_scale, x_offset, u_offset, where, like
        )
        gen = _generator(seed, like.device)
        n_in = self.nx + self.nu
        kw = {"generator": gen, "dtype": dtype, "device": like.device}
        self.net = _mlp(n_in, self.nx, hidden, act, last="small", **kw)
        self.output_network = None
        if output_network:
            self.output_network = _mlp(n_in, self.ny, hidden, act, **kw)
            self.register_buffer(
                "y_scale", _channel_vector(y_scale, self.ny, "y_scale", where, 1.0, True, like)
            )
            self.register_buffer(
                "y_offset", _channel_vector(y_offset, self.ny, "y_offset", where, 0.0, False, like)
            )

    def forward(self, t, x, u=None) -> torch.Tensor:
        """``dx/dt = x_scale * net(z) / Ts`` (*batch, nx), in state units per second; ``t`` is
        not used (the model is autonomous up to its input)."""
        x, u = self._states_inputs(x, u, "forward")
        z = self.normalizer(x, u)
        return self.normalizer.x_scale * self.net(z) * self.time_scale

    def output(self, x, u=None) -> torch.Tensor:
        """``y`` (*batch, ny): ``x[..., :ny]`` or ``y_offset + y_scale * g(z)``."""
        x, u = self._states_inputs(x, u, "output")
        if self.output_network is None:
            return x[..., : self.ny]
        return self.y_offset + self.y_scale * self.output_network(self.normalizer(x, u))


# ----------------------------------------------------------------------------- HybridODE
class HybridODE(ContinuousTimeModel):
    """Physics plus a residual network: ``x' = f_phys(t, x, u, p) + E r_theta(x, u)``.

    ``f_phys`` and its named parameters ``p`` come from a :class:`GreyBoxModel` (any of its
    kinds of right-hand side: a function ``f(t, x, u, p)``, an ``nn.Module`` such as a zoo
    plant or a :class:`~sysid.mechanics.LagrangianSystem`, an index-1 DAE), evaluated by the
    grey-box model's own right-hand side (:meth:`GreyBoxModel.rhs`). ``E`` places the residual
    ``r_theta = x_scale[idx] * net(z) / Ts`` (normalised input ``z`` as in
    :class:`NeuralODE`) on the state components ``idx`` (``residual_states``). The last layer
    of ``net`` starts at zero, so the initial model is exactly the physics.

    Every free :class:`~sysid.continuous.Param` of the grey-box model is an ``nn.Parameter``
    in its unconstrained coordinate (``Param.to_unconstrained``, so the bounds hold for every
    value); fixed ones are buffers. ``physical_parameters()`` returns the free ones by name.

    Args:
        physics: the :class:`GreyBoxModel` (per-experiment parameters are not supported).
        network: None (an MLP with ``hidden`` / ``activation``) or an ``nn.Module`` mapping
            ``z`` (*batch, nx + nu) to (*batch, len(idx)) (used as given, not zeroed).
        residual_states: indices or state names of the components that get a residual
            (default all).
        nu: number of inputs (default the module's ``nu``; required for a function).
        ny: number of outputs (default: as many as the grey-box output selects, else ``nx``);
            the output is the grey-box model's (selected states or ``h(x, u, p)``).
        Ts, x_scale, u_scale, x_offset, u_offset, seed, dtype, device: as for
            :class:`NeuralODE`.
        method, substeps: default those of ``physics``.

    Raises:
        InputValidationError: not a GreyBoxModel, unknown state names, bad sizes.
    """

    def __init__(
        self,
        physics: GreyBoxModel,
        network: nn.Module | None = None,
        hidden=(64, 64),
        activation: str = "tanh",
        residual_states=None,
        nu: int | None = None,
        ny: int | None = None,
        Ts: float | None = None,
        x_scale=None,
        u_scale=None,
        method=None,
        substeps: int | None = None,
        seed=None,
        *,
        x_offset=None,
        u_offset=None,
        dtype: torch.dtype = torch.float64,
        device=None,
    ):
        super().__init__()
        where = "HybridODE"
        if not isinstance(physics, GreyBoxModel):
            raise InputValidationError(
                f"{where}: physics must be a sysid.continuous.GreyBoxModel, got "
                f"{type(physics).__name__}; wrap the right-hand side as GreyBoxModel(f, params)."
            )
        self.physics = physics
        self.nx = int(physics.nx)
        nu = getattr(physics.f, "nu", None) if nu is None else nu
        if nu is None:
            raise InputValidationError(
                f"{where}: the number of inputs is unknown for a function right-hand side; "
                "pass nu=."
            )
        self.nu = _check_count(nu, "nu", where, 0)
        if ny is None:
            out = physics.output
            ny = len(out) if isinstance(out, list) else self.nx
            if callable(out):
                raise InputValidationError(
                    f"{where}: the grey-box model has an output function; pass ny=."
                )
        self.ny = _check_count(ny, "ny", where, 1)
        self._output = physics.output_map(self.ny)
        dtype = _check_dtype(dtype, where)
        self.method, self.substeps = _check_method(
            physics.method if method is None else method,
            physics.substeps if substeps is None else substeps,
            where,
        )
        self.time_scale = _time_scale(Ts, where)
        self.Ts = Ts
        like = torch.empty(0, dtype=dtype, device=device)
        self.normalizer = _Normalizer(
            self.nx, self.nu, x_scale, u_scale, x_offset, u_offset, where, like
        )
        idx = self._residual_indices(residual_states, where)
        self.register_buffer("residual_index", torch.tensor(idx, device=like.device))
        if network is None:
            hidden = _check_hidden(hidden, where)
            act = _check_activation(activation, where)
            gen = _generator(seed, like.device)
            network = _mlp(
                self.nx + self.nu,
                len(idx),
                hidden,
                act,
                generator=gen,
                dtype=dtype,
                device=like.device,
                last="zero",
            )
        elif not isinstance(network, nn.Module):
            raise InputValidationError(
                f"{where}: network must be an nn.Module (z (*batch, nx + nu) -> (*batch, "
                f"{len(idx)})) or None, got {type(network).__name__}."
            )
        self.net = network
        # physical parameters: unconstrained free values as Parameters, fixed ones as buffers
        self.names = list(physics.names)
        self._free = [n for n in self.names if physics.params[n].free]
        self.raw = nn.ParameterList()
        self._slot = {}
        for i, n in enumerate(self.names):
            p = physics.params[n]
            if p.per_experiment:
                raise InputValidationError(
                    f"{where}: parameter {n!r} is per_experiment; a hybrid model shares its "
                    "parameters between experiments: declare it shared (or fit the grey-box "
                    "model first and fix it)."
                )
            value = p.values.reshape(()).to(dtype=dtype, device=like.device)
            scale = p.scale(value)
            self.register_buffer(f"_scale_{i}", scale)
            if p.free:
                self._slot[n] = len(self.raw)
                self.raw.append(nn.Parameter(p.to_unconstrained(value, scale)))
            else:
                self.register_buffer(f"_fixed_{i}", value.clone())

    def _residual_indices(self, residual_states, where) -> list[int]:
        if residual_states is None:
            return list(range(self.nx))
        names = self.physics.state_names
        idx = []
        for s in residual_states:
            if isinstance(s, str):
                if names is None or s not in names:
                    raise InputValidationError(
                        f"{where}: residual_states names unknown state {s!r}; the states are "
                        f"{names}."
                    )
                idx.append(names.index(s))
            elif isinstance(s, bool) or not isinstance(s, int) or not 0 <= s < self.nx:
                raise InputValidationError(
                    f"{where}: residual_states index {s!r} out of range for nx = {self.nx}."
                )
            else:
                idx.append(int(s))
        if not idx or len(set(idx)) != len(idx):
            raise InputValidationError(
                f"{where}: residual_states must select at least one state, each once; got "
                f"{list(residual_states)!r}."
            )
        return idx

    def physical_parameters(self) -> dict[str, nn.Parameter]:
        """Name -> unconstrained ``nn.Parameter`` of each free physical parameter."""
        return {n: self.raw[self._slot[n]] for n in self._free}

    def to_physical(self, name: str, raw: torch.Tensor) -> torch.Tensor:
        """The Param's transform: physical value of ``name`` at the unconstrained ``raw``."""
        if name not in self._slot:
            return super().to_physical(name, raw)
        scale = getattr(self, f"_scale_{self.names.index(name)}")
        return self.physics.params[name].to_physical(raw, scale.to(raw))[0]

    def physical_values(self) -> dict[str, torch.Tensor]:
        """Name -> physical value (0-dim) of every parameter, free and fixed."""
        out = {}
        for i, n in enumerate(self.names):
            if n in self._slot:
                out[n] = self.to_physical(n, self.raw[self._slot[n]])
            else:
                out[n] = getattr(self, f"_fixed_{i}")
        return out

    def _stacked(self, batch) -> torch.Tensor:
        """P (*batch, n_params) in the grey-box model's order of names."""
        values = self.physical_values()
        P = torch.stack([values[n] for n in self.names], -1)
        return P.expand(*batch, len(self.names))

    def residual(self, x, u=None) -> torch.Tensor:
        """``r_theta(x, u) = x_scale[idx] * net(z) / Ts``, (*batch, len(idx))."""
        x, u = self._states_inputs(x, u, "residual")
        r = self.net(self.normalizer(x, u))
        k = self.residual_index.numel()
        if not isinstance(r, torch.Tensor) or r.shape != (*x.shape[:-1], k):
            got = tuple(r.shape) if isinstance(r, torch.Tensor) else type(r).__name__
            raise InputValidationError(
                f"HybridODE: the residual network returns shape {got} for a batch "
                f"{tuple(x.shape[:-1])}; it must return (*batch, {k}) (one per residual state)."
            )
        return self.normalizer.x_scale[self.residual_index] * r * self.time_scale

    def forward(self, t, x, u=None) -> torch.Tensor:
        """``dx/dt = f_phys(t, x, u, p) + E r_theta(x, u)`` (*batch, nx), state units per s."""
        x, u = self._states_inputs(x, u, "forward")
        P = self._stacked(x.shape[:-1]).to(x)
        dx = self.physics.rhs()(t, x, u, P)
        return dx.index_add(dx.dim() - 1, self.residual_index, self.residual(x, u))

    def output(self, x, u=None) -> torch.Tensor:
        """The grey-box model's output at the current physical values, (*batch, ny)."""
        x, u = self._states_inputs(x, u, "output")
        return self._output(x, u, self._stacked(x.shape[:-1]).to(x))


# ----------------------------------------------------------------------------- Lagrangian
class LagrangianNetwork(LagrangianSystem, ContinuousTimeModel):
    """A mechanical system with learned energies: a :class:`~sysid.mechanics.LagrangianSystem`
    (so its equations of motion are the Lagrange equation, solved by the same autograd code
    as every other mechanical model) with

    * kinetic energy ``T(q, qdot) = 1/2 qdot^T M(q) qdot`` (eq. 2.7), mass matrix
      ``M(q) = L(q) L(q)^T + eps I`` with ``L`` lower triangular, its diagonal through a
      softplus (positive) and every entry from one MLP of ``q``: symmetric positive definite
      for every ``q`` (eigenvalues >= eps), and ``W = d^2 T / d qdot^2 = M`` (eq. 2.61);
    * potential ``V(q)``: a scalar MLP (eq. 2.33, L = T - V);
    * Rayleigh dissipation ``D(qdot) = 1/2 qdot^T R R^T qdot`` (R (nq, nq) learned, so
      ``R R^T`` is positive semi-definite) entering as the generalised force ``-dD/dqdot``;
    * input map ``B(q) u`` (generalised force per input: learned MLP, the identity, or a
      given (nq, nu) matrix);

    so ``M(q) qddot + (d(M qdot)/dq) qdot - grad_q T + grad_q V = B(q) u - R R^T qdot``
    (eq. 2.40 with the generalised force of eq. 2.112), solved for qddot (eq. 2.42). With
    ``dissipation=False`` and ``u = 0`` the energy ``T + V`` (:meth:`energy`) is conserved by
    the exact flow, whatever the weights: the model is energy-correct by construction.

    State ``x = [q, qdot]`` (*batch, 2 nq); the networks see ``(q - q_offset) / q_scale``.
    Holonomic constraints ``c(q) = 0`` pass through to the LagrangianSystem (the index-1 KKT
    form, eq. 2.168, with optional Baumgarte stabilisation ``baumgarte``, eq. 2.186).

    Args:
        nq: number of generalised coordinates (>= 1); nu: number of inputs (>= 0).
        hidden, activation, seed, dtype, device: as for :class:`NeuralODE` (one width list
            for the three networks).
        eps: the shift ``eps I`` of the mass matrix (> 0).
        dissipation: learn ``R`` (True) or no dissipation (False).
        input_map: "learned", "identity" (needs nu = nq) or a tensor (nq, nu).
        q_scale, q_offset: normalisation of the network input, numbers or (nq,).
        constraints: ``c(q) -> (*batch, nc)`` or None; baumgarte: alpha > 0 or None.
        ny: outputs ``x[..., :ny]`` (default nq, the positions).
        method, substeps: the fixed-step Runge-Kutta method and steps per sample interval.

    Raises:
        InputValidationError: nq < 1, bad widths, eps, input map, scales or method.
    """

    def __init__(
        self,
        nq: int,
        nu: int = 0,
        hidden=(64, 64),
        activation: str = "tanh",
        eps: float = 1e-3,
        dissipation: bool = True,
        input_map="learned",
        q_scale=None,
        q_offset=None,
        constraints=None,
        baumgarte: float | None = None,
        ny: int | None = None,
        method: str = "rk4",
        substeps: int = 1,
        seed=None,
        *,
        dtype: torch.dtype = torch.float64,
        device=None,
    ):
        where = "LagrangianNetwork"
        nq = _check_count(nq, "nq", where, 1)
        nu = _check_count(nu, "nu", where, 0)
        super().__init__(nq, nu=nu, constraints=constraints, baumgarte=baumgarte)
        self.ny = nq if ny is None else _check_count(ny, "ny", where, 1)
        if self.ny > self.nx:
            raise InputValidationError(
                f"{where}: ny = {self.ny} outputs but the state has nx = 2 nq = {self.nx}."
            )
        if isinstance(eps, bool) or not isinstance(eps, (int, float)) or not eps > 0:
            raise InputValidationError(
                f"{where}: eps must be a number > 0 (it bounds the eigenvalues of M(q) from "
                f"below), got {eps!r}."
            )
        self.eps = float(eps)
        hidden = _check_hidden(hidden, where)
        act = _check_activation(activation, where)
        dtype = _check_dtype(dtype, where)
        self.method, self.substeps = _check_method(method, substeps, where)
        like = torch.empty(0, dtype=dtype, device=device)
        self.register_buffer(
            "q_scale", _channel_vector(q_scale, nq, "q_scale", where, 1.0, True, like)
        )
        self.register_buffer(
            "q_offset", _channel_vector(q_offset, nq, "q_offset", where, 0.0, False, like)
        )
        gen = _generator(seed, like.device)
        kw = {"generator": gen, "dtype": dtype, "device": like.device}
        # L(q): nq diagonal entries (softplus, starting at 1) then the strict lower triangle
        self.mass_net = _mlp(nq, nq * (nq + 1) // 2, hidden, act, last="small", **kw)
        with torch.no_grad():
            self.mass_net[-1].bias[:nq] = _SOFTPLUS_INV_ONE
        rows, cols = torch.tril_indices(nq, nq, -1, device=like.device)
        diagonal = torch.arange(nq, device=like.device) * (nq + 1)
        self.register_buffer("_l_index", torch.cat([diagonal, rows * nq + cols]))
        self.potential_net = _mlp(nq, 1, hidden, act, last="small", **kw)
        self.dissipation_factor = None
        if dissipation:
            r = torch.empty(nq, nq, dtype=dtype, device=like.device)
            nn.init.xavier_uniform_(r, gain=0.1, generator=gen)
            self.dissipation_factor = nn.Parameter(r)
        self.input_net = None
        self.register_buffer("input_matrix", None)
        if nu > 0:
            self._make_input_map(input_map, hidden, act, kw, like, where)

    def _make_input_map(self, input_map, hidden, act, kw, like, where):
        nq, nu = self.nq, self.nu
        if isinstance(input_map, str) and input_map == "learned":
            self.input_net = _mlp(nq, nq * nu, hidden, act, **kw)
        elif isinstance(input_map, str) and input_map == "identity":
            if nu != nq:
                raise InputValidationError(
                    f"{where}: input_map='identity' needs nu = nq, got nu = {nu}, nq = {nq}; "
                    "give a (nq, nu) matrix or 'learned'."
                )
            self.register_buffer(
                "input_matrix", torch.eye(nq, dtype=like.dtype, device=like.device)
            )
        elif isinstance(input_map, str):
            raise InputValidationError(
                f"{where}: input_map must be 'learned', 'identity' or a (nq, nu) tensor, got "
                f"{input_map!r}."
            )
        else:
            b = torch.as_tensor(input_map, dtype=like.dtype, device=like.device).detach().clone()
            if b.shape != (nq, nu) or not bool(torch.isfinite(b).all()):
                raise InputValidationError(
                    f"{where}: input_map must be a finite ({nq}, {nu}) matrix (nq, nu), got "
                    f"shape {tuple(b.shape)}."
                )
            self.register_buffer("input_matrix", b)

    # ---------------------------------------------------------------- learned parts
    def _normalized(self, q):
        return (q - self.q_offset) / self.q_scale

    def cholesky_factor(self, q) -> torch.Tensor:
        """L(q) (*batch, nq, nq), lower triangular with a positive diagonal."""
        nq = self.nq
        raw = self.mass_net(self._normalized(q))
        values = torch.cat([nn.functional.softplus(raw[..., :nq]), raw[..., nq:]], -1)
        flat = raw.new_zeros(*raw.shape[:-1], nq * nq).index_copy(-1, self._l_index, values)
        return flat.unflatten(-1, (nq, nq))

    @_local_graph
    def mass_matrix(self, q, qdot=None):
        """M(q) = L(q) L(q)^T + eps I (*batch, nq, nq): symmetric, eigenvalues >= eps; equals
        W = d^2 T / d qdot^2 of :meth:`kinetic_energy` (eq. 2.61)."""
        self._check_args("mass_matrix", q=q, qdot=qdot)
        L = self.cholesky_factor(q)
        M = L @ L.transpose(-1, -2)
        eye = torch.eye(self.nq, dtype=M.dtype, device=M.device)
        return 0.5 * (M + M.transpose(-1, -2)) + self.eps * eye

    @_local_graph
    def kinetic_energy(self, q, qdot):
        """``T = 1/2 qdot^T M(q) qdot = 1/2 (||L^T qdot||^2 + eps ||qdot||^2)`` (eq. 2.7),
        (*batch,)."""
        L = self.cholesky_factor(q)
        lq = (L.transpose(-1, -2) @ qdot.unsqueeze(-1)).squeeze(-1)
        return 0.5 * ((lq * lq).sum(-1) + self.eps * (qdot * qdot).sum(-1))

    def potential(self, q):
        """The learned potential V(q), (*batch,)."""
        return self.potential_net(self._normalized(q)).squeeze(-1)

    def input_matrix_at(self, q) -> torch.Tensor | None:
        """B(q) (*batch, nq, nu), or None without inputs."""
        if self.nu == 0:
            return None
        if self.input_net is not None:
            return self.input_net(self._normalized(q)).unflatten(-1, (self.nq, self.nu))
        return self.input_matrix.expand(*q.shape[:-1], self.nq, self.nu)

    def generalized_force(self, q, qdot, u):
        """Q = B(q) u - R R^T qdot (eq. 2.112), (*batch, nq), or None (neither part)."""
        force = None
        if self.dissipation_factor is not None:
            R = self.dissipation_factor
            force = -((qdot @ R) @ R.transpose(-1, -2))
        if self.nu > 0 and u is not None:
            B = self.input_matrix_at(q)
            bu = (B @ u.to(q).unsqueeze(-1)).squeeze(-1)
            force = bu if force is None else force + bu
        return force

    def dissipation(self, qdot) -> torch.Tensor:
        """Rayleigh dissipation function D = 1/2 qdot^T R R^T qdot (*batch,) (zero without)."""
        if self.dissipation_factor is None:
            return qdot.new_zeros(qdot.shape[:-1])
        v = qdot @ self.dissipation_factor
        return 0.5 * (v * v).sum(-1)

    def energy(self, x, qdot=None):
        """Total energy T + V (*batch,) of states x = [q, qdot] (*batch, 2 nq), or of
        (q, qdot) given separately (the LagrangianSystem signature)."""
        if qdot is None:
            x, qdot = self._split_state(x, "energy")
        return super().energy(x, qdot)

    def output(self, x, u=None) -> torch.Tensor:
        """``y = x[..., :ny]`` (*batch, ny) (default ny = nq: the positions)."""
        self._split_state(x, "output")
        return x[..., : self.ny]
