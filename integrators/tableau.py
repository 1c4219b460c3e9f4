"""Butcher tableaus: validation, order conditions, stability functions.

A Runge-Kutta method (notes eq. 6.26) is defined by its tableau ``(A, b, c)``:

    K_i     = f(t_k + c_i dt, x_k + dt * sum_j a_ij K_j)
    x_{k+1} = x_k + dt * sum_i b_i K_i

A method has order p when ``b . Phi(tau) = 1 / gamma(tau)`` for every rooted tree ``tau``
with at most p vertices, where ``Phi`` is the elementary weight vector (products of
``A @ Phi(child)`` over the children of the root) and ``gamma`` the tree's density.
These conditions are generated here for any order, so a tableau verifies its own order
numerically instead of trusting a typed-in label.

The number of rooted trees grows about 3x per order (OEIS A000081: 4766 of order 12,
12 826 228 of order 20), so high orders are verified with Butcher's simplifying assumptions
(Butcher 1964; Hairer, Norsett & Wanner, *Solving ODEs I*, Thm. II.7.4), which cost
``O(p s^2)``:

    B(p): sum_i b_i c_i^(k-1)       = 1 / k                          k = 1..p
    C(q): sum_j a_ij c_j^(k-1)      = c_i^k / k              all i,  k = 1..q
    D(r): sum_i b_i c_i^(k-1) a_ij  = b_j (1 - c_j^k) / k    all j,  k = 1..r

If ``B(p)``, ``C(q)`` and ``D(r)`` hold with ``p <= q + r + 1`` and ``p <= 2 q + 2``, the
method has order ``p``. ``B(p)`` is also necessary (its equations are the conditions of the
bushy trees), so the order lies between ``min(p, q + r + 1, 2 q + 2)`` and ``p``. Each
equation is linear in the polynomial ``t^(k-1)`` (with ``c^k / k = int_0^c t^(k-1) dt``), so
it is evaluated with the shifted Legendre polynomial ``P_(k-1)(2 t - 1)`` in its place: the
same conditions, but well conditioned at high degree.

The rule used here: the simplifying assumptions first; the rooted-tree conditions only for
the orders in the gap they leave, and only up to order ``MAX_TREE_ORDER``. Collocation methods
(Gauss-Legendre: ``B(2s), C(s), D(s)``; Radau IIA: ``B(2s-1), C(s), D(s-1)``) close the gap
for any ``s``; explicit methods (only ``C(1)`` holds) are checked tree by tree.
"""

from __future__ import annotations

import math
from fractions import Fraction
from functools import cache

import numpy as np
import torch

from ._options import is_real_number
from .errors import TableauError

_DEFAULT_TOL = 1e-10
#: Range of ``ButcherTableau``'s ``tol``: below ten float64 epsilons the rounding of exact
#: coefficients (1/3 stored in float64) already fails the order conditions; above 1e-6 a tableau
#: whose weights sum to 1 + 1e-6 would pass as consistent, a method that integrates
#: x' = (1 + 1e-6) f instead of x' = f. 1e-6 still admits coefficients printed to 7 digits.
_TOL_RANGE = (10 * float(np.finfo(np.float64).eps), 1e-6)
MAX_TREE_ORDER = 12
"""Highest order whose rooted-tree conditions are checked (7813 trees up to it, ~0.1 s)."""


class _RootedTrees:
    """Rooted trees enumerated by order, each a sorted multiset of child-tree indices."""

    def __init__(self) -> None:
        self.order: list[int] = [1]
        self.children: list[tuple[int, ...]] = [()]
        self.gamma: list[int] = [1]
        self.by_order: dict[int, list[int]] = {1: [0]}

    def _forests(self, total: int, min_id: int):
        if total == 0:
            yield ()
            return
        for tid in range(min_id, len(self.order)):
            size = self.order[tid]
            if size > total:
                break
            for rest in self._forests(total - size, tid):
                yield (tid, *rest)

    def upto(self, p: int) -> None:
        """Enumerate all trees with at most ``p`` vertices."""
        n = max(self.by_order) + 1
        while n <= p:
            ids = []
            for forest in list(self._forests(n - 1, 0)):
                self.order.append(n)
                self.children.append(forest)
                self.gamma.append(n * math.prod(self.gamma[child] for child in forest))
                ids.append(len(self.order) - 1)
            self.by_order[n] = ids
            n += 1


_TREES = _RootedTrees()


def _butcher_bound(p: int, q: int, r: int) -> int:
    """The order proved by B(p), C(q), D(r): ``min(p, q + r + 1, 2 q + 2)`` (Butcher 1964)."""
    return min(p, q + r + 1, 2 * q + 2)


class ButcherTableau:
    """A Runge-Kutta Butcher tableau (notes §6.3.1) that checks itself.

    Args:
        A: (s, s) stage coefficients ``a_ij``.
        b: (s,) weights of the propagating solution; must sum to 1.
        c: (s,) nodes; must equal the row sums of ``A``. Computed from ``A`` when omitted.
        b_err: (s,) weights of the embedded solution of an adaptive pair (notes eq. 6.44b);
            must sum to 1. The local error estimate is ``dt * sum_i (b_i - b_err_i) K_i``.
        order: the claimed order. It is verified (see the module docstring) and a
            :class:`TableauError` naming the verified order is raised if it does not hold.
            When omitted, the order is computed: exactly when the simplifying assumptions
            settle it or it is at most :data:`MAX_TREE_ORDER`, else as the lower bound
            :data:`MAX_TREE_ORDER`.
        name: a label used in messages and tables.
        tol: absolute tolerance on each rooted-tree condition and on each equation of the
            simplifying assumptions (in their Legendre form, see ``simplifying_assumptions``);
            a number from ``2.2e-15`` (ten float64 epsilons) to ``1e-6``.

    Raises:
        TableauError: ``tol`` outside ``[2.2e-15, 1e-6]``, non-square ``A``, inconsistent
            lengths, non-finite entries, ``c_i != sum_j a_ij``, weights that do not sum to 1
            (an inconsistent method, order 0, does not converge), or a claimed order that
            cannot be verified.

    ``A``, ``b``, ``c`` and ``b_err`` are read-only, so a tableau handed to a solver is the one
    that was checked.
    """

    def __init__(self, A, b, c=None, b_err=None, order=None, name=None, tol=_DEFAULT_TOL):
        self.name = name or "custom"
        self.tol = self._checked_tol(tol)
        if order is not None and (
            isinstance(order, bool) or not isinstance(order, (int, np.integer)) or order < 1
        ):
            raise TableauError(
                f"tableau {self.name!r}: order must be an integer >= 1, got {order!r}."
            )
        self._A = self._as_array(A, "A", ndim=2)
        s = self._A.shape[0]
        if self._A.shape != (s, s) or s == 0:
            raise TableauError(
                f"tableau {self.name!r}: A must be a non-empty square matrix, got shape "
                f"{self._A.shape}."
            )
        self._b = self._as_array(b, "b", ndim=1, length=s)
        row_sums = self._A.sum(axis=1)
        self._c = row_sums.copy() if c is None else self._as_array(c, "c", ndim=1, length=s)
        mismatch = np.abs(self._c - row_sums)
        if np.any(mismatch > 1e-12 * max(1.0, np.abs(self._A).max())):
            i = int(np.argmax(mismatch))
            raise TableauError(
                f"tableau {self.name!r}: c[{i}] = {self._c[i]!r} but row {i} of A sums to "
                f"{row_sums[i]!r}; the nodes must satisfy c_i = sum_j a_ij."
            )
        self._b_err = None if b_err is None else self._as_array(b_err, "b_err", ndim=1, length=s)
        for arr in (self._A, self._b, self._c) + (() if b_err is None else (self._b_err,)):
            arr.setflags(write=False)
        self._tensor_cache: dict = {}
        self._check_consistent(self._b, "b")
        self._order, exact = self._verified_order(self._b)
        self._embedded_order = None
        if self._b_err is not None:
            self._check_consistent(self._b_err, "b_err")
            self._embedded_order = self._verified_order(self._b_err)[0]
        if order is not None:
            if order > self._order:
                raise TableauError(self._refuted_claim(int(order), exact))
            self._order = int(order)

    def _checked_tol(self, tol) -> float:
        """``tol`` as a float when it is a real number in ``_TOL_RANGE``, else TableauError."""
        low, high = _TOL_RANGE
        if not is_real_number(tol) or not low <= tol <= high:
            raise TableauError(
                f"tableau {self.name!r}: tol must be a number from {low:.2g} to {high:g}, got "
                f"{tol!r}; it bounds the residual of every order condition (a larger one would "
                "accept weights that do not sum to 1), default 1e-10."
            )
        return float(tol)

    def _as_array(self, value, label, ndim, length=None) -> np.ndarray:
        if isinstance(value, torch.Tensor):
            value = value.detach().cpu().numpy()
        try:
            arr = np.array(value, dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise TableauError(f"tableau {self.name!r}: {label} is not numeric ({exc}).") from exc
        if arr.ndim != ndim:
            raise TableauError(
                f"tableau {self.name!r}: {label} must have {ndim} dimension(s), got shape "
                f"{arr.shape}."
            )
        if length is not None and arr.shape[0] != length:
            raise TableauError(
                f"tableau {self.name!r}: {label} has length {arr.shape[0]} but A has "
                f"{length} stages."
            )
        if not np.all(np.isfinite(arr)):
            raise TableauError(f"tableau {self.name!r}: {label} contains non-finite entries.")
        return arr

    def _check_consistent(self, weights: np.ndarray, label: str) -> None:
        """Order 1 (``sum_i w_i = 1``): without it the method does not converge."""
        total = float(weights.sum())
        if abs(total - 1.0) > self.tol:
            raise TableauError(
                f"tableau {self.name!r}: the weights {label} sum to {total!r}, not 1, so the "
                "method is inconsistent (order 0: it does not converge as dt -> 0, not even on "
                f"x' = 1). Check the coefficients of {label}; they must satisfy sum_i "
                f"{label}_i = 1."
            )

    def _refuted_claim(self, claimed: int, exact: bool) -> str:
        if exact:
            nxt = self._order + 1
            if nxt > self.simplifying_assumptions()[0]:  # B(nxt) fails: the bushy tree
                monomial = abs(float(self.b @ self.c ** (nxt - 1)) - 1.0 / nxt)
                legendre = abs(float(self._simplifying_residuals(self.b, nxt)[0][-1]))
                miss = (
                    f"its quadrature condition sum_i b_i c_i^{nxt - 1} = 1/{nxt} misses by "
                    f"{monomial:.2e}, in the shifted-Legendre form that decides by {legendre:.2e}"
                )
            else:
                worst = float(np.max(np.abs(self.order_residuals(nxt))))
                miss = f"an order-{nxt} condition misses by {worst:.2e}"
            return (
                f"tableau {self.name!r} claims order {claimed} but its order conditions hold "
                f"only up to order {self._order} ({miss}, tolerance {self.tol:.0e}). Check the "
                "coefficients, or pass order=None to have the order computed."
            )
        p, q, r = self.simplifying_assumptions()
        return (
            f"tableau {self.name!r} claims order {claimed}, which could be verified only up to "
            f"order {self._order}: the simplifying assumptions hold as B({p}), C({q}), D({r}), "
            f"which prove order {_butcher_bound(p, q, r)}, and rooted-tree conditions are "
            f"checked up to order {MAX_TREE_ORDER} only. Claim order <= {self._order}, or check "
            "the coefficients (collocation tableaus satisfy C(s) and prove their order)."
        )

    # ----------------------------------------------------------------- structure
    @property
    def A(self) -> np.ndarray:
        """(s, s) read-only stage coefficients ``a_ij``."""
        return self._A

    @property
    def b(self) -> np.ndarray:
        """(s,) read-only weights of the propagating solution."""
        return self._b

    @property
    def c(self) -> np.ndarray:
        """(s,) read-only nodes, ``c_i = sum_j a_ij``."""
        return self._c

    @property
    def b_err(self) -> np.ndarray | None:
        """(s,) read-only embedded weights, or None for a single method."""
        return self._b_err

    @property
    def stages(self) -> int:
        """Number of stages ``s``."""
        return self.A.shape[0]

    @property
    def is_explicit(self) -> bool:
        """True when ``a_ij = 0`` for all ``j >= i`` (notes §6.3.1)."""
        return bool(np.all(np.triu(self.A) == 0.0))

    @property
    def is_diagonally_implicit(self) -> bool:
        """True when ``A`` is lower triangular with a non-zero diagonal entry."""
        return bool(np.all(np.triu(self.A, 1) == 0.0)) and not self.is_explicit

    @property
    def is_fsal(self) -> bool:
        """First-same-as-last: the last stage is evaluated at the new step (notes eq. 6.45)."""
        return (
            self.is_explicit
            and abs(self.c[-1] - 1.0) <= 1e-14
            and bool(np.allclose(self.A[-1], self.b, rtol=0.0, atol=1e-15))
        )

    @property
    def order(self) -> int:
        """The verified order of the propagating weights ``b``."""
        return self._order

    @property
    def embedded_order(self) -> int | None:
        """The verified order of the embedded weights ``b_err``, or None for a single method."""
        return self._embedded_order

    @property
    def error_weights(self) -> np.ndarray | None:
        """``b - b_err``: the weights of the local error estimate (notes eq. 6.44)."""
        return None if self.b_err is None else self.b - self.b_err

    # ---------------------------------------------------------- order conditions
    def simplifying_assumptions(self, weights=None) -> tuple[int, int, int]:
        """The largest ``p, q, r`` such that ``B(p)``, ``C(q)``, ``D(r)`` hold within ``tol``.

        See the module docstring for the conditions. ``p <= 2 s`` always (an ``s``-point
        quadrature is exact for degree ``2 s - 1`` at most); ``q`` and ``r`` are reported up
        to ``p`` only, which is all that Butcher's theorem uses.

        Args:
            weights: (s,) weights; defaults to ``b``.

        Returns:
            ``(p, q, r)``; the order then lies between ``min(p, q + r + 1, 2 q + 2)`` and ``p``.
        """
        w = self.b if weights is None else np.asarray(weights, dtype=np.float64)
        res_b, res_c, res_d = self._simplifying_residuals(w, 2 * self.stages)

        def largest(residuals, limit):
            k = 0
            while k < limit and np.all(np.abs(residuals[k]) <= self.tol):
                k += 1
            return k

        p = largest(res_b, 2 * self.stages)
        return p, largest(res_c, p), largest(res_d, p)

    def _simplifying_residuals(self, w: np.ndarray, kmax: int):
        """Residuals of the k-th equations of B, C, D for k = 1..kmax, in the Legendre basis.

        The k-th equations are linear in the polynomial ``t^(k-1)``; the shifted Legendre
        polynomial ``P_(k-1)(2 t - 1)`` (bounded by 1 on [0, 1]) replaces it, so that together
        with the equations for lower k they span the same conditions. The monomial form is
        ill-conditioned at high degree: Radau IIA misses ``sum_i b_i c_i^(2s-1) = 1/(2s)`` by
        only 6e-12 at s = 10 and 5e-24 at s = 20, under any usable tolerance, but misses the
        Legendre form of the same condition by 0.21 and 0.14.

        Returns:
            ``(B, C, D)``: arrays of shapes (kmax,), (kmax, s), (kmax, s).
        """
        x = 2.0 * self.c - 1.0
        leg = np.empty((kmax + 1, self.stages))  # leg[n] = P_n(2 c - 1)
        leg[0], leg[1] = 1.0, x
        for n in range(1, kmax):
            leg[n + 1] = ((2 * n + 1) * x * leg[n] - n * leg[n - 1]) / (n + 1)
        # int_0^c P_n(2t - 1) dt = (P_(n+1) - P_(n-1)) / (2 (2n + 1)) at t = c, and c for n = 0
        integral = np.empty((kmax, self.stages))
        integral[0] = self.c
        n = np.arange(1, kmax)[:, None]
        integral[1:] = (leg[2 : kmax + 1] - leg[: kmax - 1]) / (2 * (2 * n + 1))
        whole = np.zeros((kmax, 1))  # int_0^1 P_n(2t - 1) dt = delta_n0
        whole[0] = 1.0
        vals = leg[:kmax]
        res_b = vals @ w - whole[:, 0]
        res_c = vals @ self.A.T - integral
        res_d = (vals * w) @ self.A - w * (whole - integral)
        return res_b, res_c, res_d

    def rooted_tree_order(self, limit: int, weights=None) -> int:
        """The largest ``p <= limit`` whose rooted-tree conditions all hold within ``tol``.

        Checks every tree with at most ``p + 1`` vertices (A000081 grows ~3x per order), so
        it is meant for ``limit`` up to about :data:`MAX_TREE_ORDER`.
        """
        order = 0
        for p in range(1, limit + 1):
            if not np.all(np.abs(self.order_residuals(p, weights)) <= self.tol):
                break
            order = p
        return order

    def order_residuals(self, p: int, weights=None) -> np.ndarray:
        """Residuals ``w . Phi(tau) - 1/gamma(tau)`` over all trees with exactly ``p`` vertices.

        Args:
            p: tree order, >= 1.
            weights: (s,) quadrature weights; defaults to ``b``.

        Returns:
            (number of trees of order p,) array of residuals.
        """
        if p < 1:
            raise TableauError(f"order must be >= 1, got {p}.")
        w = self.b if weights is None else np.asarray(weights, dtype=np.float64)
        phi = self._elementary_weights(p)
        return np.array([w @ phi[t] - 1.0 / _TREES.gamma[t] for t in _TREES.by_order[p]])

    def satisfies_order(self, p: int, weights=None) -> bool:
        """True when all rooted-tree conditions up to order ``p`` hold within ``tol``."""
        return self.rooted_tree_order(p, weights) == p

    def _verified_order(self, weights) -> tuple[int, bool]:
        """``(order, exact)``: the order of ``weights`` by the rule of the module docstring.

        ``exact`` is False when the order could be higher than reported: the simplifying
        assumptions leave a gap above :data:`MAX_TREE_ORDER`, and every tree condition up to
        that order holds.
        """
        p, q, r = self.simplifying_assumptions(weights)
        lower = _butcher_bound(p, q, r)
        order = lower
        for k in range(lower + 1, min(p, MAX_TREE_ORDER) + 1):
            if not np.all(np.abs(self.order_residuals(k, weights)) <= self.tol):
                return order, True
            order = k
        return order, order == p

    def _elementary_weights(self, p: int) -> dict[int, np.ndarray]:
        _TREES.upto(p)
        cache = self.__dict__.setdefault("_phi", {})
        s = self.stages
        for tid in range(len(_TREES.order)):
            if tid in cache or _TREES.order[tid] > p:
                continue
            vec = np.ones(s)
            for child in _TREES.children[tid]:
                vec = vec * (self.A @ cache[child])
            cache[tid] = vec
        return cache

    # ------------------------------------------------------------------ stability
    def stability_function(self, z):
        """R(z) = 1 + z b^T (I - z A)^{-1} 1, the growth factor on x' = lambda x, z = lambda dt.

        Args:
            z: complex scalar or array of any shape.

        Returns:
            complex ndarray of the same shape (inf where I - zA is singular).
        """
        z = np.asarray(z, dtype=np.complex128)
        s = self.stages
        flat = z.reshape(-1)
        mats = np.eye(s)[None] - flat[:, None, None] * self.A[None]
        ones = np.ones((flat.size, s, 1), dtype=np.complex128)
        out = np.full(flat.size, np.inf, dtype=np.complex128)  # inf where I - zA is singular
        ok = np.abs(np.linalg.det(mats)) > 1e-300
        if np.any(ok):
            w = np.linalg.solve(mats[ok], ones[ok])[..., 0]
            out[ok] = 1.0 + flat[ok] * (w @ self.b)
        return out.reshape(z.shape)

    def stability_at_infinity(self) -> float:
        """lim R(z) for ``|z| -> inf``: ``1 - b^T A^{-1} 1`` (0 for L-stable Radau IIA).

        Raises:
            TableauError: for tableaus with a singular ``A`` (explicit methods are unbounded).
        """
        if abs(np.linalg.det(self.A)) < 1e-300:
            raise TableauError(
                f"tableau {self.name!r} has a singular A: R(z) is unbounded as |z| -> inf."
            )
        return float(1.0 - self.b @ np.linalg.solve(self.A, np.ones(self.stages)))

    # -------------------------------------------------------------------- tensors
    def tensors(self, dtype=torch.float64, device=None):
        """``(A, b, c, error_weights)`` as torch tensors (cached per dtype and device)."""
        key = (dtype, str(device))
        if key not in self._tensor_cache:
            self._tensor_cache[key] = tuple(
                None if arr is None else torch.tensor(arr, dtype=dtype, device=device)
                for arr in (self.A, self.b, self.c, self.error_weights)
            )
        return self._tensor_cache[key]

    def __repr__(self) -> str:
        kind = "explicit" if self.is_explicit else "implicit"
        emb = "" if self.b_err is None else f", embedded order {self.embedded_order}"
        return (
            f"ButcherTableau({self.name!r}, {kind}, stages={self.stages}, order={self.order}{emb})"
        )


def _fracs(values: str) -> list[float]:
    """The exact fractions of ``values``, separated by spaces (``"1/6 -2/3 1"``), as floats."""
    return [float(Fraction(v)) for v in values.split()]


def _lower(*rows: str) -> list[list[float]]:
    """Full A from the strictly lower rows of an explicit tableau (row i has i entries)."""
    return [_fracs(row) + [0.0] * (len(rows) - i) for i, row in enumerate(rows)]


def _catalogue() -> dict[str, dict]:
    dopri_rows = (
        "",
        "1/5",
        "3/40 9/40",
        "44/45 -56/15 32/9",
        "19372/6561 -25360/2187 64448/6561 -212/729",
        "9017/3168 -355/33 46732/5247 49/176 -5103/18656",
        "35/384 0 500/1113 125/192 -2187/6784 11/84",
    )
    return {
        "euler": dict(A=[[0.0]], b=[1.0], order=1),
        "midpoint": dict(A=_lower("", "1/2"), b=[0.0, 1.0], order=2),
        "heun": dict(A=_lower("", "1"), b=[0.5, 0.5], order=2),
        "ralston": dict(A=_lower("", "2/3"), b=[0.25, 0.75], order=2),
        "kutta3": dict(A=_lower("", "1/2", "-1 2"), b=_fracs("1/6 2/3 1/6"), order=3),
        "rk4": dict(A=_lower("", "1/2", "0 1/2", "0 0 1"), b=_fracs("1/6 1/3 1/3 1/6"), order=4),
        "rk38": dict(
            A=_lower("", "1/3", "-1/3 1", "1 -1 1"), b=[0.125, 0.375, 0.375, 0.125], order=4
        ),
        "dopri5": dict(
            A=_lower(*dopri_rows),
            b=_fracs("35/384 0 500/1113 125/192 -2187/6784 11/84 0"),
            b_err=_fracs("5179/57600 0 7571/16695 393/640 -92097/339200 187/2100 1/40"),
            order=5,
        ),
        "implicit_euler": dict(A=[[1.0]], b=[1.0], order=1),
        "implicit_midpoint": dict(A=[[0.5]], b=[1.0], order=2),
    }


#: Names of the catalogued tableaus, accepted by :func:`tableau` and by ``odeint(method=...)``.
TABLEAU_NAMES = tuple(_catalogue())


@cache
def tableau(name: str) -> ButcherTableau:
    """A catalogued tableau by name: one of :data:`TABLEAU_NAMES` (notes §6.2-6.5, §7.1).

    Raises:
        TableauError: for an unknown name (the message lists the known ones).
    """
    catalogue = _catalogue()
    if name not in catalogue:
        raise TableauError(
            f"unknown tableau {name!r}; known names are {', '.join(catalogue)}. For "
            "collocation methods use gauss_legendre(s) or radau_iia(s)."
        )
    return ButcherTableau(name=name, **catalogue[name])
