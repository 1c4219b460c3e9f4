"""Grey-box continuous-time models: a physical right-hand side with named parameters.

``x' = f(t, x, u, p)``, ``y = h(x, u, p)`` sampled at ``t_k = k Ts`` (the course notes
(Modelling and Simulation), chapter 1 for the models, §8 for their sensitivities), where
``f`` is any of

* a function ``f(t, x, u, p)`` with ``p`` a dict of named tensors, each of shape ``(*batch,)``
  like a state component ``x[..., i]``;
* an ``nn.Module`` with ``forward(t, x, u)`` (a zoo plant, a
  :class:`~sysid.mechanics.LagrangianSystem`, a user network) whose named parameters are the
  physical ones: they are substituted by ``torch.func.functional_call`` with values of shape
  ``(*batch, 1)`` (the zoo's broadcast convention, see ``sysid.zoo._params``);
* a semi-explicit index-1 DAE ``x' = f(t, x, z, u), 0 = g(t, x, z, u)`` (notes eq. 5.24): an
  ``nn.Module`` with methods ``f`` and ``g`` and an attribute ``nz >= 1`` (the zoo's DAE
  plants), or an
  :class:`integrators.SemiExplicitDAE` whose functions take ``p`` last. The algebraic state is
  eliminated at every stage by Newton's method on ``g`` (index 1: ``dg/dz`` invertible,
  Corollary 1, eq. 5.56), and its derivatives reach the sensitivities by the implicit function
  theorem (eq. 3.40), so the model is the state-space form of the DAE.

The model is simulated by a fixed-step Runge-Kutta method with ``substeps`` steps per sample
interval; its output and exact discrete sensitivities (eq. 8.17-8.18 explicit, 8.24-8.28
implicit) come from :func:`integrators.sensitivities` on "segments": stretches of the record
started from their own initial states, batched together (one segment for the simulation
error, many for multiple shooting, one-interval segments for the one-step error).
"""

from __future__ import annotations

import copy
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn
from torch.func import functional_call

from integrators import SemiExplicitDAE, Status, sensitivities
from integrators.auto import choose_method
from integrators.errors import HighIndexError, InputValidationError
from integrators.inputs import CollocationInput
from integrators.jacobians import batch_jacobian
from integrators.methods import resolve_method
from integrators.newton import newton
from integrators.tableau import ButcherTableau

from ..data import IOData
from ..errors import UnstableModelWarning
from .intersample import input_between_samples, stage_fractions
from .params import Param, value_in_experiment

__all__ = ["GreyBoxModel", "initial_states"]

_IMPLICIT = ("gauss_legendre", "radau_iia", "implicit_euler", "implicit_midpoint")


class _Method(nn.Module):
    """Calls ``plant.<name>`` so that ``functional_call`` can substitute the plant's
    parameters in any of its methods (parameter names get the prefix ``plant.``)."""

    def __init__(self, plant: nn.Module, name: str):
        super().__init__()
        self.plant, self.name = plant, name

    def forward(self, *args):
        return getattr(self.plant, self.name)(*args)


@dataclass
class Segments:
    """Stretches of one experiment simulated from their own initial states.

    Segment ``j`` starts at sample ``starts[j]`` and covers ``length`` intervals (samples
    beyond the record are padded with the last input and masked out of the residuals).
    """

    starts: torch.Tensor  # (S,) int64
    length: int


def _undeclared_parameter(exc: KeyError, names, who: str) -> InputValidationError:
    """The error for a model function ``who`` whose lookup ``p[name]`` raised ``exc``."""
    return InputValidationError(
        f"the model's {who} raised KeyError({exc.args[0]!r}) reading its parameters: p holds "
        f"the declared parameters {list(names)} only; declare the parameter "
        "(params={..., name: value or Param(...)}) or correct its name."
    )


class GreyBoxModel:
    """A continuous-time model with named physical parameters, fitted by :func:`sysid.fit`.

    Args:
        f: the right-hand side (see the module docstring for the four kinds).
        params: name -> :class:`Param` or float (a free parameter starting there). For an
            ``nn.Module`` the names are its parameter names; None takes every scalar
            parameter of the module, free (those with ``requires_grad=False`` fixed), and the
            module's parameters not named here stay fixed at their values.
        nx: number of states (taken from the module's ``nx`` or ``state_names`` when omitted).
        output: None (the first ``ny`` states, ``ny`` from the data), a sequence of state
            indices or state names, or a function ``h(x, u, p) -> (*batch, ny)``.
        x0: initial state: None / ``"zero"`` (zeros), ``"estimate"`` (one free initial state
            per experiment), a tensor (nx,) / (*batch, nx) (known, every experiment), or a
            list of such tensors, one per experiment (a list of numbers is one state).
        method: a fixed-step method name or tableau ("rk4" by default; "radau_iia" or
            "gauss_legendre" for stiff plants and DAEs), or "auto" (Radau IIA where
            ``rho(df/dx) Ts / substeps`` exceeds the explicit stability limit at the start,
            RK4 otherwise; see :func:`integrators.auto.choose_method`).
        substeps: Runge-Kutta steps per sample interval.
        stages: stage count of "gauss_legendre" / "radau_iia".
        nz, z0: DAE models: number of algebraic states and the Newton start for ``z`` (zeros by
            default); ``nz`` is read from the module's ``nz`` when omitted.
        state_names: names of the states (for ``output`` and reports).
        compile: explicit methods: True runs each sample interval of the simulations and
            sensitivities as one compiled kernel (a one-off compile of seconds, then about
            ten times less time per step), False never, ``"auto"`` (default) once the model
            has spent :data:`integrators._fast.compiled.AUTO_COMPILE_EAGER_SECONDS` seconds in
            eager steps (see :func:`integrators.sensitivities`), or at once in a fit whose
            first simulation shows that it would spend that long; never for a DAE (its
            right-hand side runs a Newton solve, which the compiler cannot trace). Models the
            compiler cannot handle (autograd or a Newton solve inside ``f``) run eagerly; the
            fit's ``info`` says which ran.

    Raises:
        InputValidationError: unknown parameter names, a non-scalar module parameter, a
            missing ``nx``, a bad ``output`` or ``x0``.
        HighIndexError: a DAE whose declared index exceeds 1.
    """

    def __init__(
        self,
        f,
        params: dict | None = None,
        *,
        nx: int | None = None,
        output=None,
        x0=None,
        method: str | ButcherTableau = "rk4",
        substeps: int = 1,
        stages: int | None = None,
        nz: int | None = None,
        z0=None,
        state_names: Sequence[str] | None = None,
        compile: bool | str = "auto",
    ):
        if compile not in (True, False, "auto"):
            raise InputValidationError(f"compile must be True, False or 'auto', got {compile!r}.")
        self._rhs_cache = None
        self.f = f
        self.kind = _kind(f)
        # a DAE's right-hand side solves g = 0 by Newton at every evaluation, which the
        # compiler cannot trace (it gives up after seconds of tracing): "auto" stays eager
        dae = self.kind in ("dae_module", "dae_problem")
        self.compile = False if dae and compile == "auto" else compile
        if self.kind in ("dae_module", "dae_problem"):
            index = getattr(f, "index", 1)
            if index is not None and int(index) > 1:
                raise HighIndexError(
                    f"{type(f).__name__} is a DAE of index {index}: the grey-box model needs "
                    "index 1 (dg/dz invertible). Reduce the index first (differentiate the "
                    "constraints, e.g. sysid.dae.reduce_index, or use the index-1 KKT form "
                    "with Baumgarte stabilisation, notes eq. 2.168 and 2.186)."
                )
        self.params = _collect_params(f, params, self.kind)
        self.names = list(self.params)
        self.state_names = tuple(state_names) if state_names is not None else _state_names(f)
        self.nx = nx if nx is not None else _infer_nx(f, self.state_names)
        if self.nx is None:
            raise InputValidationError(
                "GreyBoxModel: the number of states is unknown; pass nx= (or state_names=)."
            )
        if self.state_names is not None and len(self.state_names) != self.nx:
            raise InputValidationError(
                f"GreyBoxModel: {len(self.state_names)} state names for nx = {self.nx} states."
            )
        self.nz = nz if nz is not None else getattr(f, "nz", 0 if self.kind in ("ode",) else None)
        if self.kind in ("dae_module", "dae_problem") and not self.nz:
            raise InputValidationError(
                "GreyBoxModel: a DAE model needs nz >= 1 algebraic states (pass nz=)."
            )
        self.z0 = None if z0 is None else torch.as_tensor(z0, dtype=torch.float64)
        self.output = self._check_output(output)
        self.x0 = _check_x0(x0, self.nx)
        if isinstance(substeps, bool) or int(substeps) != substeps or substeps < 1:
            raise InputValidationError(f"substeps must be an integer >= 1, got {substeps!r}.")
        self.substeps = int(substeps)
        self.method, self.stages = method, stages
        if method != "auto":
            self._tableau(method)  # validate the name and stages now

    # ----------------------------------------------------------------------- description
    def __repr__(self) -> str:
        return (
            f"GreyBoxModel({_describe_f(self.f)}, params={self.params}, nx={self.nx}, "
            f"method={self.method!r}, substeps={self.substeps})"
        )

    @property
    def free_names(self) -> list[str]:
        """Names of the free parameters."""
        return [n for n in self.names if self.params[n].free]

    def _check_output(self, output):
        if output is None or callable(output):
            return output
        idx = []
        for o in output:
            if isinstance(o, str):
                if self.state_names is None or o not in self.state_names:
                    raise InputValidationError(
                        f"output: unknown state name {o!r}; the states are {self.state_names}."
                    )
                idx.append(self.state_names.index(o))
            else:
                if not 0 <= int(o) < self.nx:
                    raise InputValidationError(
                        f"output: state index {o} out of range for nx = {self.nx}."
                    )
                idx.append(int(o))
        if not idx:
            raise InputValidationError("output: select at least one state.")
        return idx

    def output_indices(self, ny: int) -> list[int] | None:
        """The measured state indices (None for an output function)."""
        if callable(self.output):
            return None
        idx = list(range(ny)) if self.output is None else self.output
        if len(idx) != ny:
            raise InputValidationError(
                f"the data have ny = {ny} outputs but the model's output selects {len(idx)} "
                f"states ({idx}); pass output= with {ny} states or a function h(x, u, p)."
            )
        if max(idx) >= self.nx:
            raise InputValidationError(
                f"the data have ny = {ny} outputs but the model has only nx = {self.nx} states; "
                "pass output= naming the measured states or a function h(x, u, p)."
            )
        return idx

    # ----------------------------------------------------------------------- numerics
    def _tableau(self, method) -> ButcherTableau:
        """The tableau of ``method`` (``stages`` for the collocation families), run at fixed
        steps: the Jacobian of a fit is exact for the discrete simulation."""
        return resolve_method(method).tableau(self.stages)

    def choose_integrator(self, data: IOData, P: torch.Tensor, x0: torch.Tensor) -> tuple:
        """The method to use on ``data`` (resolving ``"auto"`` at the parameters ``P``
        (*batch, n_params) and initial states ``x0`` (*batch, nx)): ``(method, reason)``."""
        if self.method != "auto":
            return self.method, "as requested"
        rhs = self.rhs()
        u0 = data.u[..., 0, :]
        h = data.Ts / self.substeps
        t = torch.tensor([0.0, h], dtype=data.dtype, device=data.device)
        name, info = choose_method(lambda t, x: rhs(t, x, u0, P), x0, t)
        return ("radau_iia" if name == "radau_iia" else "rk4"), info["reason"]

    def rhs(self) -> Callable:
        """``f(t, x, u, P)`` evaluated with the parameter values in ``P`` (*batch, n_params) in
        the order of :attr:`names`; raises :class:`InputValidationError` when ``f`` returns
        another shape than ``x``'s or reads a parameter ``p`` does not hold. The same function
        object for as long as ``f``, the parameter names and ``z0`` stay the same. Compiled
        kernels are cached by ``f`` itself (its ``__wrapped__``): another model of the same
        ``f`` runs them without compiling."""
        key = (id(self.f), id(self.z0), tuple(self.names), self.kind, self.nz)
        if self._rhs_cache is not None and self._rhs_cache[0] == key:
            return self._rhs_cache[1]
        call, names = self._rhs(), tuple(self.names)
        reads_dict = self.kind not in ("module", "dae_module")  # f(..., p) with p a dict

        def checked(t, x, u, P):
            try:
                dx = call(t, x, u, P)
            except KeyError as exc:
                if not reads_dict:
                    raise
                raise _undeclared_parameter(exc, names, "f") from exc
            if not isinstance(dx, torch.Tensor) or dx.shape != x.shape:
                got = tuple(dx.shape) if isinstance(dx, torch.Tensor) else type(dx).__name__
                raise InputValidationError(
                    f"the model's right-hand side returned shape {got} for a state of shape "
                    f"{tuple(x.shape)}; it must return one derivative per state. A function "
                    "f(t, x, u, p) gets each p[name] with the shape of one state component "
                    "x[..., i] (*batch,): write p['k'] * x[..., 0], or p['k'][..., None] * x, "
                    "not p['k'] * x[..., 0:1]."
                )
            return dx

        checked.__wrapped__ = self.f  # compiled kernels are cached by the user's f
        self._rhs_cache = (key, checked)  # the closure keeps f (and a DAE's z0) alive
        return checked

    def _rhs(self) -> Callable:
        names, kind, f = self.names, self.kind, self.f
        if kind == "function":

            def call(t, x, u, P):
                return f(t, x, u, {n: P[..., j] for j, n in enumerate(names)})

            return call
        if kind == "module":

            def call(t, x, u, P):
                params = {n: P[..., j : j + 1] for j, n in enumerate(names)}
                return functional_call(f, params, (t, x, u))

            return call
        return self._dae_rhs()

    def _dae_rhs(self) -> Callable:
        names, f, nz = self.names, self.f, self.nz
        if self.kind == "dae_module":
            fm, gm = _Method(f, "f"), _Method(f, "g")

            def fun(which, t, x, z, u, P):
                params = {f"plant.{n}": P[..., j : j + 1] for j, n in enumerate(names)}
                return functional_call(fm if which == "f" else gm, params, (t, x, z, u))

        else:

            def fun(which, t, x, z, u, P):
                p = {n: P[..., j] for j, n in enumerate(names)}
                return (f.f if which == "f" else f.g)(t, x, z, u, p)

        z_start = self.z0

        def call(t, x, u, P):
            guess = x.new_zeros(*x.shape[:-1], nz)
            if z_start is not None:
                guess = guess + z_start.to(x)
            sol = newton(lambda z, x, u, P: fun("g", t, x, z, u, P), guess, x, u, P)
            if not bool(sol.converged.all()):
                # an unconverged z makes f wrong: NaN marks the affected members as failed
                bad = ~sol.converged
                z = torch.where(bad[..., None], torch.full_like(sol.x, float("nan")), sol.x)
            else:
                z = sol.x
            return fun("f", t, x, z, u, P)

        return call

    def check_index(self, x0: torch.Tensor, u0: torch.Tensor, P: torch.Tensor) -> None:
        """Raise :class:`HighIndexError` unless ``dg/dz`` is invertible at the start."""
        if self.kind not in ("dae_module", "dae_problem"):
            return
        names, f, nz = self.names, self.f, self.nz
        z = x0.new_zeros(*x0.shape[:-1], nz)
        if self.z0 is not None:
            z = z + self.z0.to(x0)
        if self.kind == "dae_module":
            gm = _Method(f, "g")

            def g(z):
                params = {f"plant.{n}": P[..., j : j + 1] for j, n in enumerate(names)}
                return functional_call(gm, params, (torch.zeros((), dtype=x0.dtype), x0, z, u0))

        else:

            def g(z):
                p = {n: P[..., j] for j, n in enumerate(names)}
                return f.g(torch.zeros((), dtype=x0.dtype), x0, z, u0, p)

        _, Gz = batch_jacobian(g, z)
        if Gz.shape[-2] != nz:
            raise InputValidationError(
                f"g returns {Gz.shape[-2]} equations for nz = {nz} algebraic states; an index-1 "
                "semi-explicit DAE has as many algebraic equations as algebraic states."
            )
        sv = torch.linalg.svdvals(Gz)
        rank_def = sv[..., -1] <= sv[..., 0] * 1e-10 * nz
        if bool(rank_def.any()):
            raise HighIndexError(
                "dg/dz is singular at the initial state: the DAE is not of index 1 (notes "
                "Corollary 1, eq. 5.56). Reduce the index (differentiate the constraints, "
                "e.g. sysid.dae.reduce_index; for mechanics the index-1 KKT form with "
                "Baumgarte stabilisation, notes eq. 2.168 and 2.186) and fit that model."
            )

    def output_map(self, ny: int) -> Callable:
        """``h(x, u, P) -> (*batch, ny)``; an output function returning another shape or
        reading a parameter ``p`` does not hold raises :class:`InputValidationError`."""
        idx = self.output_indices(ny)
        if idx is not None:
            index = torch.tensor(idx)

            def select(x, u, P):
                return x.index_select(-1, index.to(x.device))

            return select
        names, h = self.names, self.output

        def call(x, u, P):
            try:
                y = h(x, u, {n: P[..., j] for j, n in enumerate(names)})
            except KeyError as exc:
                raise _undeclared_parameter(exc, names, "output function h") from exc
            if not isinstance(y, torch.Tensor) or y.shape != (*x.shape[:-1], ny):
                got = tuple(y.shape) if isinstance(y, torch.Tensor) else type(y).__name__
                raise InputValidationError(
                    f"the output function returns shape {got} for states of shape "
                    f"{tuple(x.shape)}; the data have ny = {ny} outputs, so h(x, u, p) must "
                    f"return (*batch, {ny})."
                )
            return y

        return call

    def simulate_segments(
        self,
        P: torch.Tensor,
        nodes: torch.Tensor,
        u: torch.Tensor,
        Ts: float,
        intersample: str,
        segments: Segments,
        ny: int,
        method,
        derivatives: bool = True,
        compile: bool | str | None = None,
    ) -> dict:
        """Outputs and sensitivities of the segments of one experiment.

        Args:
            P: (*batch, n_params) physical parameter values (order of :attr:`names`).
            nodes: (*batch, S, nx) initial state of each segment.
            u: (*batch, N, nu) input samples of the experiment.
            Ts: sample time; intersample: the input between samples.
            segments: the segments (S starts, ``length`` intervals each).
            ny: number of outputs; method: the fixed-step method.
            derivatives: False computes only ``y`` and ``x_end`` (the same simulation).
            compile: overrides the model's ``compile`` for this call (None: the model's).

        Returns:
            dict with ``y`` (*batch, S, L+1, ny), ``dy_dP`` (*batch, S, L+1, ny, n_params),
            ``dy_dx0`` (*batch, S, L+1, ny, nx), ``x_end`` (*batch, S, nx), ``dxend_dP`` and
            ``dxend_dx0``, ``stats`` (the integrator's statistics), ``status`` (*batch, S)
            (:class:`~integrators.Status` codes: NON_FINITE where a segment's simulation
            became inf / NaN, NEWTON_FAILED where an implicit method's stage equations were
            not solved; its outputs NaN from there on, the other segments and data sets
            unaffected) and ``messages`` (one per failed segment).
        """
        tab = self._tableau(method)
        L = segments.length
        N = u.shape[-2]
        pad = int(segments.starts[-1]) + L + 1 - N
        u_pad = torch.cat([u, u[..., -1:, :].expand(*u.shape[:-2], max(pad, 0), u.shape[-1])], -2)
        tau = stage_fractions(tab, self.substeps)
        between = input_between_samples(u, intersample, tau)  # (*batch, N-1, q, nu)
        if pad > 0:
            last = between[..., -1:, :, :]
            between = torch.cat([between, last.expand(*last.shape[:-3], pad, *last.shape[-2:])], -3)
        idx = segments.starts.to(u.device)[:, None] + torch.arange(L + 1, device=u.device)
        u_seg = u_pad[..., idx, :]  # (*batch, S, L+1, nu)
        coeff = between[..., idx[:, :-1], :, :]  # (*batch, S, L, q, nu)
        t_loc = Ts * torch.arange(L + 1, dtype=u.dtype, device=u.device)
        nodes_q = torch.as_tensor(tau, dtype=u.dtype, device=u.device)
        rhs = self.rhs()
        sens = sensitivities(
            rhs,
            nodes,
            t_loc,
            P.unsqueeze(-2),
            u=CollocationInput(coeff, t_loc, nodes=nodes_q),
            method=tab,
            substeps=self.substeps,
            input_sensitivities=False,
            derivatives=derivatives,
            compile=self.compile if compile is None else compile,
        )
        x = sens.x  # (*batch, S, L+1, nx)
        h = self.output_map(ny)
        if not derivatives:
            Pb = P[..., None, None, :].expand(*x.shape[:-1], P.shape[-1])
            y = h(x, u_seg, Pb)
            return {
                "y": y,
                "x_end": x[..., -1, :],
                "x": x,
                "stats": sens.stats,
                "status": sens.status,
                "messages": sens.messages,
            }
        A, B = sens.A, sens.B
        n_p = P.shape[-1]
        idx_out = self.output_indices(ny)
        Pb = P[..., None, None, :].expand(*x.shape[:-1], n_p)
        if idx_out is not None:
            y = x[..., idx_out]
            dy_dx = A[..., idx_out, :]
            dy_dP = B[..., idx_out, :]
        else:
            z = torch.cat([x, Pb], -1)
            nx = self.nx
            y, H = batch_jacobian(lambda z: h(z[..., :nx], u_seg, z[..., nx:]), z)
            dy_dx = H[..., :nx] @ A
            dy_dP = H[..., :nx] @ B + H[..., nx:]
        return {
            "y": y,
            "dy_dP": dy_dP,
            "dy_dx0": dy_dx,
            "x_end": x[..., -1, :],
            "dxend_dP": B[..., -1, :, :],
            "dxend_dx0": A[..., -1, :, :],
            "x": x,
            "stats": sens.stats,
            "status": sens.status,
            "messages": sens.messages,
        }

    def simulate(self, data: IOData, params: dict | None = None, x0=None):
        """Free-run output of the model on the input of ``data``.

        Args:
            data: :class:`IOData` (its ``u``, ``Ts``, ``intersample``, experiments and
                number of outputs ``ny``; ``y`` is not used).
            params: name -> value overriding the model's values: a float or a (*batch,)
                tensor; for a per-experiment parameter the experiment is the last dimension.
            x0: initial state (nx,) / (*batch, nx), or a list of such tensors, one per
                experiment; default the model's (zeros when ``"zero"`` or ``"estimate"``).

        Returns:
            (*batch, N, ny) simulated outputs (experiments concatenated along time, like
            ``data.y``). A data set whose simulation becomes inf / NaN (the model escapes to
            infinity, or the fixed step is too large for stability) or whose implicit stage
            equations are not solved at a step has NaN outputs from that sample of the
            experiment on, and an :class:`~sysid.errors.UnstableModelWarning` names it, the
            experiment and the time.
        """
        if not isinstance(data, IOData):
            raise InputValidationError(
                f"simulate needs IOData (its input, Ts and intersample), got {type(data).__name__}."
            )
        values = {n: self.params[n].values for n in self.names}
        if params is not None:
            unknown = set(params) - set(self.names)
            if unknown:
                raise InputValidationError(
                    f"simulate: unknown parameter(s) {sorted(unknown)}; the model has {self.names}."
                )
            values.update(params)
        starts = initial_states(x0 if x0 is not None else self.x0, self.nx, data.n_experiments)
        parts, failures = [], []
        for e, part in enumerate(data.experiment_list):
            vals = [
                value_in_experiment(
                    torch.as_tensor(values[n], dtype=part.dtype),
                    self.params[n].per_experiment,
                    data.n_experiments,
                    e,
                    f"simulate: {n!r}",
                )
                for n in self.names
            ]
            x_e = starts[e]
            if x_e is None or isinstance(x_e, str):
                x_e = torch.zeros(self.nx)
            x_e = torch.as_tensor(x_e, dtype=part.dtype, device=part.device)
            shapes = {"data": part.batch_shape, "x0": x_e.shape[:-1]}
            shapes.update({n: v.shape for n, v in zip(self.names, vals, strict=True)})
            try:
                full = torch.broadcast_shapes(*shapes.values())
            except RuntimeError as exc:
                got = ", ".join(f"{k} {tuple(v)}" for k, v in shapes.items())
                raise InputValidationError(
                    f"simulate: the batch shapes of {got} do not broadcast; give the "
                    "parameters and x0 without a batch or with the data's batch."
                ) from exc
            P = torch.stack(torch.broadcast_tensors(*vals), -1)
            P = P.to(part.device).expand(*full, len(self.names))
            nodes = x_e.expand(*full, self.nx).unsqueeze(-2)
            u = part.u.expand(*full, *part.u.shape[-2:])
            method, _ = self.choose_integrator(part, P, nodes[..., 0, :])
            seg = Segments(torch.zeros(1, dtype=torch.int64), part.N - 1)
            with torch.no_grad():
                out = self.simulate_segments(
                    P, nodes, u, part.Ts, part.intersample, seg, data.ny, method, False
                )
            parts.append(out["y"][..., 0, :, :])
            failures += _failed_runs(
                out["status"][..., 0],
                out["x"][..., 0, :, :],
                part.Ts,
                e if data.n_experiments > 1 else None,
            )
        if failures:
            shown = "; ".join(failures[:5]) + (
                f"; and {len(failures) - 5} more" if len(failures) > 5 else ""
            )
            warnings.warn(
                f"simulate: the simulation became non-finite (inf/nan) or failed for {shown}; "
                "the outputs from there on are NaN. The model escapes to infinity with these "
                "parameters and initial state, or the fixed step is too large for stability "
                "(or for the stage equations of an implicit method): check them, or use more "
                "substeps or an implicit method.",
                UnstableModelWarning,
                stacklevel=2,
            )
        return torch.cat(parts, -2)

    def with_values(self, values: dict, x0=None) -> GreyBoxModel:
        """A copy whose parameters take ``values`` (name -> float or (*batch,) tensor) and, if
        given, whose known initial state is ``x0`` (a tensor, or a list with one per
        experiment). A single value is stored as :class:`Param` keeps it, shape (1,), so the
        copy prints and fits again like the original."""
        out = copy.copy(self)
        out.params = dict(self.params)
        for n, v in values.items():
            old = self.params[n]
            new = copy.copy(old)
            new.values = torch.as_tensor(v, dtype=torch.float64).detach()
            if new.values.dim() == 0:
                new.values = new.values.reshape(1)
            out.params[n] = new
        if x0 is not None:
            x0 = _check_x0(x0, self.nx)
            if isinstance(x0, list):
                x0 = [v.detach() for v in x0]
            out.x0 = x0.detach() if isinstance(x0, torch.Tensor) else x0
        return out


# ---------------------------------------------------------------------------- helpers
def _failed_runs(status: torch.Tensor, x: torch.Tensor, Ts: float, experiment) -> list[str]:
    """One line per data set whose simulation failed: ``status`` (*batch,) Status codes,
    ``x`` (*batch, N, nx) the simulated states (NaN from the failure on), ``Ts`` the sample
    time, ``experiment`` the experiment's index (None for data of one experiment)."""
    failed = status != 0
    if not bool(failed.any()):
        return []
    bad = ~torch.isfinite(x).all(-1)  # (*batch, N)
    first = bad.to(torch.int8).argmax(-1)
    where = "" if experiment is None else f", experiment {experiment},"
    lines = []
    for idx in torch.nonzero(failed.reshape(failed.shape or (1,))).tolist():
        k = int(first.reshape(failed.shape or (1,))[tuple(idx)])
        name = f"data set {tuple(idx) if len(idx) > 1 else idx[0]}" if status.dim() else "the run"
        code = int(status.reshape(failed.shape or (1,))[tuple(idx)])
        why = ", its implicit stage equations not solved" if code == Status.NEWTON_FAILED else ""
        lines.append(
            f"{name}{where} between t = {(k - 1) * Ts:.6g} and {k * Ts:.6g} (NaN from sample "
            f"{k} on{why})"
        )
    return lines


def _kind(f) -> str:
    if isinstance(f, SemiExplicitDAE):
        return "dae_problem"
    if isinstance(f, nn.Module):
        has_fg = callable(getattr(f, "g", None)) and callable(getattr(f, "f", None))
        if has_fg and int(getattr(f, "nz", 0) or 0) >= 1:
            return "dae_module"
        return "module"
    if callable(f):
        return "function"
    raise InputValidationError(
        f"GreyBoxModel: f must be a function f(t, x, u, p), an nn.Module or a SemiExplicitDAE, "
        f"got {type(f).__name__}."
    )


def _describe_f(f) -> str:
    return (
        type(f).__name__
        if isinstance(f, (nn.Module, SemiExplicitDAE))
        else getattr(f, "__name__", "f")
    )


def _collect_params(f, params, kind) -> dict[str, Param]:
    module_params = {}
    if kind in ("module", "dae_module"):
        module_params = dict(f.named_parameters())
    if params is None:
        if not module_params:
            raise InputValidationError(
                "GreyBoxModel: params= is required for a function right-hand side (name -> "
                "Param or starting value)."
            )
        params = {
            n: Param(float(v.detach().reshape(-1)[0]), free=bool(v.requires_grad))
            for n, v in module_params.items()
            if v.numel() == 1
        }
    if not isinstance(params, dict) or not params:
        raise InputValidationError("GreyBoxModel: params must be a non-empty dict name -> Param.")
    # a module's tensors that can be set by name: its parameters and buffers
    is_module = kind in ("module", "dae_module")
    settable = {**dict(f.named_buffers()), **module_params} if is_module else {}
    out = {}
    for name, p in params.items():
        if is_module and name not in settable:
            raise InputValidationError(
                f"GreyBoxModel: unknown parameter name {name!r}; the module "
                f"{type(f).__name__} has the parameters and buffers {sorted(settable)} (a "
                "plain attribute cannot be estimated: register it with nn.Parameter or "
                "register_buffer)."
            )
        if is_module and settable[name].numel() != 1:
            raise InputValidationError(
                f"GreyBoxModel: module parameter {name!r} has {settable[name].numel()} "
                "entries; only scalar parameters can be estimated by name."
            )
        out[name] = p if isinstance(p, Param) else Param(p)
    for name, v in module_params.items():  # the module's other parameters stay fixed
        if name not in out and v.numel() == 1:
            out[name] = Param(float(v.detach().reshape(-1)[0]), free=False)
    return out


def _state_names(f):
    names = getattr(f, "state_names", None)
    return tuple(names) if names is not None else None


def _infer_nx(f, state_names):
    nx = getattr(f, "nx", None)
    if isinstance(nx, (int, np.integer)):
        return int(nx)
    if state_names is not None:
        return len(state_names)
    return None


def _per_experiment(x0) -> bool:
    """Whether ``x0`` is a list or tuple of initial states, one per experiment (tensors or
    arrays; a list of numbers is one state)."""
    return (
        isinstance(x0, (list, tuple))
        and len(x0) > 0
        and all(isinstance(v, (torch.Tensor, np.ndarray)) for v in x0)
    )


def _check_x0(x0, nx):
    if x0 is None or (isinstance(x0, str) and x0 in ("zero", "estimate")):
        return x0
    if isinstance(x0, str):
        raise InputValidationError(
            f"x0 must be 'zero', 'estimate' or a tensor of shape (nx,) / (*batch, nx), got {x0!r}."
        )
    if _per_experiment(x0):
        return [_check_x0(v, nx) for v in x0]
    t = torch.as_tensor(x0, dtype=torch.float64)
    if t.dim() < 1 or t.shape[-1] != nx or not bool(torch.isfinite(t).all()):
        raise InputValidationError(
            f"x0 must be finite with shape (nx,) or (*batch, nx), nx = {nx}; got {tuple(t.shape)}."
        )
    return t


def initial_states(x0, nx: int, n_experiments: int) -> list:
    """The initial state of every experiment from a model's or a call's ``x0``.

    Args:
        x0: None, ``"zero"`` or ``"estimate"`` (returned as they are, for every experiment), a
            tensor (nx,) / (*batch, nx) shared by the experiments, or a list or tuple of such
            tensors, one per experiment.
        nx: number of states.
        n_experiments: number of experiments of the data.

    Returns:
        A list of ``n_experiments`` entries: None, a string, or a float64 tensor (*batch, nx).

    Raises:
        InputValidationError: a bad shape, a non-finite value, or a list whose length is not
            the number of experiments.
    """
    checked = _check_x0(x0, nx)
    if not isinstance(checked, list):
        return [checked] * n_experiments
    if len(checked) != n_experiments:
        raise InputValidationError(
            f"x0 is a list of {len(checked)} initial states, one per experiment, but the data "
            f"has {n_experiments} experiment(s); give one per experiment, or one tensor "
            "(nx,) / (*batch, nx) for all of them."
        )
    return checked
