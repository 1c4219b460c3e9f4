"""Right-hand sides with bound inputs: ``rhs(t, x) = f(t, x, u(t))``.

A model is ``f(t, x)`` or ``f(t, x, u)``. :func:`bind_rhs` turns it into ``rhs(t, x)`` by
binding an input signal, which is either

* a callable ``u(t) -> (nu,) or (*batch, nu)``,
* samples on the output grid ``t_grid`` of shape ``(T, nu)`` (shared by the batch) or
  ``(*batch, T, nu)``, held constant between samples (zero-order hold, notes eq. 8.34:
  ``u(t_k + tau dt) = u_k`` for ``tau in [0, 1)``) or interpolated linearly
  (``u(t_k + tau dt) = (1 - tau) u_k + tau u_{k+1}``).

``t`` is either a 0-dim tensor (a time shared by the batch, used by fixed-step solvers) or a
``(*batch, 1)`` tensor (one time per sample, used by adaptive solvers); the user's ``f`` and a
callable ``u`` receive that same ``t``.

:class:`CollocationInput` is an input given by a polynomial on every output interval (notes
eq. 8.32-8.33): a callable ``u(t)`` for any solver, and the input parameterisation whose
coefficients :func:`integrators.sensitivities` differentiates.

Fixed-step solvers do not look the input up by time: they read :attr:`BoundRHS.samples` and
hold ``u_k`` over the *closed* step interval ``[t_k, t_k + dt]``, so a stage with ``c_i = 1``
(the last stage of RK4) still uses ``u_k`` as eq. 8.34 prescribes. A pure time lookup at
``t_{k+1}`` would return ``u_{k+1}`` (the hold is right-continuous), which breaks the exact
discretisation of piecewise-constant inputs.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

from ._options import check_finite
from .collocation import gauss_legendre, lagrange_basis, radau_iia
from .errors import InputValidationError

INTERPOLATIONS = ("zoh", "linear")
COLLOCATION_NODES = ("radau", "legendre")


class BoundRHS:
    """``rhs(t, x)``: the user's model with its input bound (see module docstring).

    Attributes:
        f: the user's model ``f(t, x)`` (``kind == "none"``) or ``f(t, x, u)``.
        kind: ``"none"``, ``"callable"``, ``"zoh"`` or ``"linear"``.
        u: the input callable (``kind == "callable"``) or None.
        samples: (T, nu) or (*batch, T, nu) input samples (``"zoh"``/``"linear"``) or None.
        t_grid: (T,) sample times of ``samples`` or None.
    """

    def __init__(self, f, kind, u=None, samples=None, t_grid=None):
        self.f = f
        self.kind = kind
        self.u = u
        self.samples = samples
        self.t_grid = t_grid

    def __call__(self, t: torch.Tensor, x: torch.Tensor, interval=None) -> torch.Tensor:
        """Evaluate ``f`` at time ``t`` (0-dim or (*batch, 1)) and state ``x`` (*batch, nx).

        ``interval``: (*batch, 1) indices ``k`` of the sample intervals ``[t_k, t_{k+1}]``
        the evaluations lie in, for solvers whose steps end at the sample times
        (:attr:`breakpoints`): the zero-order hold then gives ``u_k`` on the closed
        interval, its right end included, like the fixed-step solvers."""
        if self.kind == "none":
            return self.f(t, x)
        if self.kind == "callable":
            return self.f(t, x, self.u(t))
        if interval is not None and self.kind == "zoh":
            return self.f(t, x, _take(self.samples, interval, False))
        return self.f(t, x, self.input_at(t))

    @property
    def breakpoints(self) -> torch.Tensor | None:
        """The times (T,) where the input jumps (zero-order hold) or kinks (linear
        interpolation), at which an adaptive solver's steps end; None for a smooth or
        callable input."""
        return self.t_grid if self.kind in INTERPOLATIONS else None

    def input_at(self, t: torch.Tensor) -> torch.Tensor:
        """The input at time(s) ``t`` looked up from the samples.

        Zero-order hold is right-continuous (``u_k`` on ``[t_k, t_{k+1})``); both rules hold
        the first/last sample outside ``[t_0, t_{T-1}]``.

        Args:
            t: 0-dim tensor, or (*batch, 1) per-sample times.

        Returns:
            (nu,) or (*batch, nu) for a 0-dim ``t`` (depending on the samples' shape);
            (*batch, nu) for per-sample times.
        """
        grid, samples = self.t_grid, self.samples
        T = grid.shape[0]
        tq = t.reshape(1) if t.dim() == 0 else t
        if self.kind == "zoh" or T == 1:
            idx = torch.searchsorted(grid, tq.contiguous(), right=True) - 1
            return _take(samples, idx.clamp(0, T - 1), t.dim() == 0)
        k, theta = _locate(grid, tq)
        lo = _take(samples, k, t.dim() == 0)
        hi = _take(samples, k + 1, t.dim() == 0)
        if t.dim() == 0:
            theta = theta.reshape(())
        return lo + theta * (hi - lo)


def _locate(grid: torch.Tensor, tq: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The interval ``k`` of the grid (T >= 2) holding each time of ``tq`` ((1,) or
    (*batch, 1)), looked up right-continuously and clamped to ``[0, T-2]``, and the fraction
    ``tau`` in [0, 1] of that interval at the time (the end intervals' ends held outside)."""
    k = torch.searchsorted(grid, tq.contiguous(), right=True) - 1
    k = k.clamp(0, grid.shape[0] - 2)
    return k, ((tq - grid[k]) / (grid[k + 1] - grid[k])).clamp(0.0, 1.0)


def _take(samples: torch.Tensor, idx: torch.Tensor, shared_time: bool) -> torch.Tensor:
    """Select sample rows: ``idx`` is (1,) for a shared time or (*batch, 1) per sample."""
    if shared_time:
        return samples.index_select(-2, idx).squeeze(-2)
    if samples.dim() == 2:  # (T, nu) shared by the batch
        return samples[idx.squeeze(-1)]
    batch = torch.broadcast_shapes(samples.shape[:-2], idx.shape[:-1])
    samples = samples.expand(*batch, *samples.shape[-2:])
    idx = idx.expand(*batch, 1).unsqueeze(-1).expand(*batch, 1, samples.shape[-1])
    return torch.gather(samples, -2, idx).squeeze(-2)


def bind_rhs(f: Callable, u, t_grid, *, interpolation: str = "zoh") -> BoundRHS:
    """Bind an input to a model: ``rhs(t, x) = f(t, x, u(t))``.

    Args:
        f: ``f(t, x)`` when ``u is None``, else ``f(t, x, u)``; returns (*batch, nx).
        u: None; a callable ``u(t) -> (nu,) or (*batch, nu)``; or samples of shape (T, nu) or
            (*batch, T, nu) on ``t_grid`` (array-likes are converted to ``t_grid``'s dtype).
        t_grid: (T,) strictly increasing sample times (the output grid of ``odeint``).
        interpolation: ``"zoh"`` (zero-order hold, notes eq. 8.34) or ``"linear"``; only used
            for sampled inputs.

    Returns:
        A :class:`BoundRHS`, callable as ``rhs(t, x)``.

    Raises:
        InputValidationError: unknown interpolation, samples whose time axis (dim -2) does not
            have length T, or non-finite samples (the message names the sample index).
    """
    if not callable(f):
        raise InputValidationError(f"f must be callable f(t, x[, u]), got {type(f).__name__}.")
    if interpolation not in INTERPOLATIONS:
        raise InputValidationError(
            f"unknown interpolation {interpolation!r}; use one of {INTERPOLATIONS}."
        )
    if u is None:
        return BoundRHS(f, "none")
    if callable(u) and not isinstance(u, torch.Tensor):
        return BoundRHS(f, "callable", u=u)
    t_grid = torch.as_tensor(t_grid)
    if t_grid.dim() != 1:
        raise InputValidationError(f"t_grid must be 1-D (T,), got shape {tuple(t_grid.shape)}.")
    dtype = t_grid.dtype if t_grid.is_floating_point() else torch.get_default_dtype()
    samples = torch.as_tensor(u, dtype=dtype, device=t_grid.device)
    T = t_grid.shape[0]
    if samples.dim() < 2 or samples.shape[-2] != T:
        raise InputValidationError(
            f"sampled input u must have shape (T, nu) or (*batch, T, nu) with T = len(t) = {T}, "
            f"got shape {tuple(samples.shape)}. For a single input channel use u[..., None]; "
            "for an input defined between the output times pass a callable u(t)."
        )
    check_finite(samples, "input u", time_dim=-2)
    return BoundRHS(f, interpolation, samples=samples, t_grid=t_grid.to(dtype))


class CollocationInput:
    """An input given by polynomials on the output intervals (notes eq. 8.32-8.33).

    On each interval ``[t_k, t_{k+1}]`` (``k = 0, ..., T-2``) of the output grid, with
    ``tau = (t - t_k) / (t_{k+1} - t_k)`` in [0, 1],

        u(t_k + tau (t_{k+1} - t_k)) = sum_i P[..., k, i, :] l_i(tau)              (eq. 8.32)

    where ``l_i`` are the Lagrange polynomials (eq. 7.27) of ``q`` distinct nodes
    ``tau_1 < ... < tau_q`` in [0, 1]: the coefficient ``P[..., k, i, :]`` is the input value at
    ``t_k + tau_i (t_{k+1} - t_k)``, so ``u`` is a polynomial of degree ``q - 1`` on each
    interval and may jump at the grid points. The flattened ``P`` is the parameter vector of
    eq. 8.33. With ``q = 1`` it is the piecewise-constant input of eq. 8.34.

    Use it as ``u=`` of :func:`integrators.sensitivities` (which then returns
    ``C = dx_k / dP``, shape (*batch, T, nx, T-1, q, nu)) and, being a callable ``u(t)``, of
    :func:`integrators.odeint`. A simulation uses interval ``k``'s polynomial on the *closed*
    interval (a stage at ``t_{k+1}`` of a step in interval ``k`` sees ``tau = 1``), as
    ``sensitivities`` does; a call ``u(t)`` cannot know the step and looks up the interval
    right-continuously (``t_{k+1}`` belongs to interval ``k + 1``, ``tau = 0``). The two agree
    except at a stage exactly on a grid point where the pieces jump (stages with ``c_i = 1``,
    e.g. the last stage of RK4 or Radau IIA, when ``P[..., k, :, :]`` does not continue
    into ``P[..., k+1, :, :]``). Outside ``[t_0, t_{T-1}]`` the end values are held.

    Args:
        coefficients: (T-1, q, nu) shared by the batch, or (*batch, T-1, q, nu): the input
            values at the nodes of every interval, in the units of ``u``.
        t: (T,) strictly increasing output grid (the ``t`` of the simulation).
        nodes: ``"radau"`` (default: the Radau IIA nodes, ``tau_q = 1``), ``"legendre"``
            (the Gauss-Legendre nodes, all inside (0, 1)) - the two schemes of CasADi's
            ``collocation_points(q, scheme)`` - or a (q,) sequence of distinct values in
            [0, 1] (fractions of the interval, dimensionless), e.g. ``(0, 1)`` for a
            piecewise-linear input.

    Attributes:
        coefficients: (*batch, T-1, q, nu) tensor; t: (T,); nodes: (q,) tensor (same dtype).

    Raises:
        InputValidationError: a bad shape, grid or node set, or non-finite coefficients.
    """

    def __init__(self, coefficients, t, nodes="radau"):
        t = torch.as_tensor(t)
        dtype = t.dtype if t.is_floating_point() else torch.get_default_dtype()
        if isinstance(coefficients, torch.Tensor) and coefficients.is_floating_point():
            dtype = coefficients.dtype
        t = t.to(dtype)
        if t.dim() != 1 or t.shape[0] < 2 or not bool(torch.all(t[1:] > t[:-1])):
            raise InputValidationError(
                "CollocationInput: t must be a strictly increasing (T,) grid with T >= 2, got "
                f"shape {tuple(t.shape)}."
            )
        P = torch.as_tensor(coefficients, dtype=dtype, device=t.device)
        T = t.shape[0]
        if P.dim() < 3 or P.shape[-3] != T - 1:
            raise InputValidationError(
                f"CollocationInput: coefficients must have shape (T-1, q, nu) or "
                f"(*batch, T-1, q, nu) with T-1 = {T - 1} intervals, got {tuple(P.shape)}. "
                "For one input channel use P[..., None]."
            )
        check_finite(P, "CollocationInput coefficients", time_dim=-3)
        self.coefficients, self.t = P, t
        self.nodes = _collocation_nodes(nodes, P.shape[-2], dtype, t.device)

    @property
    def n_nodes(self) -> int:
        """``q``, the number of nodes per interval."""
        return self.nodes.shape[0]

    def weights(self, tau: torch.Tensor) -> torch.Tensor:
        """``l_i(tau)`` of the nodes (eq. 7.27) at fractions ``tau`` of any shape: (*tau, q)."""
        return lagrange_basis(self.nodes, tau.to(self.nodes.dtype))

    def __call__(self, t: torch.Tensor) -> torch.Tensor:
        """The input at time(s) ``t``: a 0-dim tensor (one time for the batch) gives
        (nu,) or (*batch, nu) (like the coefficients); per-sample times (*batch, 1) give
        (*batch, nu)."""
        grid, P = self.t, self.coefficients
        t = torch.as_tensor(t, dtype=grid.dtype, device=grid.device)
        k, tau = _locate(grid, t.reshape(1) if t.dim() == 0 else t)
        w = self.weights(tau)  # (1, q) or (*batch, 1, q)
        # the interval's coefficients (q, nu) or (*batch, q, nu), rows of P flattened per interval
        Pk = _take(P.flatten(-2), k, t.dim() == 0).unflatten(-1, P.shape[-2:])
        return (w @ Pk).squeeze(-2)


def _collocation_nodes(nodes, q: int, dtype, device) -> torch.Tensor:
    """The (q,) node tensor of :class:`CollocationInput` from a scheme name or values."""
    if isinstance(nodes, str):
        if nodes not in COLLOCATION_NODES:
            raise InputValidationError(
                f"CollocationInput: unknown nodes {nodes!r}; use one of {COLLOCATION_NODES} "
                "or a (q,) sequence of distinct values in [0, 1]."
            )
        values = (radau_iia if nodes == "radau" else gauss_legendre)(q).c
        return torch.as_tensor(np.array(values), dtype=dtype, device=device)
    out = torch.as_tensor(nodes, dtype=dtype, device=device).detach()
    if out.dim() != 1 or out.shape[0] != q:
        raise InputValidationError(
            f"CollocationInput: nodes must be a (q,) sequence with q = {q} (the coefficients' "
            f"dim -2), got shape {tuple(out.shape)}."
        )
    ordered = torch.sort(out).values
    if not bool(torch.isfinite(out).all()) or bool((ordered[0] < 0) | (ordered[-1] > 1)):
        raise InputValidationError(
            f"CollocationInput: nodes must lie in [0, 1] (fractions of the interval), got "
            f"{out.tolist()}."
        )
    if bool(torch.any(ordered[1:] == ordered[:-1])):
        raise InputValidationError(
            "CollocationInput: nodes must be distinct (Lagrange interpolation), got "
            f"{out.tolist()}."
        )
    return out
