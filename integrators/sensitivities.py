"""Forward sensitivities of fixed-step Runge-Kutta simulations (notes §8).

:func:`sensitivities` differentiates the *discrete* simulation exactly (algorithmic
differentiation, notes §8.2-8.3): for one step of size ``h`` from ``x_k`` with parameters
``q = (p, w_k)`` (``w_k`` the input parameters of the current output interval, see below),

    K_i         = f(t_k + c_i h, x_k + h sum_{j<i} a_ij K_j, u_i(w_k), p)
    dK_i/dx_k   = F_x^(i) (I + h sum_{j<i} a_ij dK_j/dx_k)                      (eq. 8.17b)
    dK_i/dq     = F_x^(i) (h sum_{j<i} a_ij dK_j/dq) + F_q^(i)                   (eq. 8.17c)
    Phi_k       = I + h sum_i b_i dK_i/dx_k,   Psi_k = h sum_i b_i dK_i/dq
    A_{k+1}     = Phi_k A_k,                    A_0 = I                          (eq. 8.18b)
    B_{k+1}     = Phi_k B_k + Psi_k^p,          B_0 = 0                          (eq. 8.18c)

where ``F_x^(i), F_q^(i)`` are the Jacobians of ``f`` at stage ``i`` (``F_q`` includes the chain
rule through the input, eq. 8.30-8.31). ``[Phi_k Psi_k]`` is the Jacobian of the step map
``(x_k, q) -> x_{k+1}``: eager explicit steps form it by one batched reverse pass through all
stages (the chain rule of eq. 8.17 accumulated backwards: the same numbers to rounding, at one
autograd call per step instead of one per stage); the compiled kernel
(:func:`_interval_kernel`) runs eq. 8.17 forwards.

The notes' eq. 8.16-8.17 write ``a_sj`` and ``b_j`` inside the stage sums and an identity
inside ``dK_i/dp``: typos; the stage sums use row ``i`` of ``A`` and the parameter derivative
has no identity term (checked against autograd in tests/test_sensitivities.py). Eq. 8.28c
likewise has ``dK/dp`` where ``dK/dx_k`` belongs in the propagation factor.

Implicit tableaus. The stages solve ``r(K) = F(K) - K = 0`` (eq. 8.20, ``F_i = f(X_i)`` at the
stage states ``X_i = x_k + h sum_j a_ij K_j``); ``M = -dr/dK = I - h [a_ij F_x^(i)]_ij`` is the
Newton matrix (eq. 8.25), and the implicit function theorem (eq. 8.24, 8.27) gives all stage
derivatives at once: ``M dK/d(x_k, q) = [F_x^(i) [I 0] + [0 F_q^(i)]]_i``. Eq. 8.24 needs ``M``
at the *converged* stages, so each step factorises the exact ``M`` once, there (LU), and that
one factorisation serves

* the last Newton correction of the step, ``K <- K + M^{-1} r(K)`` (eq. 8.25-8.26, full step),
* every sensitivity column (``x_k``, ``p`` and input columns), solved together with the
  correction as one multi-column triangular solve (eq. 8.27), and
* the simplified-Newton iterations of the next step (eq. 8.22 with the previous step's ``M``;
  a contraction slower than ``1/2`` refreshes it at the current iterate).

Only the first step, which has no previous factorisation, factorises once more (at its starting
guess): ``N`` steps cost ``N + 1`` factorisations when no refresh is needed, reported in
``SensitivityResult.stats``. ``Phi_k, Psi_k`` then propagate ``A, B`` as above (eq. 8.28).
Batch members are solved independently: a member whose stage equations fail (Newton budget,
non-finite stages, a singular Newton matrix) stops with ``Status.NEWTON_FAILED`` and is frozen
at its initial state (as :func:`~integrators.odeint.odeint` freezes a failed sample), and the
others get the numbers they get alone.

Inputs are parameterised on the output grid (notes §8.5) and the parameters become columns
of ``q``:

* samples ``u`` (T, nu) held piecewise constant (eq. 8.34, ``u(t) = u_k`` on the closed
  ``[t_k, t_{k+1}]`` for every stage, as ``odeint`` does): ``w_k = u_k`` and
  ``C[..., k, :, j, :] = dx_k / du_j``;
* a :class:`~integrators.inputs.CollocationInput` (eq. 8.32-8.33): on interval ``k`` the input
  is ``sum_i P_{k,i} l_i(tau)``, evaluated at every stage time ``t_k + (m + c_i) h`` (substep
  ``m``, ``tau = (m + c_i) / substeps``), ``w_k = vec P_k`` and
  ``C[..., k, :, j, i, :] = dx_k / dP_{j,i}``.

In both cases ``x_k`` depends only on the parameters of intervals ``j < k`` (causality).
``odeint`` given the same ``CollocationInput`` (a callable ``u(t)``) runs the same simulation
except at a stage exactly on a grid point where the pieces jump (``c_i = 1``, e.g. RK4 or
Radau IIA): a call ``u(t)`` looks ``t_{k+1}`` up in the next interval.

:func:`variational_sensitivities` integrates the variational equations (eq. 8.8) alongside the
state with :func:`~integrators.odeint.odeint`. With the *same* fixed-step explicit method and
grid the two coincide to rounding (explicit RK discretisation commutes with linearisation; the
notes remark this for Euler in §8.2); with another grid or method (e.g. ``"dopri5"``) the
variational result approximates the exact sensitivities of the ODE, and the difference to the
discrete sensitivities vanishes as the step shrinks.

Typos in the notes' §8.5 (eq. 8.29-8.34): the dynamics are written ``x' = f(p, u)`` (``x`` is
missing); ``p`` and ``s`` are reused for the input parameters and the number of interpolation
nodes, which need not be the model parameters or the stage count (here ``P`` and ``q``); the
nodes ``tau_i`` of ``l_i`` are not named (they are the interpolation nodes, eq. 7.27: the
polynomial takes the value ``p_{k,i}`` at ``t_k + tau_i dt``); "``k = 0, N - 1``" means
``k = 0, ..., N - 1``; eq. 8.31 ``df/dp = df/du du/dp`` holds only when ``p`` enters through
``u`` alone (with model parameters too, the columns are ``[df/dp, df/du du/dP]``). In the IRK
algorithm the guess "``K_i = x_k``" mixes units (``K`` are derivatives; ``K_i = f(x_k)`` is meant)
and "``Delta w``" is ``Delta K``.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import torch
from torch.func import jvp, vmap

from ._fast import compiled_stepper
from ._irk_core import StageInputs, stacked_call_agrees
from ._irk_dense import extrapolation_matrix
from ._options import check_int, check_state, check_times, raise_shape_change, sample_indices
from .errors import InputValidationError
from .explicit import _failure_messages
from .inputs import CollocationInput
from .jacobians import batch_jacobian
from .methods import EXPLICIT_FIXED, resolve_method
from .newton import NewtonStatus, _default_tol, newton
from .solution import SolverStats, Status
from .tableau import ButcherTableau

__all__ = ["SensitivityResult", "sensitivities", "variational_sensitivities"]

#: a simplified-Newton iteration whose residual shrinks by less than this factor stops the
#: stage solve (``newton``'s ``divergence_ratio``); the Newton matrix is then refreshed at
#: the current stages and the solve resumes
_SLOW_CONTRACTION = 0.5
_MAX_NEWTON_ITER = 50


@dataclass
class SensitivityResult:
    """States and their sensitivities on the output grid (all detached).

    Attributes:
        t: (T,) output times.
        x: (*batch, T, nx) simulated states.
        A: (*batch, T, nx, nx) ``dx_k / dx_0`` (eq. 8.11).
        B: (*batch, T, nx, np) ``dx_k / dp``, or None without parameters.
        C: ``dx_k`` w.r.t. the input parameters, the input's shape appended to (*batch, T, nx):
            (*batch, T, nx, T, nu) ``dx_k / du_j`` for sampled inputs (eq. 8.34),
            (*batch, T, nx, T-1, q, nu) ``dx_k / dP_{j,i}`` for a
            :class:`~integrators.inputs.CollocationInput` (eq. 8.32); None otherwise.
        status: (*batch,) int8 :class:`~integrators.solution.Status` per sample: SUCCESS,
            NON_FINITE where the states or their sensitivities became inf/nan (an explicit
            run that escapes to infinity), or NEWTON_FAILED where an implicit method's stage
            equations failed at a step (then the outputs from the end of that output interval
            on are not finite); such a sample's ``x``, ``A``, ``B`` and ``C`` are NaN from the
            first output time that is not finite on, and ``messages`` name it.
        messages: one line per failed sample.
        stats: :class:`~integrators.solution.SolverStats`: ``n_steps``, ``n_f_evals`` and
            ``n_jac_evals`` (batched calls of ``f`` and of its stage Jacobian),
            ``n_newton_iters`` and ``n_factorizations`` (LU factorisations of the Newton matrix,
            one per step plus one to start, see the module docstring; 0 for explicit tableaus);
            implicit tableaus: ``extra["stacked_stages"]``, whether the stages of a step were
            evaluated in one call of ``f`` with the stage index as leading batch dimension
            (where that reproduces the stage-by-stage values, checked once per run).
    """

    t: torch.Tensor
    x: torch.Tensor
    A: torch.Tensor
    B: torch.Tensor | None = None
    C: torch.Tensor | None = None
    status: torch.Tensor | None = None
    messages: list[str] = field(default_factory=list)
    stats: SolverStats = field(default_factory=SolverStats)

    def __post_init__(self):
        if self.status is None:
            batch = self.x.shape[:-2]
            self.status = torch.zeros(batch, dtype=torch.int8, device=self.x.device)

    @property
    def success(self) -> bool:
        """Whether every sample succeeded."""
        return bool((self.status == Status.SUCCESS).all())


def _model(f: Callable, has_u: bool, has_p: bool) -> Callable:
    """``g(t, x, u, p)`` calling the user's ``f(t, x[, u][, p])``; an output that is not a
    tensor of the shape of ``x`` (broadcasting in the step sums would hide it) raises
    InputValidationError at that call."""

    def g(t, x, u, p):
        args = (t, x) + ((u,) if has_u else ()) + ((p,) if has_p else ())
        out = f(*args)
        if getattr(out, "shape", None) != x.shape:  # t: one time or a step's stage times
            raise_shape_change(out, x, t, "sensitivities: ", changed=False)
        return out

    return g


def _check_model(g: Callable, x: torch.Tensor, t: torch.Tensor, p, u) -> None:
    """Call ``g`` once at ``(t_0, x, u(t_0), p)`` so that a model that does not take the
    arguments it is given (``f(t, x, p)`` with ``p=None``) fails with a message naming the
    calling convention; ``_model`` checks the shape of its output."""
    signature = "f(t, x" + (", u" if u is not None else "") + (", p" if p is not None else "") + ")"
    u0 = None if u is None else (u(t[0]) if callable(u) else u[..., 0, :])
    try:
        with torch.no_grad():
            g(t[0], x, u0, p)
    except TypeError as exc:
        raise InputValidationError(
            f"sensitivities: calling the model as {signature} failed: {exc}. The model gets u "
            "only when u is given and p only when p is given: pass p (and u) or drop the "
            "argument from the model."
        ) from exc


def _as_tensor(value, like: torch.Tensor, name: str) -> torch.Tensor:
    out = torch.as_tensor(value, dtype=like.dtype, device=like.device).detach()
    if not bool(torch.isfinite(out).all()):
        raise InputValidationError(f"sensitivities: {name} contains non-finite entries.")
    return out


def _prepare(x0, t, p, u):
    x0 = check_state(x0, "sensitivities: x0").detach()
    t = check_times(t, x0, "sensitivities: t").detach()
    if p is not None:
        p = _as_tensor(p, x0, "p")
        if p.dim() == 0:
            p = p.reshape(1)
    if isinstance(u, CollocationInput):
        grid = u.t.to(dtype=t.dtype, device=t.device)
        if grid.shape != t.shape or not torch.equal(grid, t):
            raise InputValidationError(
                "sensitivities: the CollocationInput was built on another grid than t; build "
                "it with the same t (its intervals are the output intervals, eq. 8.32)."
            )
        u = CollocationInput(u.coefficients.detach().to(x0), t, u.nodes.to(x0))
    elif u is not None and not callable(u):
        u = _as_tensor(u, x0, "u")
        if u.dim() < 2 or u.shape[-2] != t.shape[0]:
            raise InputValidationError(
                f"sensitivities: sampled u must have shape (T, nu) or (*batch, T, nu) with "
                f"T = {t.shape[0]}, got {tuple(u.shape)}."
            )
    return x0, t, p, u


class _InputParameters:
    """The input parameters of each output interval and the stage inputs they give.

    ``kind`` is "none", "callable" (no sensitivities), "zoh" (samples, eq. 8.34) or
    "collocation" (eq. 8.32). For the last two, interval ``k`` contributes ``size`` parameters
    ``w_k`` (``u_k``: nu; ``vec P_k``: q nu), which are the columns ``k * size`` to
    ``(k + 1) * size`` of the flattened input parameters of shape ``shape``.

    Args:
        u: None, a callable, samples (*batch, T, nu) or a CollocationInput (already prepared).
        tab: the tableau (its nodes ``c``); substeps: steps per output interval.
        differentiated: False keeps the stage inputs but adds no columns (``size`` 0 in ``q``).
    """

    def __init__(self, u, tab: ButcherTableau, substeps: int, differentiated: bool = True):
        self.differentiated = differentiated
        self.kind, self.size, self.shape, self.batch = "callable", 0, (), ()
        self.values = self.weights = None
        if u is None:
            self.kind = "none"
        elif isinstance(u, CollocationInput):
            P = u.coefficients  # (*batch, T-1, q, nu)
            self.kind, self.q, self.nu = "collocation", P.shape[-2], P.shape[-1]
            self.size, self.shape, self.batch = self.q * self.nu, P.shape[-3:], P.shape[:-3]
            self.values = P.flatten(-2)
            # stage i of substep m sits at tau = (m + c_i) / substeps of the interval
            tau = (np.arange(substeps)[:, None] + np.array(tab.c)[None, :]) / substeps
            self.weights = u.weights(torch.as_tensor(tau, dtype=P.dtype, device=P.device))
        elif isinstance(u, torch.Tensor):
            self.kind, self.size, self.values = "zoh", u.shape[-1], u
            self.shape, self.batch = u.shape[-2:], u.shape[:-2]

    @property
    def parameterised(self) -> bool:
        """Whether the input values are columns of ``q`` (differentiated)."""
        return self.differentiated and self.kind in ("zoh", "collocation")

    def interval(self, k: int, batch) -> torch.Tensor:
        """``w_k``: (*batch, size)."""
        return self.values[..., k, :].expand(*batch, self.size)

    def stage_input(self, w: torch.Tensor, m: int, i: int) -> torch.Tensor:
        """The input of stage ``i`` of substep ``m`` from ``w`` (*batch, size): (*batch, nu)."""
        if self.kind == "zoh":
            return w
        return self.weights[m, i] @ w.unflatten(-1, (self.q, self.nu))

    def stacked_stage_input(self, w: torch.Tensor, m: int, batch_ndim: int) -> torch.Tensor:
        """The inputs of all stages of substep ``m`` from ``w``, (s, *batch, size) per stage or
        (*batch, size) shared by the stages: (s, *batch, nu) (held samples: ``w`` itself, the
        same at every stage)."""
        if self.kind == "zoh":
            return w
        weights = self.weights[m].reshape(-1, *(1,) * batch_ndim, self.q, 1)
        return (weights * w.unflatten(-1, (self.q, self.nu))).sum(-2)


def _combine(x, h, coefficients, Ks):
    """``x + h sum_j a_j K_j`` over the nonzero coefficients ``a_j`` (a tableau row or ``b``;
    ``Ks`` may be shorter: the stages so far), added term by term in stage order."""
    for a, K in zip(coefficients, Ks, strict=False):
        if a != 0.0:
            x = x + h * float(a) * K
    return x


def _explicit_step(stage_at, tab, h, nx: int):
    """One explicit step ``z = (x_k, q) -> x_{k+1}`` (eq. 6.26) as a function of ``z``
    (*batch, nx + nq), whose Jacobian is ``[Phi_k Psi_k]`` (eq. 8.18)."""

    def step(z):
        x, q = z[..., :nx], z[..., nx:]
        Ks = []
        for i in range(tab.stages):
            Ks.append(stage_at(i)(torch.cat([_combine(x, h, tab.A[i], Ks), q], -1)))
        return _combine(x, h, tab.b, Ks)

    return step


def _interval_kernel(g, tab: ButcherTableau, substeps: int, n_out, _layout):
    """One output interval of an explicit scheme as one function, for ``torch.compile``.

    The recursion of eq. 8.17 in forward mode: instead of the stage Jacobians ``F_x, F_q`` it
    propagates the tangent matrix ``S = [A B] = dx_k/d(x_0, p)`` directly,
    ``dK_i = F_x^(i) dX_i + F_p^(i) [0 I]`` with ``dX_i = S + h sum_j a_ij dK_j`` (eq.
    8.17-8.18), each stage one Jacobian-vector product batched over the columns of ``S``.
    Compiled, the whole interval is one kernel; the rounding differs from the eager path's
    (``Phi A``, ``Phi B + Psi``) only in the order of the sums.

    The kernel is ``(x, S, p, U, t0, h) -> (x_new, S_new)``: ``x`` (*batch, nx), ``S``
    (*batch, nx, nx + np), ``p`` (*batch, np), ``U`` (*batch, substeps, stages, nu) the stage
    inputs (nu = 0 without input), ``t0`` and ``h`` 0-dim tensors (the interval's start and
    the step).
    """
    # Python floats: dynamo would trace numpy scalars as tensors
    A = np.asarray(tab.A, dtype=np.float64).tolist()
    b, c = np.asarray(tab.b, dtype=np.float64).tolist(), np.asarray(tab.c).tolist()
    s = tab.stages

    def kernel(x, S, p, U, t0, h):
        n_p, nx = p.shape[-1], x.shape[-1]
        eye = torch.eye(n_p, dtype=x.dtype, device=x.device)
        dp = torch.cat([eye.new_zeros(n_p, nx), eye], -1).expand(*p.shape[:-1], n_p, nx + n_p)
        for m in range(substeps):
            tk = t0 + m * h
            Ks, dKs = [], []
            for i in range(s):
                ti = tk + c[i] * h
                xs, dxs = _combine(x, h, A[i], Ks), _combine(S, h, A[i], dKs)
                u = U[..., m, i, :]

                def rhs(xx, pp, ti=ti, u=u):
                    return g(ti, xx, u, pp)

                def column(dx, dpp, xs=xs, rhs=rhs):
                    return jvp(rhs, (xs, p), (dx, dpp))

                K, dK = vmap(column, in_dims=(-1, -1), out_dims=(None, -1))(dxs, dp)
                Ks.append(K)
                dKs.append(dK)
            x, S = _combine(x, h, b, Ks), _combine(S, h, b, dKs)
        return x, S

    return kernel


def _tableau_key(tab: ButcherTableau) -> tuple:
    """A hashable description of the tableau's coefficients (a compile-cache key)."""
    return tuple(np.asarray(tab.A, dtype=np.float64).ravel()) + tuple(tab.b) + tuple(tab.c)


def _stage_inputs(inputs, u, t, tab: ButcherTableau, substeps: int, like) -> torch.Tensor:
    """The input of every stage of every interval: (*batch, T-1, substeps, stages, nu), the
    values the eager loop computes one by one (``nu = 0`` without input)."""
    T, s = t.shape[0], tab.stages
    if inputs.kind == "none":
        return like.new_zeros(T - 1, substeps, s, 0)
    if inputs.kind == "zoh":
        held = inputs.values[..., :-1, :]
        return held[..., None, None, :].expand(*held.shape[:-1], substeps, s, held.shape[-1])
    if inputs.kind == "collocation":
        P = inputs.values.unflatten(-1, (inputs.q, inputs.nu))
        return torch.einsum("msq,...kqn->...kmsn", inputs.weights, P)
    rows = []
    for k in range(T - 1):
        h = (t[k + 1] - t[k]) / substeps
        steps = []
        for m in range(substeps):
            tk = t[k] + m * h
            steps.append(torch.stack([u(tk + float(tab.c[i]) * h) for i in range(s)], -2))
        rows.append(torch.stack(steps, -3))
    return torch.stack(rows, -4)


class _StageFailures:
    """The members whose implicit stage equations failed, recorded step by step.

    A member fails at the step where :meth:`_ImplicitStages.step` gives up on it; from then
    on it is frozen (evaluated at a finite safe state, out of every batch-wide decision) and
    its outputs from the end of that output interval on are NaN.

    Args:
        batch: the batch shape; T: the number of output times; like: a tensor of the state's
            device.
    """

    def __init__(self, batch: torch.Size, T: int, like: torch.Tensor):
        self.frozen = torch.zeros(batch, dtype=torch.bool, device=like.device)
        # host arrays (*batch,): NewtonStatus code (0: none), output index from which the
        # outputs are NaN, and the step, interval and time of the failure
        self.reason = np.zeros(batch, dtype=np.int8)
        self.stop = np.full(batch, T, dtype=np.int64)
        self.where = np.zeros((*batch, 2), dtype=np.int64)
        self.time = np.zeros(batch)

    def record(self, failure: torch.Tensor, k: int, m: int, tk: torch.Tensor) -> None:
        """Freeze the members with a nonzero ``failure`` code (*batch,), failed in step ``m``
        of interval ``k`` starting at ``tk``."""
        new = failure != 0
        if not bool(new.any()):
            return
        self.frozen = self.frozen | new
        new_host = new.cpu().numpy()
        self.reason[new_host] = failure.cpu().numpy()[new_host]
        self.stop[new_host] = k + 1
        self.where[new_host] = (m, k)
        self.time[new_host] = float(tk)

    @property
    def all_frozen(self) -> bool:
        """Whether every member (of a nonempty batch) has failed."""
        return self.frozen.numel() > 0 and bool(self.frozen.all())

    def messages(self, failed: torch.Tensor, t: torch.Tensor, name: str, tol: float) -> list[str]:
        """One line per member of ``failed`` (*batch,): its index, where its stage equations
        failed and why."""
        reasons = {
            NewtonStatus.MAX_ITER: (
                f"did not reach ||r||_inf <= {tol:.3g} in {_MAX_NEWTON_ITER} Newton iterations"
            ),
            NewtonStatus.NON_FINITE: "became non-finite",
            NewtonStatus.SINGULAR: "have a singular Newton matrix I - h A (x) F_x",
        }
        t_host = t.detach().cpu().tolist()
        idx, _ = sample_indices(failed, failed.numel())
        lines = []
        for i in idx:
            at = i if self.reason.ndim else ()
            m, k = self.where[at].tolist()
            lines.append(
                f"sample {i[0] if len(i) == 1 else i}: the stage equations (eq. 8.20) of "
                f"{name!r} {reasons[NewtonStatus(int(self.reason[at]))]} in step {m} of "
                f"interval {k} (t = {float(self.time[at]):.6g}); its outputs from t = "
                f"{t_host[k + 1]:.6g} on are NaN. Try more substeps."
            )
        return lines


class _ImplicitStages:
    """Stages of implicit RK steps and their derivatives, one factorisation per step
    (eq. 8.20-8.28; see the module docstring).

    Keeps the LU factors of the exact Newton matrix ``M = I - h [a_ij F_x^(i)]`` at the last
    converged stages (the next step's simplified-Newton matrix), the last stages (for the next
    starting guess) and the work counters. Every decision (convergence, refreshing the
    matrix, the iteration budget) is per member, so a member gets the numbers it gets alone.

    Args:
        tab: implicit tableau; like: a tensor of the state dtype and device.
        tol: residual tolerance ``||r(K)||_inf`` (units of ``dx/dt``), per sample.
    """

    def __init__(self, tab: ButcherTableau, like: torch.Tensor, tol: float):
        self.s, self.tol = tab.stages, tol
        self.a = torch.as_tensor(np.array(tab.A), dtype=like.dtype, device=like.device)
        self.c = np.array(tab.c, dtype=np.float64)
        # the previous stage polynomial extrapolates into the step when the nodes are distinct
        self.extrapolate = np.unique(self.c).size == self.s
        self.lu = None
        self.K_prev = self.h_prev = None
        self.stack = None  # whether all stages are evaluated in one call (decided once)
        self.n_lu = self.n_iter = self.n_f = self.n_jac = 0

    def _stage_values(self, stage_at, stacked, x, h, K, q, jacobians=False):
        """``F_i`` (*batch, s, nx) at the stages ``K``, and with ``jacobians`` also the stage
        Jacobians ``[F_x^(i) F_q^(i)]`` (*batch, s, nx, nx + nq) (:func:`batch_jacobian`).

        ``stage_at(i)`` is stage ``i``'s function of ``(X_i, q)`` (*batch, nx + nq);
        ``stacked`` that of all stages at once, the stage index a leading batch dimension
        (s, *batch, nx + nq): used where it reproduces the stage-by-stage values (checked
        once per run, :func:`~integrators._irk_core.stacked_call_agrees`)."""
        # (X_i, q) with the stage states X_i = x_k + h sum_j a_ij K_j: (*batch, s, nx + nq)
        X = x[..., None, :] + h * (self.a @ K)
        Z = torch.cat([X, q[..., None, :].expand(*X.shape[:-1], q.shape[-1])], -1)
        self.n_f += self.s
        self.n_jac += self.s if jacobians else 0

        def by_stage(Z):
            return torch.stack([stage_at(i)(Z[..., i, :]) for i in range(self.s)], -2)

        def at_once(Z):
            return stacked(Z.movedim(-2, 0)).movedim(0, -2)

        if self.stack is None:
            self.stack = stacked_call_agrees(by_stage, at_once, Z)
        if not jacobians:
            return at_once(Z) if self.stack else by_stage(Z)
        if self.stack:
            F, J = batch_jacobian(stacked, Z.movedim(-2, 0))
            return F.movedim(0, -2), J.movedim(0, -3)
        pairs = [batch_jacobian(stage_at(i), Z[..., i, :]) for i in range(self.s)]
        return torch.stack([v for v, _ in pairs], -2), torch.stack([d for _, d in pairs], -3)

    def _factorize(self, stage_at, stacked, x, h, K, q, out, update=None):
        """Linearise at ``K``: keeps the LU of ``M`` (of the members in ``update`` (*batch,)
        bool, default all) and returns ``r(K)`` (*batch, s, nx), the stage Jacobians ``F_x``
        (*batch, s, nx, nx), ``F_q`` (*batch, s, nx, nq) and the members (*batch,) bool, not
        ``out``, whose ``M`` is singular. The members ``out`` of the solve and the singular
        ones keep the identity as their factors (finite solves, no effect on the others)."""
        nx = x.shape[-1]
        F, J = self._stage_values(stage_at, stacked, x, h, K, q, jacobians=True)
        Fx, Fq = J[..., :nx], J[..., nx:]
        # M[(i, r), (j, c)] = delta_ij delta_rc - h a_ij F_x^(i)[r, c]
        blocks = torch.einsum("ij,...irc->...irjc", self.a, Fx).flatten(-4, -3).flatten(-2, -1)
        eye = torch.eye(self.s * nx, dtype=x.dtype, device=x.device)
        M = torch.where(out[..., None, None], eye, eye - h * blocks)
        lu, piv, info = torch.linalg.lu_factor_ex(M)
        self.n_lu += 1
        singular = info != 0
        if update is not None:  # the members not updated keep their factors
            singular &= update
            lu = torch.where(update[..., None, None], lu, self.lu[0])
            piv = torch.where(update[..., None], piv, self.lu[1])
        if bool(singular.any()):  # the identity for the singular members
            base = torch.arange(1, self.s * nx + 1, dtype=piv.dtype, device=piv.device)
            lu = torch.where(singular[..., None, None], eye, lu)
            piv = torch.where(singular[..., None], base, piv)
        self.lu = (lu, piv)
        return F - K, Fx, Fq, singular

    def _guess(self, stage_at, x, h, q):
        """Starting stages: the previous stage polynomial extrapolated, else ``f(x_k)``."""
        if self.K_prev is None:
            self.n_f += 1
            f0 = stage_at(0)(torch.cat([x, q], -1))
            return f0[..., None, :].expand(*f0.shape[:-1], self.s, f0.shape[-1])
        if not self.extrapolate:
            return self.K_prev
        L = extrapolation_matrix(self.c, float(h / self.h_prev))
        return torch.as_tensor(L, dtype=x.dtype, device=x.device) @ self.K_prev

    def step(self, stage_at, stacked, h, x, q, seed, frozen, safe):
        """One step: stages ``K_i`` (*batch, nx), ``dK_i/d(x_k, q)`` (*batch, nx, nx + nq) and
        the members (*batch,) whose stage equations failed in this step, as a
        :class:`~integrators.newton.NewtonStatus` code (MAX_ITER, NON_FINITE, SINGULAR; 0
        elsewhere). ``stage_at``, ``stacked``: the stage functions (see
        :meth:`_stage_values`); ``frozen`` (*batch,) bool: the members that failed before, at
        the finite state ``safe`` (*batch, nx) in ``x``.

        The stages come from :func:`~integrators.newton.newton` (simplified, with the kept
        factorisation) on ``K - F(K) = 0``; a member whose residual shrinks by less than
        ``_SLOW_CONTRACTION`` in one iteration stops it, its matrix is refreshed at its current
        stages and its iteration resumes, within ``_MAX_NEWTON_ITER`` iterations of its own.
        A member fails when that budget runs out, when its stages become non-finite or when
        its Newton matrix is singular; from then on it is out of the solve: its stages are
        zero, its residual is zero, its matrix the identity and it evaluates ``f`` at
        ``safe``, so its failure changes no number of the others. The iterations run in rounds
        of at most the smallest budget left to a member still solving: a member that
        reaches the end of a round resumes in the next with the same iterate and matrix,
        which continues its iteration exactly."""
        s, nx = self.s, x.shape[-1]
        failure = torch.zeros(frozen.shape, dtype=torch.int8, device=x.device)
        out = frozen.clone()

        def drop(mask, code):
            """Take the members of ``mask`` still in the solve out of it, for ``code``."""
            failure.masked_fill_(mask & ~out, code)
            out.logical_or_(mask)

        def parked(K):
            """``K`` and ``x`` with the members out of the solve at zero stages and ``safe``."""
            return torch.where(out[..., None, None], 0.0, K), torch.where(out[..., None], safe, x)

        K = self._guess(stage_at, x, h, q)
        drop(~torch.isfinite(K).flatten(-2).all(-1), NewtonStatus.NON_FINITE)
        if self.lu is None:  # first step: a starting Newton matrix at the guess
            K, x_run = parked(K)
            singular = self._factorize(stage_at, stacked, x_run, h, K, q, out)[-1]
            drop(singular, NewtonStatus.SINGULAR)
        left = torch.full(frozen.shape, _MAX_NEWTON_ITER, dtype=torch.int64, device=x.device)
        converged = torch.zeros_like(frozen)
        while True:
            solving = ~out & ~converged
            if not bool(solving.any()):
                break
            K, x_run = parked(K)
            skip = out.clone()

            def stage_equations(k, x_run=x_run, skip=skip):  # K - F(K) of eq. 8.20: (*batch, s nx)
                k = k.unflatten(-1, (s, nx))
                r = self._stage_values(stage_at, stacked, x_run, h, k, q) - k
                return -torch.where(skip[..., None, None], 0.0, r).flatten(-2)

            res = newton(
                stage_equations,
                K.flatten(-2),
                method="simplified",
                factorization=self.lu,
                tol=self.tol,
                max_iter=int(left[solving].min()),
                divergence_ratio=_SLOW_CONTRACTION,
                params=(),  # stage values only: their derivatives are propagated separately
            )
            K = res.x.unflatten(-1, (s, nx))
            left -= res.iterations
            self.n_iter += int(res.iterations.max())
            converged = res.converged & ~out
            drop(res.status == NewtonStatus.NON_FINITE, NewtonStatus.NON_FINITE)
            drop(~converged & (left <= 0), NewtonStatus.MAX_ITER)
            # a kept matrix that contracts too slowly: refreshed at the member's stages
            slow = (res.status == NewtonStatus.DIVERGED) & ~out
            if bool(slow.any()):
                K, x_run = parked(K)
                singular = self._factorize(stage_at, stacked, x_run, h, K, q, out, slow)[-1]
                drop(singular, NewtonStatus.SINGULAR)
        # the one factorisation of this step, at the converged stages: the last correction and
        # every sensitivity column in one solve (eq. 8.24-8.27)
        K, x_run = parked(K)
        r, Fx, Fq, singular = self._factorize(stage_at, stacked, x_run, h, K, q, out)
        drop(singular, NewtonStatus.SINGULAR)
        r = torch.where(out[..., None, None], 0.0, r)
        rhs = Fx @ seed[..., None, :, :]  # (*batch, s, nx, nx + nq)
        rhs[..., nx:] += Fq
        sol = torch.linalg.lu_solve(*self.lu, torch.cat([r[..., None], rhs], -1).flatten(-3, -2))
        sol = sol.unflatten(-2, (s, nx))
        K = torch.where(out[..., None, None], 0.0, K + sol[..., 0])
        self.n_iter += 1
        self.K_prev, self.h_prev = K, h
        return list(K.unbind(-2)), list(sol[..., 1:].unbind(-3)), failure


def sensitivities(
    f: Callable,
    x0,
    t,
    p=None,
    *,
    method: str | ButcherTableau = "rk4",
    u=None,
    substeps: int = 1,
    stages: int | None = None,
    newton_tol: float | None = None,
    input_sensitivities: bool = True,
    derivatives: bool = True,
    compile: bool | str = "auto",
) -> SensitivityResult:
    """Exact sensitivities of a fixed-step Runge-Kutta simulation (notes eq. 8.13-8.34).

    Explicit tableaus propagate the stage derivatives (eq. 8.17-8.18); implicit ones
    ("gauss_legendre", "radau_iia", "implicit_euler", "implicit_midpoint" or an implicit
    tableau) solve the stage equations by Newton and get the stage derivatives from the
    implicit function theorem with the step's one factorisation of the Newton matrix
    (eq. 8.24-8.28, see the module docstring).

    Args:
        f: the model ``f(t, x)``, ``f(t, x, u)``, ``f(t, x, p)`` or ``f(t, x, u, p)``
            (``u`` is passed when given, ``p`` when given) returning (*batch, nx); ``t`` is a
            0-dim tensor. ``p`` arrives with shape (*batch, np), so index it as ``p[..., i]``;
            ``u`` as (*batch, nu) (or what a callable ``u`` returns).
        x0: (*batch, nx) initial states.
        t: (T,) strictly increasing output grid.
        p: None, (np,) parameters shared by the batch, or (*batch, np).
        method: a tableau or its name (default "rk4"; every name of
            :data:`integrators.methods.METHOD_NAMES` but "auto"); the run is at fixed steps,
            ``b_err`` is ignored.
        u: the input, one of

            * None;
            * samples (T, nu) or (*batch, T, nu) held piecewise constant on the output grid
              (eq. 8.34; the last sample is not used): ``C = dx_k/du_j``;
            * a :class:`~integrators.inputs.CollocationInput` built on the same ``t``:
              polynomials on each output interval given by their values ``P`` (T-1, q, nu) or
              (*batch, T-1, q, nu) at ``q`` nodes (eq. 8.32-8.33), evaluated at every stage
              time: ``C = dx_k/dP``;
            * a callable ``u(t)`` (no input sensitivities).
        substeps: equal RK steps per output interval.
        stages: number of stages for "gauss_legendre" (default 2) / "radau_iia" (default 3);
            refused for other methods.
        newton_tol: implicit methods: the stage equations are solved to
            ``||r(K)||_inf <= newton_tol`` (units of ``dx/dt``) before the last correction;
            default ``max(1e-10, 100 eps)`` of the dtype.
        input_sensitivities: False skips ``C`` for sampled and collocation inputs: the stage
            inputs are the same, only the input columns are not propagated (``C`` is None).
            Use it when only ``dx/dx0`` and ``dx/dp`` are wanted: ``C`` has
            ``T * T * nx * nu`` entries per batch member, quadratic in the record length.
        derivatives: False returns only the states (``A``, ``B``, ``C`` None): the same
            discrete simulation, arithmetic for arithmetic, without the derivative work for an
            eager explicit tableau (an implicit one still needs the Newton matrix; a compiled
            run uses the kernel of the runs with derivatives and drops them), e.g. for the
            trial points of a line search whose Jacobians come from this function.
        compile: explicit tableaus without input sensitivities: True runs each output
            interval as one ``torch.compile``-d kernel (forward-mode stage derivatives, see
            :func:`_interval_kernel`), False never; ``"auto"`` (default) compiles once
            ``integrators._fast.compiled.AUTO_COMPILE_EAGER_SECONDS`` seconds were spent
            stepping eagerly with the same ``f``, configuration and batch shape over all
            calls, this run's predicted eager time included (compiled kernels are cached
            per ``f``; runs with and without ``derivatives`` share one kernel). A
            model the compiler or forward-mode differentiation cannot handle (one calling
            autograd or a Newton solver inside ``f``) runs eagerly; ``stats.extra`` reports
            ``compiled``, ``compile_fallback`` (why a wanted compile did not happen) and
            ``compile_s``.

    Returns:
        :class:`SensitivityResult` with ``x``, ``A = dx_k/dx_0``, ``B = dx_k/dp``, ``C`` (the
        input sensitivities, shapes above), ``stats`` and per sample ``status`` and
        ``messages``: a sample whose states or sensitivities become inf/nan is NON_FINITE;
        with an implicit method, a sample whose stage equations fail at a step (not solved
        within the Newton budget, non-finite, or a singular Newton matrix) is NEWTON_FAILED.
        Either way its outputs are NaN from the failing output time on, and the other
        samples get the numbers they get alone (a failed implicit sample is frozen: see
        :meth:`_ImplicitStages.step`); a run whose samples all fail returns their statuses.

    Raises:
        InputValidationError: bad shapes or grid, non-finite data, substeps < 1, a
            CollocationInput on another grid, ``stages`` for a method of fixed stages.
        TableauError: an unknown method or "auto".
    """
    x0, t, p, u = _prepare(x0, t, p, u)
    resolved = resolve_method(method)
    tab = resolved.tableau(stages)
    if newton_tol is not None and tab.is_explicit:
        raise InputValidationError(
            f"sensitivities: newton_tol={newton_tol!r} applies to implicit methods (their stage "
            f"equations) only, not to the explicit method {resolved.name!r}: remove newton_tol."
        )
    substeps = check_int(substeps, "sensitivities: substeps")
    inputs = _InputParameters(u, tab, substeps, differentiated=bool(input_sensitivities))
    g = _model(f, u is not None, p is not None)
    nx, n_p = x0.shape[-1], (0 if p is None else p.shape[-1])
    try:
        batch = torch.broadcast_shapes(
            x0.shape[:-1], () if p is None else p.shape[:-1], inputs.batch
        )
    except RuntimeError:
        raise InputValidationError(
            f"sensitivities: the batch shapes of x0 {tuple(x0.shape[:-1])}, p "
            f"{None if p is None else tuple(p.shape[:-1])} and u {tuple(inputs.batch)} do not "
            "broadcast."
        ) from None
    x = x0.expand(*batch, nx).clone()
    _check_model(g, x, t, None if p is None else p.expand(*batch, n_p), u)
    eye = torch.eye(nx, dtype=x.dtype, device=x.device)
    T, nw = t.shape[0], (inputs.size if inputs.parameterised else 0)
    nq = n_p + nw
    A = eye.expand(*batch, nx, nx).clone()
    B = x.new_zeros(*batch, nx, n_p)
    # input sensitivities, flattened: columns k * nw .. (k + 1) * nw belong to interval k
    C = x.new_zeros(*batch, nx, inputs.shape.numel()) if inputs.parameterised else None
    outputs = [(x, A, B, C)]  # per output time
    seed = torch.cat([eye, eye.new_zeros(nx, nq)], -1).expand(*batch, nx, nx + nq)
    solver = None
    # stacked stage times t_k + c h broadcast like stacked stage states (s, *batch, nx)
    c_stacked = torch.as_tensor(np.array(tab.c), dtype=t.dtype, device=t.device)
    c_stacked = c_stacked.reshape(-1, *(1,) * (len(batch) + 1))
    if not tab.is_explicit:
        tol = _default_tol(x.dtype) if newton_tol is None else newton_tol
        solver = _ImplicitStages(tab, x, float(tol))
        stopped = _StageFailures(batch, T, x)
        safe = x.clone()  # where failed members evaluate f (finite: x0 is validated)
    p_batch = x.new_zeros(*batch, 0) if p is None else p.expand(*batch, n_p)
    n_steps = n_f = n_jac = 0

    def interval_kernel(mode):
        """The compiled interval kernel of this run (a Stepper), its stage inputs and ``p``."""
        # one kernel with and without derivatives: a run without them drops S (one compile
        # serves e.g. a fit's Jacobians and its line-search trials)
        config = ("sensitivities", _tableau_key(tab), substeps, inputs.kind, n_p)
        with torch.no_grad():  # the results are detached: no graph through the kernel
            stepper = compiled_stepper(
                f,
                config,
                compile=mode,
                x0=x,
                make_chunk=lambda slots, *layout: _interval_kernel(
                    _model(slots[0], u is not None, p is not None), tab, substeps, *layout
                ),
                callables=(f,),
                n_out=1,
            )
        if not stepper.active:
            return stepper, None, None
        stage_u = _stage_inputs(inputs, u, t, tab, substeps, x)
        if inputs.kind in ("zoh", "collocation"):
            stage_u = stage_u.expand(*batch, *stage_u.shape[-4:])
        # materialised: forward-mode duals of a broadcast view (stride 0) fail to compile
        return stepper, stage_u, p_batch.contiguous()

    fast = None
    if tab.is_explicit and not inputs.parameterised and compile is not False:
        fast, stage_u, p_kernel = interval_kernel(compile)
    tic = time.perf_counter()
    for k in range(T - 1):
        # "auto": compile for the rest of the run once its predicted eager time would reach
        # the threshold (the eager intervals so far, extrapolated to the whole record)
        elapsed = time.perf_counter() - tic
        if fast is not None and k > 0 and fast.worth_compiling(elapsed * (T - 1) / k):
            fast.add_eager_seconds(elapsed)
            fast, stage_u, p_kernel = interval_kernel(True)
            tic = time.perf_counter()
        if solver is not None and stopped.all_frozen:  # nothing left to solve: outputs held
            n_steps += substeps
            outputs.append((x, A, B, C))
            continue
        h = (t[k + 1] - t[k]) / substeps
        if fast is not None and fast.active:
            S = torch.cat([A, B], -1)
            with torch.no_grad():
                out = fast(x, S, p_kernel, stage_u[..., k, :, :, :], t[k], h)
            if out is not None:
                x, S = out
                if derivatives:
                    A, B = S[..., :nx], S[..., nx:]
                n_steps += substeps
                n_f += tab.stages * substeps
                n_jac += tab.stages * substeps  # the kernel propagates S either way
                outputs.append((x, A, B, C))
                continue
        held = inputs.interval(k, batch) if inputs.kind in ("zoh", "collocation") else None
        # q = (p, w_k): the quantities differentiated on this interval, (*batch, nq)
        q = torch.cat([p_batch] + ([held] if inputs.parameterised else []), -1)
        for m in range(substeps):
            tk = t[k] + m * h

            def stage_at(i, tk=tk, h=h, m=m, held=held):
                ti = tk + float(tab.c[i]) * h
                u_call = u(ti) if inputs.kind == "callable" else None

                def stage(z):
                    zp = z[..., nx : nx + n_p] if p is not None else None
                    w = z[..., nx + n_p :] if inputs.parameterised else held
                    zu = u_call if w is None else inputs.stage_input(w, m, i)
                    return g(ti, z[..., :nx], zu, zp)

                return stage

            def stacked_stages(z, tk=tk, h=h, m=m, held=held):
                """All stages at once: z (s, *batch, nx + nq) -> (s, *batch, nx)."""
                ti = tk + c_stacked * h
                zp = z[..., nx : nx + n_p] if p is not None else None
                w = z[..., nx + n_p :] if inputs.parameterised else held
                zu = None if w is None else inputs.stacked_stage_input(w, m, len(batch))
                if inputs.kind == "callable":
                    zu = StageInputs([u(tk + float(c) * h) for c in tab.c], len(batch)).stacked
                return g(ti, z[..., :nx], zu, zp)

            n_steps += 1
            if solver is None:
                n_f += tab.stages
                step = _explicit_step(stage_at, tab, h, nx)
                if not derivatives:
                    x = step(torch.cat([x, q], -1)).detach()
                    continue
                # [Phi Psi] of eq. 8.18: the step's Jacobian, one batched reverse pass
                x, J = batch_jacobian(step, torch.cat([x, q], -1))
                n_jac += tab.stages
            else:
                Ks, dKs, failure = solver.step(
                    stage_at, stacked_stages, h, x, q, seed, stopped.frozen, safe
                )
                x = _combine(x, h, tab.b, Ks)
                stopped.record(failure, k, m, tk)
                # failed members: at the safe state, their A, B, C held (Phi = I, Psi = 0)
                x = torch.where(stopped.frozen[..., None], safe, x)
                if not derivatives:
                    continue
                J = torch.where(
                    stopped.frozen[..., None, None], seed, _combine(seed, h, tab.b, dKs)
                )
            Phi, Psi = J[..., :nx], J[..., nx:]  # eq. 8.18b-c / 8.28b-c
            A = Phi @ A
            B = Phi @ B + Psi[..., :n_p]
            if C is not None:  # columns of later intervals are still zero (causality)
                lo, hi = k * nw, (k + 1) * nw
                head = Phi @ C[..., :hi]
                head[..., lo:hi] += Psi[..., n_p:]
                C = torch.cat([head, C[..., hi:]], -1)
        outputs.append((x, A, B, C))
    if fast is not None and not fast.active:
        fast.add_eager_seconds(time.perf_counter() - tic)
    stats = SolverStats(n_f_evals=n_f, n_steps=n_steps, n_jac_evals=n_jac)
    if fast is not None:
        stats.extra.update(fast.stats())
    else:
        why = None
        if compile is True:
            this = (
                "an implicit method"
                if solver is not None
                else "input sensitivities (pass input_sensitivities=False where C is not needed)"
            )
            why = (
                "compiled kernels serve explicit tableaus without input sensitivities; this run "
                f"has {this}"
            )
        stats.extra.update(compiled=False, compile_fallback=why, compile_s=0.0)
    if solver is not None:
        stats.n_f_evals, stats.n_jac_evals = solver.n_f, solver.n_jac
        stats.n_newton_iters, stats.n_factorizations = solver.n_iter, solver.n_lu
        stats.extra["stacked_stages"] = bool(solver.stack)
    xs, As, Bs, Cs = zip(*outputs, strict=True)
    return _with_failures(
        SensitivityResult(
            t=t,
            x=torch.stack(xs, -2),
            A=torch.stack(As, -3) if derivatives else None,
            B=None if p is None or not derivatives else torch.stack(Bs, -3),
            C=None if C is None else torch.stack(Cs, -3).unflatten(-1, inputs.shape),
            stats=stats,
        ),
        None if solver is None else (stopped, tab.name, solver.tol),
    )


def _with_failures(res: SensitivityResult, stages=None) -> SensitivityResult:
    """``res`` with its failed samples marked, their outputs NaN from the failure on, and one
    message each: NON_FINITE where the states or sensitivities are not finite at some output
    time (inf/nan are absorbing in a run; the wording of :func:`~integrators.odeint.odeint`),
    NEWTON_FAILED where ``stages`` (a :class:`_StageFailures`, the method's name and the
    Newton tolerance; implicit methods) says the stage equations failed first."""
    T = res.x.shape[-2]
    outputs = {n: v for n in ("x", "A", "B", "C") if (v := getattr(res, n)) is not None}
    bad = False  # (*batch, T): an entry of an output time (*batch, T, ...) is not finite
    for value in outputs.values():
        bad = bad | ~torch.isfinite(value).all(dim=tuple(range(res.x.dim() - 1, value.dim())))
    first = torch.where(bad.any(-1), bad.to(torch.int8).argmax(-1), T)
    nonfinite = first < T
    if stages is not None:
        stop = torch.as_tensor(stages[0].stop, device=first.device).reshape(first.shape)
        stage_failed = stop < first
        nonfinite &= ~stage_failed
        first = torch.minimum(first, stop)
    failed = first < T
    if not bool(failed.any()):
        return res
    late = torch.arange(T, device=bad.device) >= first.unsqueeze(-1)  # (*batch, T)
    for name, value in outputs.items():
        mask = late.reshape(*late.shape, *([1] * (value.dim() - late.dim())))
        setattr(res, name, torch.where(mask, torch.full_like(value, float("nan")), value))
    res.status = torch.where(nonfinite, Status.NON_FINITE.value, res.status).to(torch.int8)
    res.messages = []
    if stages is not None:
        res.status.masked_fill_(stage_failed, Status.NEWTON_FAILED.value)  # made above
        res.messages = stages[0].messages(stage_failed, res.t, *stages[1:])
    res.messages += _failure_messages(nonfinite, first, res.t)
    return res


def variational_sensitivities(
    f: Callable,
    x0,
    t,
    p=None,
    *,
    method: str | ButcherTableau = "rk4",
    u=None,
    **odeint_options,
) -> SensitivityResult:
    """Sensitivities from the variational equations (notes eq. 8.8), integrated by ``odeint``.

    The augmented state ``(x, vec A, vec B)`` obeys ``x' = f``, ``A' = F_x A`` (A(0) = I),
    ``B' = F_x B + F_p`` (B(0) = 0), with batched autograd Jacobians ``F_x, F_p``.

    Args:
        f, x0, t, p, u: as in :func:`sensitivities` (``u``: samples, a callable or a
            :class:`~integrators.inputs.CollocationInput`, which ``odeint`` calls as ``u(t)``;
            no input sensitivities are formed).
        method: any ``odeint`` method, e.g. "rk4" (same discretisation as the simulation:
            identical to :func:`sensitivities`) or "dopri5" (near-exact ODE sensitivities).
        **odeint_options: passed to :func:`~integrators.odeint.odeint` (``substeps``,
            ``rtol``, ``atol``, ``interpolation``, ...).

    Returns:
        :class:`SensitivityResult` with ``x``, ``A`` and ``B`` (``C`` is None).
    """
    from .odeint import odeint

    x0, t, p, u = _prepare(x0, t, p, u)
    g = _model(f, u is not None, p is not None)
    nx, n_p = x0.shape[-1], (0 if p is None else p.shape[-1])
    batch = torch.broadcast_shapes(x0.shape[:-1], () if p is None else p.shape[:-1])
    x0 = x0.expand(*batch, nx)
    _check_model(g, x0, t, None if p is None else p.expand(*batch, n_p), u)
    eye = torch.eye(nx, dtype=x0.dtype, device=x0.device)

    def augmented(tt, z, *uu):
        x = z[..., :nx]
        A = z[..., nx : nx + nx * nx].unflatten(-1, (nx, nx))
        B = z[..., nx + nx * nx :].unflatten(-1, (nx, n_p))
        ui = uu[0] if uu else None
        parts = [x] if p is None else [x, p.expand(*z.shape[:-1], n_p)]

        def rhs(w):
            return g(tt, w[..., :nx], ui, w[..., nx:] if p is not None else None)

        fx, J = batch_jacobian(rhs, torch.cat(parts, -1))
        Fx, Fp = J[..., :nx], J[..., nx:]
        return torch.cat([fx, (Fx @ A).flatten(-2), (Fx @ B + Fp).flatten(-2)], -1)

    z0 = torch.cat([x0, eye.expand(*batch, nx, nx).flatten(-2), x0.new_zeros(*batch, nx * n_p)], -1)
    with torch.no_grad():
        if resolve_method(method).kind == EXPLICIT_FIXED:  # autograd Jacobians inside the rhs
            odeint_options.setdefault("compile", False)
        sol = odeint(augmented, z0, t, method=method, u=u, **odeint_options)
    z = sol.x
    return SensitivityResult(
        t=t,
        x=z[..., :nx],
        A=z[..., nx : nx + nx * nx].unflatten(-1, (nx, nx)),
        B=None if p is None else z[..., nx + nx * nx :].unflatten(-1, (nx, n_p)),
        status=sol.status,
        messages=sol.messages,
        stats=sol.stats,
    )
