"""Batched Newton methods for nonlinear equations and unconstrained minimisation (notes §3).

``newton`` solves ``phi(x, *args) = 0`` for ``x`` independently for every member of a batch:

- ``method="full"``: full Newton steps ``x <- x - J(x)^{-1} phi(x)`` (eq. 3.5-3.9), quadratic
  convergence near a regular root (Theorem 3).
- ``method="damped"``: reduced steps ``x <- x + t dx`` with ``t`` found by backtracking on the
  merit function ``||phi||_2^2`` with the Armijo condition. The Newton step is a descent
  direction of that merit function (Theorem 4, eq. 3.30-3.32: its slope is ``-2 ||phi||^2``).
- ``method="simplified"``: the Jacobian (or a user-supplied approximation ``M``) is evaluated and
  factorised once and reused; convergence is linear with rate ``kappa = ||I - M^{-1} J||``
  (Theorem 6, eq. 3.45-3.47).

The solution is differentiable with respect to the tensors in ``args`` (and optional closure
``params``) by the implicit function theorem (eq. 3.40): the backward pass solves one linear
system with the transposed Jacobian at the converged point, so no Newton iteration is stored
and memory does not grow with the number of iterations. ``x0`` receives no gradient. Under
``create_graph=True`` the backward pass is itself differentiable and exact to second order
(Hessians and Hessian-vector products through a solve).

``minimize`` applies the same machinery to ``min_theta Phi(theta)`` with the exact Hessian
(eq. 3.49-3.52), to least-squares residuals with the regularised Gauss-Newton Hessian
``J^T J + alpha I`` (eq. 3.57-3.61), or, by Levenberg-Marquardt with adaptive damping, to
``sum_k rho(r_k)`` for a robust per-residual loss ``rho`` (one iteration loop for all three).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from enum import IntEnum

import torch
from torch.autograd import forward_ad

from ._options import check_flag, check_int, check_nonnegative, check_positive, check_state
from .block_jacobian import BlockJacobian
from .block_tridiagonal import BorderedBlockTridiagonal
from .errors import ConvergenceError, InputValidationError, SingularMatrixError
from .jacobians import batch_jacobian, graph_nodes, jacobian_rows

__all__ = [
    "MinimizeResult",
    "NewtonResult",
    "NewtonStatus",
    "minimize",
    "newton",
]

_ARMIJO = 1e-4
_MAX_BACKTRACKS = 30
_MAX_SHOWN = 10


class NewtonStatus(IntEnum):
    """Per-sample outcome of :func:`newton` / :func:`minimize`, stored as int8 codes."""

    CONVERGED = 0
    MAX_ITER = 1  # the iteration budget ran out
    # the (approximate) Jacobian / Hessian could not be factorised: for newton, an LU pivot
    # at most n eps times the largest entry of its row of the matrix
    SINGULAR = 2
    NON_FINITE = 3  # phi (at every trial step of "damped"), its Jacobian or the iterate: inf/nan
    LINE_SEARCH_FAILED = 4  # no step length in (0, 1] decreased the merit function
    DIVERGED = 5  # the residual grew by more than ``divergence_ratio`` in one iteration
    INTERRUPTED = 6  # a KeyboardInterrupt stopped :func:`minimize` (``catch_interrupt=True``)


@dataclass
class NewtonResult:
    """The result of :func:`newton`.

    Attributes:
        x: (*batch, n) final iterates (differentiable w.r.t. ``args``/``params`` by the IFT).
        converged: (*batch,) bool, ``||phi(x)||_inf <= tol``.
        status: (*batch,) int8 :class:`NewtonStatus` codes.
        iterations: (*batch,) int64 Newton updates taken by each member.
        residual_norms: (iters + 1, *batch) ``||phi||_inf`` before each iteration; a member that
            has stopped keeps its final value.
        step_sizes: (iters, *batch) step lengths ``t`` taken (1 for full steps, 0 once stopped).
        n_phi_evals: batched evaluations of ``phi`` (line-search trials included).
        n_jac_evals: batched Jacobian evaluations.
        n_factorizations: batched LU factorisations.
        factorization: ``(LU, pivots)`` of the last factorised matrix (reusable by passing
            ``factorization=`` to a later simplified-Newton call), or None.
        x_history: (iters + 1, *batch, n) iterates when ``return_history=True``, else None.
        messages: one line per member that did not converge (the first few), naming its index.
    """

    x: torch.Tensor
    converged: torch.Tensor
    status: torch.Tensor
    iterations: torch.Tensor
    residual_norms: torch.Tensor
    step_sizes: torch.Tensor
    n_phi_evals: int = 0
    n_jac_evals: int = 0
    n_factorizations: int = 0
    factorization: tuple[torch.Tensor, torch.Tensor] | None = None
    x_history: torch.Tensor | None = None
    messages: list[str] = field(default_factory=list)

    @property
    def contraction(self) -> torch.Tensor:
        """(*batch,) last observed ratio ``||phi_{k+1}|| / ||phi_k||`` (linear rate, Thm. 6)."""
        r = _informative_tail(self.residual_norms, self.iterations, 2)
        return r[..., 1] / r[..., 0]

    @property
    def observed_order(self) -> torch.Tensor:
        """(*batch,) estimate ``log(r_{k+1}/r_k) / log(r_k/r_{k-1})`` of the convergence order.

        About 2 for exact Newton near a regular root (Theorem 3) and 1 for an approximate
        Jacobian (Theorem 6); NaN for members with fewer than three residuals above the
        rounding floor (e.g. linear problems solved in one step).
        """
        r = _informative_tail(self.residual_norms, self.iterations, 3)
        return torch.log(r[..., 2] / r[..., 1]) / torch.log(r[..., 1] / r[..., 0])


@dataclass
class MinimizeResult:
    """The result of :func:`minimize`.

    Attributes:
        theta: (*batch, n) minimisers.
        converged: (*batch,) bool.
        status: (*batch,) int8 :class:`NewtonStatus` codes.
        iterations: (*batch,) int64.
        loss: (*batch,) final loss (``0.5 ||r||^2`` for Gauss-Newton, ``sum rho(r_k)`` for
            Levenberg-Marquardt).
        loss_history: (iters + 1, *batch) loss before each iteration.
        grad: (*batch, n) gradient at ``theta``.
        hessian: (*batch, n, n) the Hessian used at ``theta`` (exact, or ``J^T C J`` for the
            residual methods, ``C = 1`` for Gauss-Newton; without regularisation); a
            :class:`~integrators.block_tridiagonal.BorderedBlockTridiagonal` for
            Levenberg-Marquardt with a :class:`~integrators.block_jacobian.BlockJacobian`
            that has a chain (``.dense()`` gives the matrix).
        J: (*batch, m, n) residual Jacobian at ``theta`` (residual methods only), e.g. for
            the covariance ``sigma^2 (J^T J)^{-1}`` of a least-squares estimate; the
            :class:`~integrators.block_jacobian.BlockJacobian` where ``jacobian`` gave one.
        residual: (*batch, m) residual at ``theta`` (residual methods only).
        n_fun_evals: batched evaluations of the objective / residual.
        messages: lines for members that did not converge.
        damping: (*batch,) final relative damping ``lam`` (Levenberg-Marquardt only).
    """

    theta: torch.Tensor
    converged: torch.Tensor
    status: torch.Tensor
    iterations: torch.Tensor
    loss: torch.Tensor
    loss_history: torch.Tensor
    grad: torch.Tensor
    hessian: torch.Tensor | BorderedBlockTridiagonal
    J: torch.Tensor | BlockJacobian | None = None
    residual: torch.Tensor | None = None
    n_fun_evals: int = 0
    messages: list[str] = field(default_factory=list)
    damping: torch.Tensor | None = None


# ----------------------------------------------------------------------------- helpers
def _informative_tail(norms: torch.Tensor, iterations: torch.Tensor, k: int) -> torch.Tensor:
    """The last ``k`` residual norms of each member above the rounding floor: (*batch, k)."""
    eps = torch.finfo(norms.dtype).eps
    floor = 100 * eps * torch.clamp(norms[0], min=1.0)
    above = norms > floor  # (iters + 1, *batch)
    column = (-1, *([1] * iterations.dim()))  # a (len, 1, ..., 1) view against (*batch,)
    steps = torch.arange(norms.shape[0], device=norms.device).view(column)
    valid = above & (steps <= iterations)
    last = torch.where(valid, steps, torch.full_like(steps, -1)).amax(dim=0)  # (*batch,)
    idx = last.unsqueeze(0) - torch.arange(k - 1, -1, -1, device=norms.device).view(column)
    vals = norms.gather(0, idx.clamp(min=0))
    vals = torch.where(idx >= 0, vals, torch.full_like(vals, float("nan")))
    return vals.movedim(0, -1)


def _detach(args):
    return tuple(a.detach() if isinstance(a, torch.Tensor) else a for a in args)


def _refuse_forward_mode(tensors) -> None:
    """Refuse dual tensors: the solve's derivatives are attached for reverse mode only."""
    if any(
        isinstance(a, torch.Tensor) and forward_ad.unpack_dual(a).tangent is not None
        for a in tensors
    ):
        raise InputValidationError(
            "newton: forward-mode derivatives (dual tensors of torch.autograd.forward_ad, "
            "batch_jacobian(strategy='forward')) do not pass through the solve, whose "
            "derivatives come from the implicit function theorem in reverse mode; "
            "differentiate with backward, torch.autograd.grad or batch_jacobian(strategy="
            "'vmap' or 'rows')."
        )


def _default_tol(dtype) -> float:
    return max(1e-10, 100 * torch.finfo(dtype).eps)


def _lu(M: torch.Tensor):
    LU, pivots, info = torch.linalg.lu_factor_ex(M)
    finite = torch.isfinite(M).flatten(-2).all(-1)
    ok = (info == 0) & finite
    if bool(ok.any()):
        # each pivot against the largest entry of the row of M it came from (M = P L U): a
        # row-scaled test, so a well-posed matrix with rows of very different sizes (equations
        # in different units, e.g. diag(1e9, 1e-9)) is not mistaken for a singular one
        perm = torch.lu_unpack(LU, pivots, unpack_data=False)[0]
        rows = perm.transpose(-1, -2) @ M.abs().amax(-1, keepdim=True)
        scale = rows[..., 0].clamp(min=torch.finfo(M.dtype).tiny)
        diag = torch.diagonal(LU, dim1=-2, dim2=-1).abs()
        ok = ok & (diag > M.shape[-1] * torch.finfo(M.dtype).eps * scale).all(-1)
    # keep the factors of failed members harmless (identity) so solves stay finite
    eye = torch.eye(M.shape[-1], dtype=M.dtype, device=M.device).expand_as(M)
    LU = torch.where(ok[..., None, None], LU, eye)
    base = torch.arange(1, M.shape[-1] + 1, dtype=pivots.dtype, device=pivots.device)
    pivots = torch.where(ok[..., None], pivots, base.expand_as(pivots))
    return LU, pivots, ok


def _lu_solve(LU, pivots, rhs):
    return torch.linalg.lu_solve(LU, pivots, rhs.unsqueeze(-1)).squeeze(-1)


def _describe(status, norms, label="residual") -> list[str]:
    """One line per member that did not converge (the first ``_MAX_SHOWN``), naming its index,
    its status and its final ``norms`` value; one host transfer for all of them."""
    failed = status != NewtonStatus.CONVERGED
    bad = torch.nonzero(failed)
    if bad.shape[0] == 0:
        return []
    shown = bad[:_MAX_SHOWN]
    codes = status[failed][:_MAX_SHOWN].tolist()
    values = norms.expand(status.shape)[failed][:_MAX_SHOWN].tolist()
    lines = [
        f"sample {tuple(i) if len(i) != 1 else i[0]}: {NewtonStatus(c).name.lower()}, "
        f"{label} {v:.3e}"
        for i, c, v in zip(shown.tolist(), codes, values, strict=True)
    ]
    if bad.shape[0] > _MAX_SHOWN:
        lines.append(f"... and {bad.shape[0] - _MAX_SHOWN} more")
    return lines


# -------------------------------------------------------------------- implicit function
class _ImplicitSolution(torch.autograd.Function):
    """Attach IFT gradients (eq. 3.40) to a converged root ``x*`` of ``phi(x, *args) = 0``.

    Backward: one evaluation of ``phi`` at ``x*`` gives the exact Jacobian ``J(x*)`` (its rows
    in one vmapped pass) and, after ``J(x*)^T lam = grad_x`` is solved once,
    ``grad_{args, params} = -(dphi/d(args, params))^T lam`` by one vector-Jacobian product.
    Under ``create_graph=True`` the gradient is instead built from differentiable operations
    (:func:`_second_order_root`), so second derivatives through the solve are exact too.
    """

    @staticmethod
    def forward(ctx, phi, x_star, n_args, *inputs):
        ctx.phi, ctx.x_star, ctx.n_args, ctx.inputs = phi, x_star, n_args, inputs
        return x_star.clone()

    @staticmethod
    def backward(ctx, grad_x):
        inputs = list(ctx.inputs)
        wanted = [
            i for i, t in enumerate(inputs) if isinstance(t, torch.Tensor) and t.requires_grad
        ]
        create_graph = torch.is_grad_enabled()
        with torch.enable_grad():
            # one evaluation at x* serves J (rows wrt x) and, first order, the product with
            # the arguments (fresh graph leaves) and closure parameters
            x_star = ctx.x_star.detach().requires_grad_(True)
            args = _detach(inputs[: ctx.n_args]) if create_graph else inputs[: ctx.n_args]
            if not create_graph:
                for i, t in enumerate(args):
                    if isinstance(t, torch.Tensor):
                        args[i] = t.detach().requires_grad_(i in wanted)
            y = ctx.phi(x_star, *args)
            (J,) = jacobian_rows(y, (x_star,), batched=True)
        LU, pivots, ok = _lu(J)
        if not bool(ok.all()):
            bad = torch.nonzero(~ok).tolist()[:_MAX_SHOWN]
            raise SingularMatrixError(
                "implicit-function gradient: the Jacobian dphi/dx is singular at the solution "
                f"for sample(s) {bad}; the root is not regular (eq. 3.38), so x(args) is not "
                "differentiable there."
            )
        if create_graph:  # a differentiable backward
            grads = _second_order_root(ctx, LU, pivots, grad_x, wanted)
        else:
            lam = torch.linalg.lu_solve(LU, pivots, grad_x.unsqueeze(-1), adjoint=True)
            targets = [args[i] if i < ctx.n_args else inputs[i] for i in wanted]
            # retained: the graph of a closure tensor computed outside phi (reached through
            # its leaves) belongs to the caller, who may differentiate through it again
            grads = torch.autograd.grad(
                y, targets, -lam.squeeze(-1), allow_unused=True, retain_graph=True
            )
        out = [None] * len(inputs)
        for i, g in zip(wanted, grads, strict=True):
            out[i] = torch.zeros_like(inputs[i]) if g is None else g
        return (None, None, None, *out)


def _second_order_root(ctx, LU, pivots, grad_x, wanted):
    """Vector-Jacobian product ``grad_x^T dx*/d(inputs[wanted])`` as a differentiable graph:
    the gradient, taken with ``create_graph``, of :func:`root_with_derivatives`. Each argument
    enters as ``a + delta`` with a zero leaf ``delta``: its gradient is the partial derivative
    through this solve only, while the graph still reaches ``a``. A closure parameter's
    gradient through ``x`` also follows the arguments computed from it; that path, which
    autograd adds again through the arguments' own gradients, is subtracted, leaving the
    partial derivative through the closure."""
    inputs = list(ctx.inputs)
    args = list(inputs[: ctx.n_args])
    with torch.enable_grad():
        deltas, arg_ids = [], [i for i in wanted if i < ctx.n_args]
        for i in arg_ids:
            deltas.append(torch.zeros_like(args[i], requires_grad=True))
            args[i] = args[i] + deltas[-1]
        params = [inputs[i] for i in wanted if i >= ctx.n_args]
        x = root_with_derivatives(
            lambda x: ctx.phi(x, *args),
            ctx.x_star,
            lambda r: _lu_solve(LU, pivots, r),
        )
        grads = torch.autograd.grad(
            x, deltas + params, grad_x, create_graph=True, allow_unused=True
        )
        arg_grads, param_grads = list(grads[: len(deltas)]), list(grads[len(deltas) :])
        through_args = [
            (inputs[i], g) for i, g in zip(arg_ids, arg_grads, strict=True) if g is not None
        ]
        if params and through_args:
            outputs, vectors = zip(*through_args, strict=True)
            counted = torch.autograd.grad(
                outputs, params, vectors, create_graph=True, allow_unused=True
            )
            param_grads = [
                g if c is None or g is None else g - c
                for g, c in zip(param_grads, counted, strict=True)
            ]
    return arg_grads + param_grads


def root_with_derivatives(residual: Callable, x_star: torch.Tensor, solve: Callable, r_star=None):
    """The root ``x*`` of ``residual(x) = 0`` with its first and second derivatives attached
    (implicit function theorem, eq. 3.40, and its derivative).

    ``x1 = x* - J^{-1} residual(x*)`` and ``x2 = x1 - J^{-1} residual(x1)`` with ``J`` the
    exact Jacobian ``d residual / dx`` at ``x*``, frozen: both corrections are zero-valued;
    ``x1`` carries ``dx* = -J^{-1} d residual`` (derivatives with respect to whatever the
    residual's graph reaches: arguments, parameters), so ``d residual(x1) = 0`` and the second
    correction adds exactly ``-J^{-1} d^2 residual`` (derivatives of ``J`` multiply
    ``residual = 0`` or ``d residual = 0``). Returned as ``x* + (x2 - stop_grad(x2))``.

    Args:
        residual: ``x -> (*batch, q)``, built from differentiable operations.
        x_star: (*batch, q) the converged root (its graph, if any, is ignored).
        solve: ``r -> J^{-1} r`` for (*batch, q) ``r``, differentiable in ``r`` (``J`` fixed).
        r_star: ``residual(x_star)`` with its graph when the caller has it already.

    Returns:
        (*batch, q) tensor with the value of ``x_star``.
    """
    x_star = x_star.detach()
    with torch.enable_grad():

        def correction(r):
            d = solve(r)
            return d.detach() - d

        x1 = x_star + correction(residual(x_star) if r_star is None else r_star)
        x2 = x1 + correction(residual(x1))
    return x_star + (x2 - x2.detach())


# ------------------------------------------------------------------------------ newton
def _graph_leaves(y: torch.Tensor, exclude: torch.Tensor) -> list[torch.Tensor]:
    """The leaf tensors that require grad and that the autograd graph of ``y`` reaches
    (``exclude`` left out): the tensors its AccumulateGrad nodes hold."""
    leaves = (getattr(node, "variable", None) for node in graph_nodes(y))
    return [leaf for leaf in leaves if leaf is not None and leaf is not exclude]


def newton(
    phi: Callable,
    x0,
    *args,
    jacobian: Callable | torch.Tensor | None = None,
    method: str = "full",
    tol: float | None = None,
    xtol: float = 0.0,
    max_iter: int = 50,
    factorization: tuple[torch.Tensor, torch.Tensor] | None = None,
    divergence_ratio: float | None = None,
    params: Sequence[torch.Tensor] | None = None,
    raise_on_failure: bool = False,
    return_history: bool = False,
) -> NewtonResult:
    """Solve ``phi(x, *args) = 0`` for every member of a batch (notes §3).

    Args:
        phi: ``phi(x, *args) -> (*batch, n)`` for ``x`` of shape (*batch, n); members must be
            independent (row ``i`` of the output depends only on row ``i`` of ``x``).
        x0: (*batch, n) initial guess (or broadcastable to phi's output; detached: it gets no
            gradient).
        *args: extra arguments of ``phi``; tensors among them that require grad receive
            implicit-function-theorem gradients (eq. 3.40).
        jacobian: None (exact Jacobian by batched autograd), a callable
            ``jacobian(x, *args) -> (*batch, n, n)`` (exact or approximate), or a fixed matrix
            (n, n) / (*batch, n, n) used as ``M`` in ``dx = -M^{-1} phi`` (eq. 3.44) and
            factorised only once.
        method: "full" (eq. 3.5-3.9), "damped" (Armijo backtracking on ``||phi||^2``, Theorem
            4, eq. 3.33-3.35) or "simplified" (Jacobian evaluated and factorised once at
            ``x0``, or taken from ``factorization``, then reused: Theorem 6).
        tol: convergence when ``||phi(x)||_inf <= tol`` (the notes' test). Default
            ``max(1e-10, 100 eps)`` of the dtype; 0 only together with ``xtol > 0``.
        xtol: also converge when ``||dx||_inf <= xtol * (1 + ||x||_inf)`` (0 disables).
        max_iter: iteration budget per member (an integer >= 0).
        factorization: ``(LU, pivots)`` from ``torch.linalg.lu_factor`` of an approximate
            Jacobian to reuse (simplified Newton only), e.g. ``result.factorization``.
        divergence_ratio: stop a member (status DIVERGED) when its residual grows by more than
            this factor in one iteration; None disables.
        params: the tensors that ``phi`` reads from its closure (e.g. the parameters of a
            module whose method ``phi`` calls) and that receive IFT gradients. None (default):
            all of them, found in the autograd graphs of ``phi`` at ``x0`` and at the solution
            (the leaf tensors that require grad, ``x`` and ``args`` aside; in grad mode, one
            evaluation more once the iterate has moved, since a branch in ``phi`` may read
            other tensors there), so gradients reach whatever ``phi`` reads, as plain autograd
            would; ``()`` differentiates with respect to ``args`` only.
        raise_on_failure: raise :class:`ConvergenceError` naming the failed members instead of
            only flagging them.
        return_history: keep every iterate in ``result.x_history``.

    Returns:
        :class:`NewtonResult`. Members that have stopped keep their iterate; ``converged``
        and ``status`` say why each stopped.

    Raises:
        InputValidationError: bad shapes, non-finite ``x0``, unknown method, forward-mode
            (dual) tensors among ``x0``, ``args`` and ``params``, a ``tol`` or ``xtol`` that
            is not a finite number >= 0 (or both 0), a ``divergence_ratio`` that is not a
            finite number > 0, a ``max_iter`` that is not an integer >= 0.
        ConvergenceError: with ``raise_on_failure=True`` when any member failed.
    """
    if method not in ("full", "damped", "simplified"):
        raise InputValidationError(
            f"newton: unknown method {method!r}; use 'full', 'damped' or 'simplified'."
        )
    if factorization is not None and method != "simplified":
        raise InputValidationError("newton: factorization= is only used by method='simplified'.")
    xtol = check_nonnegative(xtol, "newton: xtol", " (0 disables the step test)")
    raise_on_failure = check_flag(raise_on_failure, "newton: raise_on_failure")
    if tol is not None:
        tol = check_nonnegative(
            tol, "newton: tol", " (the residual tolerance; None for the default)"
        )
        if tol == 0 and xtol == 0:
            raise InputValidationError(
                "newton: tol = 0 with xtol = 0 leaves no convergence test a rounded residual "
                "can pass; pass tol > 0 (None for the default), or xtol > 0 to stop on the "
                "step size."
            )
    max_iter = check_int(max_iter, "newton: max_iter", minimum=0)
    if divergence_ratio is not None:
        divergence_ratio = check_positive(
            divergence_ratio, "newton: divergence_ratio", " (None disables the divergence test)"
        )
    grad_mode = torch.is_grad_enabled()
    _refuse_forward_mode((x0, *args, *(params or ())))
    x = check_state(x0, "newton: x0").detach()
    frozen = _detach(args)
    # the autograd Jacobian at x0 (the first one any method takes) comes from the graph of
    # this first evaluation: one evaluation of phi fewer per solve
    start_graph = jacobian is None and factorization is None
    x_start = x.clone().requires_grad_(start_graph)
    with torch.set_grad_enabled(start_graph or (grad_mode and params is None)):
        fx = phi(x_start, *frozen)
    if not isinstance(fx, torch.Tensor):
        raise InputValidationError(f"newton: phi must return a tensor, got {type(fx).__name__}.")
    discover = params is None and grad_mode
    if params is None:
        params = _graph_leaves(fx, x_start) if grad_mode else ()
    params = tuple(params)
    # (graph at x0, its output) while unused; None: phi at x0 has no graph through x
    same_layout = fx.shape == x.shape and fx.dtype == x.dtype
    start = (x_start, fx) if start_graph and fx.requires_grad and same_layout else None
    fx = fx.detach()
    if fx.shape != x.shape:
        try:
            x = x.expand(fx.shape).clone()
        except RuntimeError as exc:
            raise InputValidationError(
                f"newton: phi returned shape {tuple(fx.shape)} for x0 of shape "
                f"{tuple(x.shape)}; phi must map (*batch, n) to (*batch, n)."
            ) from exc
    x = x.to(fx.dtype)
    tol = _default_tol(x.dtype) if tol is None else tol
    batch = x.shape[:-1]
    dev = x.device
    counts = {"phi": 1, "jac": 0, "lu": 0}

    def residual(z):
        counts["phi"] += 1
        y = phi(z, *frozen)
        if not isinstance(y, torch.Tensor) or y.shape != x.shape:
            got = tuple(y.shape) if isinstance(y, torch.Tensor) else type(y).__name__
            raise InputValidationError(
                f"newton: phi must return a tensor shaped like x {tuple(x.shape)}, got {got} "
                "during the iteration."
            )
        return y

    def iteration_matrix(z):
        nonlocal start
        counts["jac"] += 1
        if start is not None:  # z is x0: the rows from the first evaluation's graph
            (J,) = jacobian_rows(start[1], start[:1], batched=True)
            start = None
            return J.detach()
        if jacobian is None:
            _, J = batch_jacobian(phi, z, *frozen)
            counts["phi"] += 1
            return J
        J = jacobian if isinstance(jacobian, torch.Tensor) else jacobian(z, *frozen)
        return _matrix_of_batch(J, batch, x.shape[-1], "jacobian", x.dtype, dev)

    def factorise(z, status, active):
        """LU factors of the iteration matrix at ``z``; of the ``active`` members, those whose
        matrix has an inf / NaN get status NON_FINITE, those whose matrix is singular
        SINGULAR. Returns the factors and the members still active."""
        counts["lu"] += 1
        M = iteration_matrix(z)
        LU, pivots, ok = _lu(M)
        finite = torch.isfinite(M).flatten(-2).all(-1)
        status.masked_fill_(active & ~finite, NewtonStatus.NON_FINITE)
        status.masked_fill_(active & finite & ~ok, NewtonStatus.SINGULAR)
        return LU, pivots, active & ok

    with torch.no_grad():
        status = torch.full(batch, NewtonStatus.MAX_ITER, dtype=torch.int8, device=dev)
        iterations = torch.zeros(batch, dtype=torch.int64, device=dev)
        norm = fx.abs().amax(-1)  # NaN where fx has a NaN
        nonfinite = ~torch.isfinite(norm)
        status.masked_fill_(nonfinite, NewtonStatus.NON_FINITE)
        done = norm <= tol
        status.masked_fill_(done, NewtonStatus.CONVERGED)
        active = ~(done | nonfinite)
        norms, steps, history = [norm], [], [x.clone()] if return_history else None
        LU = pivots = None
        frozen_matrix = method == "simplified" or isinstance(jacobian, torch.Tensor)
        if frozen_matrix:
            if factorization is not None:
                LU, pivots = (f.detach() for f in factorization)
                LU = _matrix_of_batch(LU, batch, x.shape[-1], "factorization", x.dtype, dev)
                pivots = pivots.expand(*batch, pivots.shape[-1])
            else:
                LU, pivots, active = factorise(x, status, active)
        for _ in range(max_iter):
            if not bool(active.any()):
                break
            if not frozen_matrix:
                LU, pivots, active = factorise(x, status, active)
            dx = _lu_solve(LU, pivots, fx)  # the Newton step is -dx
            x_new = x - dx
            f_new = residual(x_new)
            t = active.to(x.dtype)  # the step length of every active member, 1 or halved
            if method == "damped":
                merit = (fx * fx).sum(-1)
                for attempt in range(_MAX_BACKTRACKS + 1):
                    f_ok = torch.isfinite(f_new).all(-1)
                    accept = f_ok & ((f_new * f_new).sum(-1) <= (1 - 2 * _ARMIJO * t) * merit)
                    retry = active & ~accept
                    if not bool(retry.any()):
                        break
                    if attempt == _MAX_BACKTRACKS:  # NON_FINITE where phi is inf / NaN there
                        status.masked_fill_(retry & f_ok, NewtonStatus.LINE_SEARCH_FAILED)
                        status.masked_fill_(retry & ~f_ok, NewtonStatus.NON_FINITE)
                        active &= ~retry
                        break
                    t = torch.where(retry, t / 2, t)
                    x_try = x - t[..., None] * dx
                    f_try = residual(x_try)
                    x_new = torch.where(retry[..., None], x_try, x_new)
                    f_new = torch.where(retry[..., None], f_try, f_new)
                t = t * active  # zero for members whose line search failed
            upd = active[..., None]
            x = torch.where(upd, x_new, x)
            fx = torch.where(upd, f_new, fx)
            iterations += active
            steps.append(t)
            f_norm = fx.abs().amax(-1)  # NaN where fx has a NaN
            new_norm = torch.where(active, f_norm, norm)
            bad = active & ~torch.isfinite(f_norm + x.abs().amax(-1))
            status.masked_fill_(bad, NewtonStatus.NON_FINITE)
            active &= ~bad
            done = new_norm <= tol
            if xtol > 0:
                done |= (t[..., None] * dx).abs().amax(-1) <= xtol * (1 + x.abs().amax(-1))
            done &= active
            status.masked_fill_(done, NewtonStatus.CONVERGED)
            active &= ~done
            if divergence_ratio is not None:
                grew = active & (new_norm > divergence_ratio * norm)
                status.masked_fill_(grew, NewtonStatus.DIVERGED)
                active &= ~grew
            norm = new_norm
            norms.append(norm)
            if return_history:
                history.append(x.clone())

    converged = status == NewtonStatus.CONVERGED
    messages = _describe(status, norm)
    if raise_on_failure and not bool(converged.all()):
        raise ConvergenceError(
            f"newton ({method}) failed for {int((~converged).sum())} of {converged.numel()} "
            f"sample(s) after at most {max_iter} iterations (tol {tol:.1e}): "
            + "; ".join(messages)
            + ". Try a better initial guess, method='damped', a larger max_iter, or check "
            "that the Jacobian is non-singular at the solution."
        )
    if discover and bool((iterations > 0).any()):  # the IFT holds at x*: what phi reads there
        with torch.enable_grad():
            at_solution = _graph_leaves(phi(x, *frozen), x)
        counts["phi"] += 1
        params += tuple(p for p in at_solution if not any(p is q for q in params))
    wanted = [a for a in (*args, *params) if isinstance(a, torch.Tensor) and a.requires_grad]
    if wanted and torch.is_grad_enabled():
        x = _ImplicitSolution.apply(phi, x, len(args), *args, *params)
    return NewtonResult(
        x=x,
        converged=converged,
        status=status,
        iterations=iterations,
        residual_norms=torch.stack(norms),
        step_sizes=torch.stack(steps) if steps else x.new_zeros((0, *batch)),
        n_phi_evals=counts["phi"],
        n_jac_evals=counts["jac"],
        n_factorizations=counts["lu"],
        factorization=None if LU is None else (LU, pivots),
        x_history=torch.stack(history) if return_history else None,
        messages=messages,
    )


# ---------------------------------------------------------------------------- minimize
MINIMIZE_METHODS = ("newton", "gauss_newton", "levenberg_marquardt")


def _matrix_of_batch(M, batch, n: int, what: str, dtype, device) -> torch.Tensor:
    """``M`` (*b, n, n) detached and expanded to (*batch, n, n), or InputValidationError
    naming ``what`` when it is not a tensor of that shape."""
    if not isinstance(M, torch.Tensor) or M.dim() < 2 or M.shape[-2:] != (n, n):
        got = tuple(M.shape) if isinstance(M, torch.Tensor) else type(M).__name__
        raise InputValidationError(f"newton: {what} must be (*batch, {n}, {n}), got {got}.")
    try:
        return M.detach().to(dtype=dtype, device=device).expand(*batch, n, n)
    except RuntimeError:
        raise InputValidationError(
            f"newton: {what} of batch shape {tuple(M.shape[:-2])} does not broadcast to the "
            f"batch {tuple(batch)} of x0."
        ) from None


def _loss_derivatives(fun, theta, args, method, jacobian=None, loss=None, members=None):
    """(loss, grad, H, J, r) at ``theta``: exact Newton (eq. 3.50-3.51), or for residuals
    the quadratic model ``H = J' C J``, ``grad = J' psi(r)`` with the curvature weights
    ``C = loss.curvature(r)`` (``C = 1``, ``psi(r) = r``: Gauss-Newton, eq. 3.58-3.60).
    ``members`` (an index tensor, ``compact=True`` of :func:`minimize`) is passed on to
    ``fun``, ``jacobian`` and the loss methods; None passes nothing."""
    batch = theta.shape[:-1]
    kw = {} if members is None else {"members": members}
    if kw:
        fun = functools.partial(fun, **kw)
    if method != "newton":
        if jacobian is None:
            r, J = batch_jacobian(fun, theta, *args)
        else:
            r, J = jacobian(theta, *args, **kw)
            r, J = r.detach(), J if isinstance(J, BlockJacobian) else J.detach()
            if J.shape != (*r.shape, theta.shape[-1]):
                raise InputValidationError(
                    f"minimize: jacobian must return r (*batch, m) and J (*batch, m, n), got "
                    f"{tuple(r.shape)} and {tuple(J.shape)}."
                )
        if r.dim() < 1 or r.shape[:-1] != batch:
            raise InputValidationError(
                f"minimize: the residual must have shape (*batch, m) with batch {tuple(batch)}, "
                f"got {tuple(r.shape)}."
            )
        if loss is None:  # Gauss-Newton: psi(r) = r, C = 1
            value, psi, weights = 0.5 * (r * r).sum(-1), r, None
        else:
            value, psi = loss.rho(r, **kw).sum(-1), loss.psi(r, **kw)
            weights = loss.curvature(r, **kw)
        if isinstance(J, BlockJacobian):
            grad, H = J.rmatvec(psi), J.normal(weights)
            if method != "levenberg_marquardt" and isinstance(H, BorderedBlockTridiagonal):
                H = H.dense()  # the shifted Cholesky of Gauss-Newton works on the matrix
        else:
            Jt = J.transpose(-1, -2)
            grad = (Jt @ psi.unsqueeze(-1)).squeeze(-1)
            H = Jt @ (J if weights is None else J * weights.unsqueeze(-1))
        return value, grad, H, J, r
    store = {}

    def gradient(z):
        value = fun(z, *args)
        if not isinstance(value, torch.Tensor) or value.shape != batch:
            got = tuple(value.shape) if isinstance(value, torch.Tensor) else type(value).__name__
            raise InputValidationError(
                f"minimize: the objective must return one loss per problem, shape "
                f"{tuple(batch)}, got {got}."
            )
        store["loss"] = value.detach()
        (g,) = torch.autograd.grad(value.sum(), z, create_graph=True)
        return g

    grad, H = batch_jacobian(gradient, theta)
    return store["loss"], grad, 0.5 * (H + H.transpose(-1, -2)), None, None


def _loss_only(fun, theta, args, method, loss=None, admissible=None, members=None):
    """The objective at ``theta`` (``inf`` where it is not finite or ``theta`` inadmissible);
    ``members`` as for :func:`_loss_derivatives`, also passed to ``admissible``."""
    kw = {} if members is None else {"members": members}
    value = fun(theta, *args, **kw)
    if method != "newton":  # the loss of the residual
        value = 0.5 * (value * value).sum(-1) if loss is None else loss.rho(value, **kw).sum(-1)
    value = torch.where(torch.isfinite(value), value, torch.full_like(value, math.inf))
    if admissible is not None:
        value = torch.where(admissible(theta, **kw), value, torch.full_like(value, math.inf))
    return value


def _shifted_cholesky(H, alpha):
    """Cholesky factor of ``H + shift I`` with the smallest per-member shift >= alpha found by
    doubling that makes the matrix positive definite (Theorem 7 needs M > 0)."""
    n = H.shape[-1]
    eye = torch.eye(n, dtype=H.dtype, device=H.device)
    scale = H.diagonal(dim1=-2, dim2=-1).abs().amax(-1).clamp(min=1.0)
    shift = torch.full(H.shape[:-2], float(alpha), dtype=H.dtype, device=H.device)
    L, info = torch.linalg.cholesky_ex(H + shift[..., None, None] * eye)
    for _ in range(60):
        bad = (info != 0) | ~torch.isfinite(L).flatten(-2).all(-1)
        if not bool(bad.any()):
            break
        shift = torch.where(bad, torch.clamp(2 * shift, min=1e-10 * scale), shift)
        L_new, info_new = torch.linalg.cholesky_ex(H + shift[..., None, None] * eye)
        L = torch.where(bad[..., None, None], L_new, L)
        info = torch.where(bad, info_new, info)
    ok = (info == 0) & torch.isfinite(L).flatten(-2).all(-1)
    return torch.where(ok[..., None, None], L, eye.expand_as(L)), ok


def _damped_solve(H, grad, shift):
    """``((H + shift I)^{-1} grad, ok)`` for a dense ``H`` (Cholesky) or a
    :class:`~integrators.block_tridiagonal.BorderedBlockTridiagonal` one (its block
    Cholesky); ``ok`` False where the shifted matrix is numerically not positive definite."""
    if isinstance(H, BorderedBlockTridiagonal):
        return H.solve(grad, shift)
    eye = torch.eye(H.shape[-1], dtype=H.dtype, device=H.device)
    L, info = torch.linalg.cholesky_ex(H + shift[..., None, None] * eye)
    ok = info == 0
    L = torch.where(ok[..., None, None], L, eye.expand_as(L))
    return torch.cholesky_solve(grad.unsqueeze(-1), L).squeeze(-1), ok


def _damped_step(H, grad, lam, scale):
    """The Levenberg-Marquardt step ``-(H + lam scale I)^{-1} grad`` (eq. 3.61 with
    ``alpha = lam scale``); ``lam`` grows tenfold per member while the matrix is numerically
    indefinite. Returns ``(step, lam, ok)``."""
    x, ok = _damped_solve(H, grad, lam * scale)
    for _ in range(30):
        if bool(ok.all()):
            break
        lam = torch.where(ok, lam, lam * 10)
        x_new, ok_new = _damped_solve(H, grad, lam * scale)
        x = torch.where(ok[..., None], x, x_new)
        ok = ok | ok_new
    return -torch.where(ok[..., None], x, torch.zeros_like(x)), lam, ok


def _diagonal(H) -> torch.Tensor:
    """The (*batch, n) diagonal of a dense or structured matrix."""
    if isinstance(H, BorderedBlockTridiagonal):
        return H.diagonal()
    return H.diagonal(dim1=-2, dim2=-1)


def _select(keep: torch.Tensor, a, b):
    """``a`` for the batch members where ``keep`` (*batch,) holds, ``b`` for the others: (*batch,
    ...) tensors, :class:`BlockJacobian` or :class:`BorderedBlockTridiagonal` values, or None."""
    if a is None:
        return None
    if isinstance(a, torch.Tensor):
        return torch.where(keep.reshape(keep.shape + (1,) * (a.dim() - keep.dim())), a, b)
    return a.where(keep, b)


def _members_of(mask: torch.Tensor) -> torch.Tensor:
    """(k,) int64 indices, into the flattened batch, of the members where ``mask`` is True."""
    return torch.nonzero(mask.reshape(-1)).squeeze(-1)


def _replace_rows(full: torch.Tensor, members: torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
    """``full`` (*batch, *tail) with the members ``members`` (k,) of its flattened batch
    replaced by ``rows`` (k, *tail); a new tensor."""
    tail = full.shape[full.dim() - rows.dim() + 1 :]
    return full.reshape(-1, *tail).index_copy(0, members, rows).reshape(full.shape)


def minimize(
    fun: Callable,
    theta0,
    *args,
    method: str = "newton",
    regularization: float = 0.0,
    line_search: bool = True,
    tol: float | None = None,
    xtol: float = 1e-10,
    ftol: float = 1e-10,
    max_iter: int = 100,
    raise_on_failure: bool = False,
    jacobian: Callable | None = None,
    loss=None,
    admissible: Callable | None = None,
    damping: float = 1e-6,
    max_backtracks: int | None = None,
    callback: Callable | None = None,
    catch_interrupt: bool = False,
    compact: bool = False,
) -> MinimizeResult:
    """Batched unconstrained minimisation by Newton-type steps (notes §3.5).

    Each iteration solves ``(H + alpha I) dtheta = -grad`` and takes ``theta + t dtheta`` with
    ``t = 1, 1/2, ...`` from Armijo backtracking on the loss (Theorem 7),
    ``f(theta + t dtheta) <= f(theta) + 1e-4 t grad' dtheta`` (only ``t = 1`` where the
    predicted decrease ``-grad' dtheta`` is below the rounding error of the loss: shorter
    steps could not be told apart from it). The three methods share this iteration; they
    differ in the model ``(H, grad)`` and in how ``alpha`` is chosen.

    Methods:
        ``"newton"``: ``fun(theta, *args) -> (*batch,)`` is the objective; ``H`` is its exact
        Hessian from autograd (eq. 3.50-3.51); ``alpha = regularization``, doubled per
        problem while ``H + alpha I`` is not positive definite, so every step is a descent
        direction.

        ``"gauss_newton"``: ``fun(theta, *args) -> (*batch, m)`` is a residual and the loss
        ``0.5 ||r||^2``; ``H = J'J``, ``grad = J'r`` (eq. 3.57-3.60); ``alpha`` as for
        ``"newton"`` (eq. 3.61).

        ``"levenberg_marquardt"``: ``fun`` is a residual and the loss ``sum_k rho(r_k)``
        (``0.5 ||r||^2`` when ``loss`` is None); ``H = J' C J``, ``grad = J' psi(r)`` with the
        curvature weights ``C = loss.curvature(r)``, and ``alpha = lam trace(H) / n`` with a
        per-problem ``lam`` (starting at ``damping``) that shrinks tenfold after a full step,
        doubles after a shortened one and grows tenfold when the line search finds no
        decrease; a problem whose ``lam`` exceeds ``1e10`` that way has failed. Candidates
        that ``admissible`` rejects count as an infinite loss.

    Loss protocol (``loss=``, Levenberg-Marquardt only): any object with elementwise
    methods ``rho(r)`` (per-residual loss, ``~ r^2 / 2`` near 0), ``psi(r) = rho'(r)`` and
    ``curvature(r)``, the weights ``c_k`` of the quadratic model
    ``sum_k c_k (r_k + J_k d)^2 / 2`` used for the step (``rho''`` for a Newton step,
    ``psi(r)/r`` for iteratively reweighted least squares), on (*batch, m) tensors.

    Args:
        fun: objective or residual, see Methods; problems in the batch must be independent.
        theta0: (*batch, n) initial parameters (detached).
        *args: extra arguments of ``fun`` (not differentiated).
        method: "newton", "gauss_newton" or "levenberg_marquardt".
        regularization: ``alpha >= 0`` of eq. 3.61 for "newton" and "gauss_newton".
        line_search: Armijo backtracking (else full steps; "newton", "gauss_newton").
        tol: gradient tolerance. "newton", "gauss_newton": converged when
            ``||grad||_inf <= tol`` (eq. 3.49), default ``max(1e-8, 1000 eps)``.
            "levenberg_marquardt": when ``||grad||_inf <= tol (1 + f) sqrt(trace(H) / n)``
            (scale-free), default ``1e-12``.
        xtol: step tolerance. "newton", "gauss_newton": converged when an accepted step
            satisfies ``||t dtheta||_inf <= xtol (1 + ||theta||_inf)``, or when the line search
            fails with a predicted decrease at the rounding level of the loss.
            "levenberg_marquardt": when ``||t dtheta||_2 <= xtol (xtol + ||theta||_2)``
            (``xtol`` at least ``10 eps``).
        ftol: "levenberg_marquardt": also converged when an accepted step decreases the loss
            by at most ``ftol f`` (``ftol`` at least ``10 eps``), or when no step decreases it
            while the predicted decrease ``-g'd`` is below ``10 sqrt(m) eps f``, the rounding
            error of a sum of ``m`` residual terms.
        max_iter: iteration budget.
        raise_on_failure: raise :class:`ConvergenceError` naming the failed problems.
        jacobian: residual methods: ``jacobian(theta, *args) -> (r, J)`` with ``J`` of shape
            (*batch, m, n), replacing the reverse-mode autograd Jacobian; e.g. forward
            sensitivities of a simulation (:func:`integrators.sensitivities`), which cost
            ``n`` directions instead of ``m`` reverse passes when ``m >> n``. ``J`` may be a
            :class:`~integrators.block_jacobian.BlockJacobian` (sparse row blocks, e.g.
            multiple shooting): ``J'CJ`` and ``J'psi`` are then formed block by block, and
            where it has a chain, Levenberg-Marquardt solves with the block tridiagonal
            ``J'CJ`` in time linear in the chain length
            (:class:`~integrators.block_tridiagonal.BorderedBlockTridiagonal`).
        loss: "levenberg_marquardt": the per-residual loss (protocol above); None is the
            squared loss ``r^2 / 2``.
        admissible: "levenberg_marquardt": ``theta (*batch, n) -> (*batch,)`` bool; steps to
            inadmissible parameters (e.g. an unstable model) are rejected by the line search.
            ``theta0`` must be admissible.
        damping: "levenberg_marquardt": the initial relative damping ``lam``.
        max_backtracks: step halvings tried per iteration; default 30 ("newton",
            "gauss_newton") or 11 ("levenberg_marquardt").
        callback: ``callback(iteration, theta, loss)`` after every iteration, with the
            largest iteration count of the batch (int), the current iterate (*batch, n) and
            its loss (*batch,) (e.g. for a progress bar); it may raise ``KeyboardInterrupt``.
        catch_interrupt: on ``KeyboardInterrupt`` (Ctrl-C, or raised by ``fun`` or
            ``callback``) return the last accepted iterate, with its loss, gradient,
            Jacobian and residual, instead of propagating the exception; the problems still
            iterating get status ``INTERRUPTED``.
        compact: evaluate ``fun``, ``jacobian``, ``admissible`` and the ``loss`` methods only
            for the members whose values are used: after the first evaluation (every
            member), the trial points of the members still searching a step and the
            derivatives of the members that took one, so that an iteration costs the work of
            the problems still iterating, not of the whole batch. Each of these callables
            then receives the keyword argument ``members``, a (k,) int64 tensor of indices
            into the flattened batch (row-major over ``*batch``), with ``theta`` of shape
            (k, n) (the rows ``members`` of ``theta.reshape(-1, n)``) and ``*args`` unchanged;
            ``fun`` returns (k, m) residuals ((k,) objective values for "newton"),
            ``jacobian`` (k, m) and (k, m, n) (a dense ``J``), ``admissible`` (k,) and the
            ``loss`` methods their values on (k, m) residuals; per-member data (e.g. a data
            set per problem, a per-problem loss scale) are indexed with ``members``. The
            result is that of ``compact=False``; ``n_fun_evals`` counts the calls of ``fun``
            or ``jacobian``, however many members each evaluates.

    Returns:
        :class:`MinimizeResult` with the estimate, the loss history, the gradient, the
        Hessian used (``J'CJ`` for the residual methods, without damping), for the residual
        methods ``J`` and the residual at the solution (e.g. for the covariance
        ``sigma^2 (J'J)^{-1}``), and for Levenberg-Marquardt the final ``lam`` in ``damping``.
        A line-search failure has status ``LINE_SEARCH_FAILED``.

    Raises:
        InputValidationError: unknown method, options the method does not use, a
            ``regularization``, ``tol``, ``xtol`` or ``ftol`` that is not a finite number
            >= 0, a ``damping`` that is not a finite number > 0, a ``max_iter`` or
            ``max_backtracks`` that is not an integer >= 0; with ``compact=True``, a
            ``jacobian`` that returns a :class:`~integrators.block_jacobian.BlockJacobian`.
        ConvergenceError: with ``raise_on_failure=True`` when any problem failed.
    """
    if method not in MINIMIZE_METHODS:
        raise InputValidationError(
            f"minimize: unknown method {method!r}; use one of {', '.join(MINIMIZE_METHODS)}."
        )
    adaptive = method == "levenberg_marquardt"
    regularization = check_nonnegative(regularization, "minimize: regularization")
    raise_on_failure = check_flag(raise_on_failure, "minimize: raise_on_failure")
    if tol is not None:
        tol = check_nonnegative(
            tol, "minimize: tol", " (the gradient tolerance; None for the default)"
        )
    xtol = check_nonnegative(xtol, "minimize: xtol")
    ftol = check_nonnegative(ftol, "minimize: ftol")
    max_iter = check_int(max_iter, "minimize: max_iter", minimum=0)
    if max_backtracks is not None:
        max_backtracks = check_int(max_backtracks, "minimize: max_backtracks", minimum=0)
    if jacobian is not None and method == "newton":
        raise InputValidationError(
            "minimize: jacobian= is only used by the residual methods 'gauss_newton' and "
            "'levenberg_marquardt'."
        )
    if not adaptive and (loss is not None or admissible is not None):
        raise InputValidationError(
            "minimize: loss= and admissible= are only used by method='levenberg_marquardt'."
        )
    if adaptive and not line_search:
        raise InputValidationError(
            "minimize: method='levenberg_marquardt' always uses its line search; pass "
            "line_search=True (or use method='gauss_newton' for full steps)."
        )
    if adaptive:
        damping = check_positive(damping, "minimize: damping")
    theta = check_state(theta0, "minimize: theta0").detach()
    frozen = _detach(args)
    batch, dev, n = theta.shape[:-1], theta.device, theta.shape[-1]
    eps = torch.finfo(theta.dtype).eps
    if adaptive:
        tol = 1e-12 if tol is None else tol
        xtol, ftol = max(xtol, 10 * eps), max(ftol, 10 * eps)  # reachable in float32 too
        trials = 1 + (11 if max_backtracks is None else max_backtracks)
    else:
        tol = max(1e-8, 1e3 * eps) if tol is None else tol
        trials = 1 + (_MAX_BACKTRACKS if max_backtracks is None else max_backtracks)
        trials = trials if line_search else 1
    compact = check_flag(compact, "minimize: compact")
    n_evals = 0

    def derivatives(point, move, current):
        """(loss, grad, H, J, r) of :func:`_loss_derivatives` at ``point`` (*batch, n); with
        ``compact`` evaluated only for the members in ``move``, the others keeping their
        values in ``current`` (None: every member is evaluated)."""
        nonlocal n_evals
        if not compact:
            n_evals += 1
            return _loss_derivatives(fun, point, frozen, method, jacobian, loss)
        members = _members_of(move)
        if current is not None and members.numel() == 0:
            return current
        n_evals += 1
        rows = _loss_derivatives(
            fun, point.reshape(-1, n)[members], frozen, method, jacobian, loss, members
        )
        if isinstance(rows[3], BlockJacobian):
            raise InputValidationError(
                "minimize: compact=True needs a dense Jacobian (*batch, m, n), not a BlockJacobian."
            )
        if current is None:
            return tuple(None if v is None else v.reshape(batch + v.shape[1:]) for v in rows)
        return tuple(
            None if v is None else _replace_rows(c, members, v)
            for c, v in zip(current, rows, strict=True)
        )

    def objective(point, pending):
        """:func:`_loss_only` at ``point`` (*batch, n) for every member, or with ``compact``
        for the members in ``pending`` (the others: ``inf``)."""
        nonlocal n_evals
        n_evals += 1
        if not compact:
            return _loss_only(fun, point, frozen, method, loss, admissible)
        members = _members_of(pending)
        rows = _loss_only(
            fun, point.reshape(-1, n)[members], frozen, method, loss, admissible, members
        )
        out = torch.full((batch.numel(),), math.inf, dtype=rows.dtype, device=dev)
        return out.index_copy(0, members, rows).reshape(batch)

    everyone = torch.ones(batch, dtype=torch.bool, device=dev)
    loss_value, grad, H, J, r = derivatives(theta, everyone, None)
    # the rounding error of the loss: of a sum of m residual terms (Levenberg-Marquardt), or
    # of a loss no smaller than eps
    rounding_terms, loss_floor = (math.sqrt(r.shape[-1]), 0.0) if adaptive else (1.0, eps)
    with torch.no_grad():
        status = torch.full(batch, NewtonStatus.MAX_ITER, dtype=torch.int8, device=dev)
        iterations = torch.zeros(batch, dtype=torch.int64, device=dev)
        active = everyone.clone()
        lam = torch.full(batch, float(damping), dtype=theta.dtype, device=dev)
        history = [loss_value]

        def snapshot():
            # the state of the last accepted iterate, stored in one assignment so that an
            # interrupt never sees half of an update
            counters = (iterations.clone(), status.clone(), active.clone(), len(history))
            return (theta, loss_value, grad, H, J, r, *counters)

        committed = snapshot()
        try:
            for _ in range(max_iter + 1):
                nonfinite = active & ~(torch.isfinite(loss_value) & torch.isfinite(grad).all(-1))
                status.masked_fill_(nonfinite, NewtonStatus.NON_FINITE)
                active &= ~nonfinite
                gnorm = grad.abs().amax(-1)
                if adaptive:  # the curvature scale of eq. 3.61's alpha and of the gradient test
                    scale = (_diagonal(H).sum(-1) / n).clamp_min(torch.finfo(theta.dtype).tiny)
                    done = active & (gnorm <= tol * (1 + loss_value) * scale.sqrt())
                else:
                    done = active & (gnorm <= tol)
                status.masked_fill_(done, NewtonStatus.CONVERGED)
                active &= ~done
                if not bool(active.any()) or int(iterations.max()) >= max_iter:
                    break
                if adaptive:
                    step, lam, ok = _damped_step(H, grad, lam, scale)
                else:
                    Lc, ok = _shifted_cholesky(torch.nan_to_num(H), regularization)
                    step = -torch.cholesky_solve(grad.unsqueeze(-1), Lc).squeeze(-1)
                status.masked_fill_(active & ~ok, NewtonStatus.SINGULAR)
                active &= ok
                slope = (grad * step).sum(-1)  # < 0: descent direction (Theorem 7)
                # a predicted decrease below the rounding error of the loss (Levenberg-Marquardt:
                # of a sum of m residual terms, about sqrt(m) eps |loss|): the full step is
                # tried, shorter ones would only compare rounding errors
                rounding = 10 * eps * rounding_terms * loss_value.abs().clamp(min=loss_floor)
                flat_step = -slope <= rounding
                t = torch.ones(batch, dtype=theta.dtype, device=dev)
                accepted = torch.zeros(batch, dtype=torch.bool, device=dev)
                trial_loss = loss_value.clone()
                pending = active.clone()
                for attempt in range(trials):
                    if not bool(pending.any()):
                        break
                    value = objective(theta + t[..., None] * step, pending)
                    ok = pending & (value <= loss_value + _ARMIJO * t * slope)
                    ok = ok if line_search else pending
                    accepted |= ok
                    trial_loss = torch.where(ok, value, trial_loss)
                    pending &= ~ok
                    if attempt == 0:
                        pending &= ~flat_step
                    t = torch.where(pending, t / 2, t)
                # no decrease found: converged if the predicted decrease is at the rounding level
                # of the loss, else a genuine failure (Levenberg-Marquardt: lam grows instead)
                no_decrease = active & ~accepted
                flat = no_decrease & flat_step
                if adaptive and bool(flat.any()):
                    # the minimum is reached where the undamped step's predicted decrease is at
                    # the rounding level too (heavy damping, e.g. grown by inadmissible trials,
                    # hides a slope)
                    undamped, _, solved = _damped_step(H, grad, torch.zeros_like(lam), scale)
                    flat &= ~(solved & (-(grad * undamped).sum(-1) > rounding))
                status.masked_fill_(flat, NewtonStatus.CONVERGED)
                active &= ~flat
                no_decrease &= ~flat
                if adaptive:
                    full = accepted & (t == 1)
                    lam = torch.where(full, (lam / 10).clamp_min(1e-12), lam)
                    lam = torch.where(accepted & ~full, lam * 2, lam)
                    lam = torch.where(no_decrease, lam * 10, lam)
                else:
                    status.masked_fill_(no_decrease, NewtonStatus.LINE_SEARCH_FAILED)
                    active &= ~no_decrease
                move = active & accepted
                dtheta = torch.where(move[..., None], t[..., None] * step, 0.0)
                if adaptive:
                    small = dtheta.norm(dim=-1) <= xtol * (xtol + theta.norm(dim=-1))
                    small |= (loss_value - trial_loss) <= ftol * loss_value
                    small &= move
                    # a step small only because heavy damping shortened it (lam >= 1) is no
                    # sign of a minimum: the undamped step must be small too
                    damped = small & (lam >= 1)
                    if bool(damped.any()):
                        undamped, _, solved = _damped_step(H, grad, torch.zeros_like(lam), scale)
                        still_x = undamped.norm(dim=-1) <= xtol * (xtol + theta.norm(dim=-1))
                        still_f = -0.5 * (grad * undamped).sum(-1) <= ftol * loss_value
                        small &= ~(damped & solved & ~still_x & ~still_f)
                else:
                    small = dtheta.abs().amax(-1) <= xtol * (1 + theta.abs().amax(-1))
                new = derivatives(theta + dtheta, move, (loss_value, grad, H, J, r))
                theta = theta + dtheta
                iterations = iterations + active.to(torch.int64)
                keep = ~move
                loss_value, grad, H, J, r = (
                    _select(keep, a, b)
                    for a, b in zip((loss_value, grad, H, J, r), new, strict=True)
                )
                history.append(loss_value)
                stalled = active & small & torch.isfinite(loss_value)
                status.masked_fill_(stalled, NewtonStatus.CONVERGED)
                active &= ~stalled
                if adaptive:
                    failed = no_decrease & (lam > 1e10)
                    status.masked_fill_(failed, NewtonStatus.LINE_SEARCH_FAILED)
                    active &= ~failed
                committed = snapshot()
                if callback is not None:
                    callback(int(iterations.max()), theta, loss_value)
        except KeyboardInterrupt:
            if not catch_interrupt:
                raise
            theta, loss_value, grad, H, J, r, iterations, status, active, n_history = committed
            del history[n_history:]
            status.masked_fill_(active, NewtonStatus.INTERRUPTED)
    converged = status == NewtonStatus.CONVERGED
    messages = _describe(status, grad.abs().amax(-1), label="gradient norm")
    if raise_on_failure and not bool(converged.all()):
        raise ConvergenceError(
            f"minimize ({method}) failed for {int((~converged).sum())} of {converged.numel()} "
            f"problem(s): " + "; ".join(messages) + ". Try a better initial guess, a larger "
            "max_iter or regularization, or check that the problem is identifiable."
        )
    return MinimizeResult(
        theta=theta,
        converged=converged,
        status=status,
        iterations=iterations,
        loss=loss_value,
        loss_history=torch.stack(history),
        grad=grad,
        hessian=H,
        J=J,
        residual=r,
        n_fun_evals=n_evals,
        messages=messages,
        damping=lam if adaptive else None,
    )
