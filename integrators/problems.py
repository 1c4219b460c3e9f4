"""Problem classes for implicit ODEs and index-1 DAEs, integrated by :func:`daeint`.

Each class only stores the user's functions; ``daeint`` turns them into stage residuals
(notes eq. 7.52, 7.56, 7.63). The functions take the time first and the input ``u`` last;
``u`` is omitted when ``daeint`` is called without an input (``u=None``), exactly like ``f`` in
``odeint`` (see :mod:`integrators.inputs`). Times are 0-dim tensors (fixed step) or (*batch, 1)
(adaptive).

Parameters to be identified: pass the functions as ``torch.nn.Module`` instances (or closures
over tensors that require grad). Gradients reach every tensor the functions use through the
implicit-function-theorem step (see ``integrators._irk_core``); no parameter list is needed.
"""

from __future__ import annotations

from collections.abc import Callable

import torch

from .errors import InputValidationError


def _check_callable(fn, label):
    if not callable(fn):
        raise InputValidationError(f"{label} must be callable, got {type(fn).__name__}.")
    return fn


def _sample_index(mask: torch.Tensor) -> tuple:
    """The batch index of the first True entry of a (*batch,) mask (``()`` unbatched)."""
    return tuple(torch.nonzero(mask)[0].tolist()) if mask.dim() else ()


class _Problem:
    kind = ""

    def modules(self) -> list[torch.nn.Module]:
        """The functions that are ``nn.Module`` (registered by :class:`DAELayer`)."""
        return [fn for fn in self.functions() if isinstance(fn, torch.nn.Module)]

    def functions(self) -> tuple:
        raise NotImplementedError

    def check_start(self, t0, x0, z0, u0) -> None:
        """Evaluate every function once at the start and check what it returns.

        Each output must be a floating-point tensor whose last dimension is the expected
        number of residuals and whose batch shape broadcasts to that of ``x0``, with finite
        entries; the residuals that ``daeint`` differentiates for its index check and Newton
        matrix (``g``, ``F``) must carry an autograd graph back to the states. Called by
        :func:`daeint` before the index check and the consistent initialisation, so that a
        wrong width or a non-finite value is reported against the function that produced it.

        Args:
            t0: start time (0-dim, or (*batch, 1)).
            x0: (*batch, n) initial differential states.
            z0: (*batch, m) guess of the initial algebraic states (m = 0 for ImplicitODE).
            u0: the input at ``t0`` (*batch, nu), or None when the problem takes no input.

        Raises:
            InputValidationError: naming the function, when calling it fails with a
                ``TypeError`` (e.g. it takes no ``u`` but ``daeint`` received one), or the
                shape, dtype or graph it returned against the one expected (or the first sample
                with a non-finite entry).
        """
        raise NotImplementedError

    @staticmethod
    def _check_output(out, label, width, why, batch, point) -> None:
        """``out`` must be a (*batch, width) tensor (batch broadcastable) of finite values."""
        if not isinstance(out, torch.Tensor):
            raise InputValidationError(f"{label} must return a tensor, got {type(out).__name__}.")
        if not out.is_floating_point():
            raise InputValidationError(
                f"{label} returned a {out.dtype} tensor; it must return floating-point values "
                "in the states' dtype (a comparison or an integer cast is not differentiable: "
                "write the residual with torch operations on float arguments)."
            )
        if out.dim() == 0 or out.shape[-1] != width:
            got = "a scalar" if out.dim() == 0 else f"width {out.shape[-1]}"
            raise InputValidationError(
                f"{label} returned {got} (shape {tuple(out.shape)}) but {why}."
            )
        try:
            fits = torch.broadcast_shapes(out.shape[:-1], batch) == batch
        except RuntimeError:
            fits = False
        if not fits:
            raise InputValidationError(
                f"{label} returned batch shape {tuple(out.shape[:-1])} for states of batch "
                f"shape {tuple(batch)}; it must return (*batch, {width}). If the model's "
                "parameters carry a batch, give x0 and z0 that batch shape."
            )
        bad = ~torch.isfinite(out.detach()).all(-1)
        if bool(bad.any()):
            raise InputValidationError(
                f"{label} returned inf/nan at {point} for sample {_sample_index(bad)}; the "
                "initial states must lie where the model is finite (check x0, the z0 guess "
                "and the input at t0)."
            )

    @staticmethod
    def _args(u0, *names) -> str:
        return ", ".join(("t", *names) + (("u",) if u0 is not None else ()))

    @staticmethod
    def _call(fn, label, t0, u0, *args, graph=False):
        """``fn(t0, *args[, u0])`` without autograd, or with ``graph`` on fresh leaves of the
        state arguments ``args``, whose output must then depend on them through autograd.

        Raises:
            InputValidationError: the call fails with a ``TypeError`` (wrong number of
                arguments), or ``graph`` and the output has no autograd graph.
        """
        if graph:
            args = tuple(a.detach().requires_grad_() for a in args)
        try:
            with torch.set_grad_enabled(graph):
                out = fn(t0, *args) if u0 is None else fn(t0, *args, u0)
        except TypeError as exc:
            raise InputValidationError(
                f"calling the model as {label} failed: {exc}. The functions are called with "
                "an input u only when daeint receives u."
            ) from exc
        if graph and isinstance(out, torch.Tensor) and out.is_floating_point():
            if not out.requires_grad:
                raise InputValidationError(
                    f"{label} returned a tensor without autograd graph: daeint differentiates "
                    "it with torch.autograd (index check, Newton matrix), so compute it with "
                    "torch operations on its arguments, not through numpy, .detach(), .item() "
                    "or torch.tensor(...)."
                )
        return out


class _Residual(_Problem):
    """A problem given by one implicit residual function ``F``."""

    kind = "implicit"

    def __init__(self, F: Callable):
        self.F = _check_callable(F, "F")

    def functions(self) -> tuple:
        return (self.F,)


class ImplicitODE(_Residual):
    """Implicit ODE ``F(t, x', x[, u]) = 0`` with ``dF/dx'`` invertible (notes eq. 7.46).

    Args:
        F: ``F(t, xdot, x[, u]) -> (*batch, n)`` residual, e.g. the mechanical form eq. 7.49
            ``M(q) x' - rhs(q, v)``.
    """

    def check_start(self, t0, x0, z0, u0) -> None:
        n = x0.shape[-1]
        label = f"F({self._args(u0, 'xdot', 'x')})"
        out = self._call(self.F, label, t0, u0, torch.zeros_like(x0), x0, graph=True)
        self._check_output(
            out,
            label,
            n,
            f"x0 has width {n}: F must return one residual per state",
            x0.shape[:-1],
            "(t0, xdot = 0, x0)",
        )


class SemiExplicitDAE(_Problem):
    """Semi-explicit DAE ``x' = f(t, x, z[, u]), 0 = g(t, x, z[, u])`` (notes eq. 5.24, 7.61).

    Index 1 requires ``dg/dz`` to be invertible along the trajectory (Corollary 1, eq. 5.56);
    :func:`daeint` checks it.

    Args:
        f: ``f(t, x, z[, u]) -> (*batch, n)``.
        g: ``g(t, x, z[, u]) -> (*batch, m)``.
    """

    kind = "semi"

    def __init__(self, f: Callable, g: Callable):
        self.f = _check_callable(f, "f")
        self.g = _check_callable(g, "g")

    def functions(self) -> tuple:
        return (self.f, self.g)

    def check_start(self, t0, x0, z0, u0) -> None:
        n, m = x0.shape[-1], z0.shape[-1]
        if m == 0:
            raise InputValidationError(
                "a SemiExplicitDAE needs at least one algebraic state, got z0 of width 0; "
                "for x' = f(t, x) use odeint (or solve_implicit_ode for stiff problems)."
            )
        args = self._args(u0, "x", "z")
        point = "(t0, x0, z0)"
        self._check_output(
            self._call(self.f, f"f({args})", t0, u0, x0, z0),
            f"f({args})",
            n,
            f"x0 has width {n}: f must return one derivative per differential state",
            x0.shape[:-1],
            point,
        )
        self._check_output(
            self._call(self.g, f"g({args})", t0, u0, x0, z0, graph=True),
            f"g({args})",
            m,
            f"z0 has width {m}: g must return one residual per algebraic state",
            x0.shape[:-1],
            point,
        )


class ImplicitDAE(_Residual):
    """Fully implicit DAE ``F(t, x', x, z[, u]) = 0`` (notes eq. 5.22, 7.53).

    Index 1 requires ``[dF/dx', dF/dz]`` to be invertible (Theorem 9, eq. 5.53); :func:`daeint`
    checks it.

    Args:
        F: ``F(t, xdot, x, z[, u]) -> (*batch, n + m)``.
    """

    def check_start(self, t0, x0, z0, u0) -> None:
        n, m = x0.shape[-1], z0.shape[-1]
        if m == 0:
            raise InputValidationError(
                "an ImplicitDAE needs at least one algebraic state, got z0 of width 0; for "
                "F(t, x', x) = 0 use ImplicitODE (F is then called without z)."
            )
        label = f"F({self._args(u0, 'xdot', 'x', 'z')})"
        out = self._call(self.F, label, t0, u0, torch.zeros_like(x0), x0, z0, graph=True)
        self._check_output(
            out,
            label,
            n + m,
            f"x0 and z0 have widths {n} + {m}: F must return one residual per differential "
            f"and algebraic state ({n + m})",
            x0.shape[:-1],
            "(t0, xdot = 0, x0, z0)",
        )
