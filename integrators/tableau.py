"""Butcher tableaus: validation, order conditions from rooted trees, stability functions.

A Runge-Kutta method (notes eq. 6.26) is defined by its tableau ``(A, b, c)``:

    K_i     = f(t_k + c_i dt, x_k + dt * sum_j a_ij K_j)
    x_{k+1} = x_k + dt * sum_i b_i K_i

A method has order p when ``b . Phi(tau) = 1 / gamma(tau)`` for every rooted tree ``tau``
with at most p vertices, where ``Phi`` is the elementary weight vector (products of
``A @ Phi(child)`` over the children of the root) and ``gamma`` the tree's density.
These conditions are generated here for any order, so a tableau verifies its own order
numerically instead of trusting a typed-in label.
"""

from __future__ import annotations

from fractions import Fraction
from functools import cache

import numpy as np
import torch

from .errors import TableauError

_DEFAULT_TOL = 1e-10
_MAX_AUTO_ORDER = 12


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
                gamma = n
                for child in forest:
                    gamma *= self.gamma[child]
                self.order.append(n)
                self.children.append(forest)
                self.gamma.append(gamma)
                ids.append(len(self.order) - 1)
            self.by_order[n] = ids
            n += 1


_TREES = _RootedTrees()


class ButcherTableau:
    """A Runge-Kutta Butcher tableau (notes §6.3.1) that checks itself.

    Args:
        A: (s, s) stage coefficients ``a_ij``.
        b: (s,) weights of the propagating solution.
        c: (s,) nodes; must equal the row sums of ``A``. Computed from ``A`` when omitted.
        b_err: (s,) weights of the embedded solution of an adaptive pair (notes eq. 6.44b);
            the local error estimate is ``dt * sum_i (b_i - b_err_i) K_i``.
        order: the claimed order. It is verified against the rooted-tree conditions and a
            :class:`TableauError` is raised if it does not hold. When omitted, the order is
            found numerically (up to ``s`` for explicit tableaus, ``2 s`` for implicit ones).
        name: a label used in messages and tables.
        tol: absolute tolerance on each order condition.

    Raises:
        TableauError: non-square ``A``, inconsistent lengths, non-finite entries,
            ``c_i != sum_j a_ij``, or a claimed order that the conditions refute.
    """

    def __init__(self, A, b, c=None, b_err=None, order=None, name=None, tol=_DEFAULT_TOL):
        self.name = name or "custom"
        self.tol = float(tol)
        self.A = self._as_array(A, "A", ndim=2)
        s = self.A.shape[0]
        if self.A.shape != (s, s) or s == 0:
            raise TableauError(
                f"tableau {self.name!r}: A must be a non-empty square matrix, got shape "
                f"{self.A.shape}."
            )
        self.b = self._as_array(b, "b", ndim=1, length=s)
        row_sums = self.A.sum(axis=1)
        self.c = row_sums.copy() if c is None else self._as_array(c, "c", ndim=1, length=s)
        mismatch = np.abs(self.c - row_sums)
        if np.any(mismatch > 1e-12 * max(1.0, np.abs(self.A).max())):
            i = int(np.argmax(mismatch))
            raise TableauError(
                f"tableau {self.name!r}: c[{i}] = {self.c[i]!r} but row {i} of A sums to "
                f"{row_sums[i]!r}; the nodes must satisfy c_i = sum_j a_ij."
            )
        self.b_err = None if b_err is None else self._as_array(b_err, "b_err", ndim=1, length=s)
        for arr in (self.A, self.b, self.c) + (() if self.b_err is None else (self.b_err,)):
            arr.setflags(write=False)
        self._tensor_cache: dict = {}
        limit = s if self.is_explicit else 2 * s
        self._order = self._find_order(self.b, min(limit, _MAX_AUTO_ORDER))
        if order is not None:
            if not self.satisfies_order(int(order)):
                worst = max(
                    (abs(r) for p in range(1, int(order) + 1) for r in self.order_residuals(p)),
                    default=0.0,
                )
                raise TableauError(
                    f"tableau {self.name!r} claims order {order} but its order conditions hold "
                    f"only up to order {self._order} (largest residual {worst:.2e}). Check the "
                    "coefficients, or pass order=None to have the order computed."
                )
            self._order = int(order)

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

    # ----------------------------------------------------------------- structure
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
        """The order of the embedded weights ``b_err``, or None for a single method."""
        if self.b_err is None:
            return None
        return self._find_order(self.b_err, self.stages if self.is_explicit else 2 * self.stages)

    @property
    def error_weights(self) -> np.ndarray | None:
        """``b - b_err``: the weights of the local error estimate (notes eq. 6.44)."""
        return None if self.b_err is None else self.b - self.b_err

    # ---------------------------------------------------------- order conditions
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
        """True when all order conditions up to order ``p`` hold within ``tol``."""
        return all(
            np.all(np.abs(self.order_residuals(q, weights)) <= self.tol) for q in range(1, p + 1)
        )

    def _find_order(self, weights, limit: int) -> int:
        order = 0
        for p in range(1, limit + 1):
            if not np.all(np.abs(self.order_residuals(p, weights)) <= self.tol):
                break
            order = p
        return order

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
        out = np.empty(flat.size, dtype=np.complex128)
        dets = np.abs(np.linalg.det(mats))
        ok = dets > 1e-300
        if np.any(ok):
            w = np.linalg.solve(mats[ok], ones[ok])[..., 0]
            out[ok] = 1.0 + flat[ok] * (w @ self.b)
        out[~ok] = np.inf
        return out.reshape(z.shape)

    def stability_at_infinity(self) -> float:
        """lim R(z) for |z| -> inf: ``1 - b^T A^{-1} 1`` (0 for L-stable Radau IIA).

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

            def conv(arr):
                return None if arr is None else torch.tensor(arr, dtype=dtype, device=device)

            self._tensor_cache[key] = (
                conv(self.A),
                conv(self.b),
                conv(self.c),
                conv(self.error_weights),
            )
        return self._tensor_cache[key]

    def __repr__(self) -> str:
        kind = "explicit" if self.is_explicit else "implicit"
        emb = "" if self.b_err is None else f", embedded order {self.embedded_order}"
        return (
            f"ButcherTableau({self.name!r}, {kind}, stages={self.stages}, order={self.order}{emb})"
        )


def _fr(x) -> float:
    return float(Fraction(x))


def _lower(rows) -> list[list[float]]:
    """Full A from the strictly lower rows of an explicit tableau (row i has i entries)."""
    s = len(rows)
    A = [[0.0] * s for _ in range(s)]
    for i, row in enumerate(rows):
        for j, value in enumerate(row):
            A[i][j] = _fr(value)
    return A


def _catalogue() -> dict[str, dict]:
    dopri_rows = [
        [],
        ["1/5"],
        ["3/40", "9/40"],
        ["44/45", "-56/15", "32/9"],
        ["19372/6561", "-25360/2187", "64448/6561", "-212/729"],
        ["9017/3168", "-355/33", "46732/5247", "49/176", "-5103/18656"],
        ["35/384", "0", "500/1113", "125/192", "-2187/6784", "11/84"],
    ]
    dopri_b = ["35/384", "0", "500/1113", "125/192", "-2187/6784", "11/84", "0"]
    dopri_b_err = [
        "5179/57600",
        "0",
        "7571/16695",
        "393/640",
        "-92097/339200",
        "187/2100",
        "1/40",
    ]
    return {
        "euler": dict(A=[[0.0]], b=[1.0], order=1),
        "midpoint": dict(A=_lower([[], ["1/2"]]), b=[0.0, 1.0], order=2),
        "heun": dict(A=_lower([[], ["1"]]), b=[0.5, 0.5], order=2),
        "ralston": dict(A=_lower([[], ["2/3"]]), b=[0.25, 0.75], order=2),
        "kutta3": dict(
            A=_lower([[], ["1/2"], ["-1", "2"]]), b=[_fr("1/6"), _fr("2/3"), _fr("1/6")], order=3
        ),
        "rk4": dict(
            A=_lower([[], ["1/2"], ["0", "1/2"], ["0", "0", "1"]]),
            b=[_fr("1/6"), _fr("1/3"), _fr("1/3"), _fr("1/6")],
            order=4,
        ),
        "rk38": dict(
            A=_lower([[], ["1/3"], ["-1/3", "1"], ["1", "-1", "1"]]),
            b=[0.125, 0.375, 0.375, 0.125],
            order=4,
        ),
        "dopri5": dict(
            A=_lower(dopri_rows),
            b=[_fr(v) for v in dopri_b],
            b_err=[_fr(v) for v in dopri_b_err],
            order=5,
        ),
        "implicit_euler": dict(A=[[1.0]], b=[1.0], order=1),
        "implicit_midpoint": dict(A=[[0.5]], b=[1.0], order=2),
    }


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
