"""Collocation Runge-Kutta tableaus built from polynomial roots (notes §7.4).

A collocation method with nodes ``c_1 < ... < c_s`` in [0, 1] approximates the state derivative
on each step by the interpolating polynomial ``sum_j K_j l_j(tau)`` (eq. 7.31), where ``l_j``
are the Lagrange polynomials of the nodes (eq. 7.27). Integrating it (eq. 7.37-7.38) gives the
Butcher tableau (eq. 7.41, written with the row index first):

    a_ij = L_j(c_i) = int_0^{c_i} l_j(tau) dtau,    b_j = L_j(1),    c_i = tau_i,

i.e. row ``i`` of ``A`` holds the stage ``i`` quadrature weights. (The notes write
``a_ji = L_i(tau_j)``, the same thing with the indices swapped in both places.)

Node families:

- Gauss-Legendre: the roots of the *shifted* Legendre polynomial ``P_s(2 tau - 1)``. The notes'
  eq. 7.42 gives the Legendre polynomial on [-1, 1], whose roots lie outside the step for
  half of them; the grid of eq. 7.43 must use the shifted one. Order ``2 s``, A-stable,
  ``|R(i y)| = 1``.
- Radau IIA: the roots of ``P_s(2 tau - 1) - P_{s-1}(2 tau - 1)``, which include ``tau = 1``.
  Order ``2 s - 1``, L-stable (``R(inf) = 0``), stiffly accurate (last row of A equals b).

Every collocation tableau satisfies ``C(s)`` (row ``i`` of ``A`` integrates polynomials of
degree ``< s`` over ``[0, c_i]``); Gauss-Legendre adds ``B(2 s)`` and ``D(s)``, Radau IIA
``B(2 s - 1)`` and ``D(s - 1)``, so :class:`ButcherTableau` proves the claimed order from
Butcher's simplifying assumptions in ``O(s^3)`` operations for any ``s`` (see
``integrators/tableau.py``).

The integrals ``int_0^theta l_j`` are computed by an ``s``-point Gauss quadrature on
``[0, theta]`` (exact for the degree ``s - 1`` integrand) with ``l_j`` evaluated in product
form, which avoids the ill-conditioned monomial/Vandermonde route and keeps every entry
accurate to a few ulps for all stage counts used in practice: against 60-digit references,
nodes are within 1e-16 and ``A``, ``b`` within 1e-15 at ``s = 20``.
"""

from __future__ import annotations

from functools import cache

import numpy as np
import torch
from numpy.polynomial import legendre as npleg

from .errors import InputValidationError, TableauError
from .tableau import ButcherTableau

__all__ = ["collocation_output_weights", "gauss_legendre", "lagrange_basis", "radau_iia"]


def _check_stages(s) -> int:
    if isinstance(s, bool) or not isinstance(s, (int, np.integer)) or s < 1:
        raise InputValidationError(
            f"the number of collocation stages must be an integer >= 1, got {s!r}."
        )
    return int(s)


def _gauss_nodes(s: int) -> np.ndarray:
    """Roots of the shifted Legendre polynomial P_s(2 tau - 1), ascending, in (0, 1)."""
    x, _ = npleg.leggauss(s)
    return (x + 1.0) / 2.0


def _radau_nodes(s: int) -> np.ndarray:
    """Roots of P_s(2 tau - 1) - P_{s-1}(2 tau - 1), ascending; the last one is exactly 1."""
    if s == 1:
        return np.array([1.0])
    coef = np.zeros(s + 1)
    coef[s], coef[s - 1] = 1.0, -1.0
    # x = 1 is a root (P_n(1) = 1 for all n); deflate it analytically by dividing by (x - 1).
    quotient, _ = npleg.legdiv(coef, np.array([-1.0, 1.0]))
    # its roots (variable x in [-1, 1]), polished by three Newton steps
    interior, deriv = np.sort(npleg.legroots(quotient).real), npleg.legder(quotient)
    for _ in range(3):
        interior = interior - npleg.legval(interior, quotient) / npleg.legval(interior, deriv)
    return np.append((interior + 1.0) / 2.0, 1.0)


def lagrange_basis(nodes: torch.Tensor, tau: torch.Tensor) -> torch.Tensor:
    """``l_j(tau)`` of eq. 7.27 in product form, ``prod_{m != j} (tau - c_m) / (c_j - c_m)``,
    for nodes (s,) and points ``tau`` of any shape: (*tau.shape, s)."""
    s = nodes.shape[0]
    diff = tau[..., None] - nodes  # (..., s)
    denom = nodes[:, None] - nodes[None, :] + torch.eye(s, dtype=nodes.dtype, device=nodes.device)
    factors = diff[..., None, :] / denom  # (..., j, m)
    eye = torch.eye(s, dtype=torch.bool, device=nodes.device)
    return torch.where(eye, torch.ones_like(factors), factors).prod(-1)


def _lagrange_integrals(nodes: torch.Tensor, theta: torch.Tensor) -> torch.Tensor:
    """``L_j(theta) = int_0^theta l_j`` (eq. 7.38): (*theta.shape, s), by the ``s``-point Gauss
    rule on ``[0, theta]`` (exact for the degree ``s - 1`` integrand)."""
    xi, w = npleg.leggauss(max(nodes.shape[0], 1))
    xi = torch.as_tensor((xi + 1.0) / 2.0, dtype=nodes.dtype, device=nodes.device)
    w = torch.as_tensor(w / 2.0, dtype=nodes.dtype, device=nodes.device)
    basis = lagrange_basis(nodes, theta[..., None] * xi)  # (..., q, s)
    return theta[..., None] * torch.einsum("q,...qj->...j", w, basis)


def _collocation_tableau(nodes: np.ndarray, order: int, name: str) -> ButcherTableau:
    c = torch.from_numpy(nodes)
    A = _lagrange_integrals(c, c).numpy()
    b = _lagrange_integrals(c, torch.ones((), dtype=c.dtype)).numpy()
    # c_i = sum_j a_ij holds analytically (sum_j l_j = 1) and to rounding here; keeping the
    # exact nodes as c makes c_s = 1 exact for Radau IIA (so its last row of A equals b).
    return ButcherTableau(A, b, c=nodes, order=order, name=name)


@cache
def gauss_legendre(s: int) -> ButcherTableau:
    """The ``s``-stage Gauss-Legendre collocation tableau: order ``2 s``, A-stable.

    Nodes are the roots of the shifted Legendre polynomial ``P_s(2 tau - 1)`` (eq. 7.42-7.43,
    corrected to [0, 1]); the coefficients follow eq. 7.41. ``s = 1`` is the implicit midpoint
    rule, ``s = 2`` the fourth-order Hammer-Hollingsworth method.

    Args:
        s: number of stages, >= 1.

    Returns:
        A :class:`ButcherTableau` whose order ``2 s`` has been verified (``B(2 s)``, ``C(s)``,
        ``D(s)``). Results are cached (tableaus are immutable).
    """
    s = _check_stages(s)
    return _collocation_tableau(_gauss_nodes(s), 2 * s, f"gauss_legendre_{s}")


@cache
def radau_iia(s: int) -> ButcherTableau:
    """The ``s``-stage Radau IIA collocation tableau: order ``2 s - 1``, L-stable.

    Nodes are the roots of ``P_s(2 tau - 1) - P_{s-1}(2 tau - 1)`` with ``c_s = 1``; the
    coefficients follow eq. 7.41. ``s = 1`` is implicit Euler, ``s = 3`` the method of
    scipy's ``Radau`` solver.

    Args:
        s: number of stages, >= 1.

    Returns:
        A :class:`ButcherTableau` whose order ``2 s - 1`` has been verified (``B(2 s - 1)``,
        ``C(s)``, ``D(s - 1)``). Results are cached.
    """
    s = _check_stages(s)
    return _collocation_tableau(_radau_nodes(s), 2 * s - 1, f"radau_iia_{s}")


def _check_collocation(tab: ButcherTableau) -> np.ndarray:
    nodes = np.array(tab.c, dtype=np.float64)
    if np.unique(nodes).size != nodes.size:
        raise TableauError(
            f"tableau {tab.name!r} has repeated nodes c = {nodes.tolist()}; dense output by "
            "collocation needs distinct nodes."
        )
    c = torch.from_numpy(nodes)
    if not np.allclose(tab.A, _lagrange_integrals(c, c).numpy(), rtol=0.0, atol=1e-10):
        raise TableauError(
            f"tableau {tab.name!r} is not a collocation method (A differs from the integrated "
            "Lagrange polynomials of its nodes, eq. 7.41), so eq. 7.44 gives no dense output "
            "for it. Use gauss_legendre(s) or radau_iia(s)."
        )
    return nodes


def collocation_output_weights(tab: ButcherTableau, theta):
    """Dense-output weights of a collocation method (eq. 7.44).

    Inside a step, ``x(t_k + theta dt) = x_k + dt * sum_j w_j(theta) K_j`` with
    ``w_j(theta) = int_0^theta l_j(tau) dtau``; ``w(1) = b`` and ``w(c_i) = A[i]``.

    Args:
        tab: a collocation tableau (``gauss_legendre``, ``radau_iia``, implicit midpoint,
            implicit Euler, ...).
        theta: scalar, sequence, ndarray or tensor of fractions of the step, any shape.

    Returns:
        weights of shape ``(*theta.shape, s)``: a tensor (same dtype and device as ``theta``,
        differentiable with respect to it) when ``theta`` is a tensor, else a float64 ndarray.
        For a 1-D ``theta`` this is a ``(len(theta), s)`` array, one row of weights per fraction.

    Raises:
        TableauError: when ``tab`` is not a collocation method.
    """
    nodes = torch.from_numpy(_check_collocation(tab))
    if not isinstance(theta, torch.Tensor):
        theta = torch.tensor(np.asarray(theta, dtype=np.float64))  # a copy: may be read-only
        return _lagrange_integrals(nodes, theta).numpy()
    dtype = theta.dtype if theta.is_floating_point() else torch.get_default_dtype()
    return _lagrange_integrals(nodes.to(dtype=dtype, device=theta.device), theta.to(dtype))
