"""Continuous extensions (dense output) of explicit Runge-Kutta steps.

A continuous extension replaces the weights ``b`` of a step (notes eq. 6.26d / 6.44a) by
polynomials ``b_i(theta)``, ``theta in [0, 1]``:

    x(t_k + theta dt) = x_k + dt * sum_i b_i(theta) K_i,     b_i(theta) = sum_m w_im theta^m.

The weights here act on the *extended* stage list ``K_1 .. K_s, f(t_{k+1}, x_{k+1})``; for a
first-same-as-last tableau (notes eq. 6.45) the last stage already is ``f(t_{k+1}, x_{k+1})``
and the list is just ``K_1 .. K_s``.

Dormand-Prince 5(4) (notes §6.5, tableau after eq. 6.44) gets a quartic extension of order 4,
derived here from the order conditions of the interpolant: for every rooted tree ``tau`` with
at most 4 vertices, ``sum_i b_i(theta) Phi_i(tau) = theta^|tau| / gamma(tau)`` for all theta,
plus the Hermite conditions ``b(0) = 0``, ``b'(0) = e_1`` (slope ``K_1``), ``b(1) = b``
(reproduces ``x_{k+1}``) and ``b'(1) = e_7`` (slope ``f(x_{k+1}) = K_7``). These linear
conditions leave exactly one free parameter, ``w_74``; it is fixed by minimising
``int_0^1 sum_{|tau| = 5} (b(theta) . Phi(tau) - theta^5 / gamma(tau))^2 / sigma(tau) dtheta``
(sigma the tree's symmetry number), i.e. the principal error coefficients of the interpolant,
which gives ``w_74 = 73965745 / 30922813`` (Shampine's classical choice is the nearby
``69997945 / 29380423``). The conditions are re-checked numerically in the tests.

Other tableaus with an embedded pair get the cubic Hermite interpolant through
``x_k, x_{k+1}, f(x_k), f(x_{k+1})`` (order 3).
"""

from __future__ import annotations

from dataclasses import dataclass
from fractions import Fraction

import numpy as np
import torch

from .tableau import ButcherTableau, tableau

_DOPRI5_DENSE = [
    ["1", "-8472496741/2968590048", "9121521793/2968590048", "-13388161945/11874360192"],
    ["0", "0", "0", "0"],
    [
        "0",
        "138520041400/34417090869",
        "-71731485600/11472363623",
        "92135821900/34417090869",
    ],
    ["0", "-1853598675/494765008", "14986943675/1484295024", "-11279746325/1979060032"],
    [
        "0",
        "134998302753/52445090848",
        "-337624797537/52445090848",
        "742877787105/209780363392",
    ],
    ["0", "-300946503/216459691", "2145829961/649379073", "-1543936955/865838764"],
    ["0", "43042932/30922813", "-117008677/30922813", "73965745/30922813"],
]


@dataclass(frozen=True)
class ContinuousExtension:
    """Polynomial stage weights of a dense-output formula.

    Attributes:
        weights: (s_ext, 4) array ``w`` with ``b_i(theta) = sum_{m=1..4} w[i, m-1] theta^m``.
        order: the order of the interpolant (local error O(dt^(order+1)) for every theta).
        extra_eval: True when ``f(t_{k+1}, x_{k+1})`` is not a stage of the tableau and is
            appended as stage ``s + 1`` (it is then reused as ``K_1`` of the next step).
    """

    weights: np.ndarray
    order: int
    extra_eval: bool

    def stage_weights(self, theta) -> np.ndarray:
        """``b_i(theta)`` as a (len(theta), s_ext) array for theta of shape (M,)."""
        theta = np.atleast_1d(np.asarray(theta, dtype=np.float64))
        powers = theta[:, None] ** np.arange(1, 5)[None, :]
        return powers @ self.weights.T

    def tensor(self, dtype=torch.float64, device=None) -> torch.Tensor:
        """The weights as a (s_ext, 4) tensor."""
        return torch.as_tensor(self.weights, dtype=dtype, device=device)


def dopri5_dense_weights() -> np.ndarray:
    """The (7, 4) quartic dense-output weights of Dormand-Prince 5(4) derived above."""
    return np.array([[float(Fraction(v)) for v in row] for row in _DOPRI5_DENSE])


def _is_dopri5(tab: ButcherTableau) -> bool:
    ref = tableau("dopri5")
    if tab.stages != ref.stages or tab.b_err is None:
        return False
    return all(
        np.allclose(getattr(tab, k), getattr(ref, k), rtol=0, atol=1e-15)
        for k in ("A", "b", "b_err")
    )


def continuous_extension(tab: ButcherTableau) -> ContinuousExtension:
    """The dense-output formula used by the adaptive solver for an explicit tableau.

    Dormand-Prince 5(4) gets its quartic 4th-order extension; every other explicit tableau
    gets the cubic Hermite interpolant written in stage weights: with ``D = sum_i b_i K_i``
    (so ``x_{k+1} - x_k = dt D``) and ``F = f(x_{k+1})``,
    ``b(theta) = theta e_1 + theta^2 (3 D - 2 e_1 - F) + theta^3 (e_1 + F - 2 D)``.
    """
    if _is_dopri5(tab):
        return ContinuousExtension(dopri5_dense_weights(), order=4, extra_eval=False)
    s = tab.stages
    extra = not tab.is_fsal
    n = s + 1 if extra else s
    bvec = np.zeros(n)
    bvec[:s] = tab.b
    first, last = np.eye(n)[[0, -1]]
    weights = np.stack(
        [first, 3.0 * bvec - 2.0 * first - last, first + last - 2.0 * bvec, np.zeros(n)], axis=1
    )
    return ContinuousExtension(weights, order=min(3, tab.order), extra_eval=extra)
