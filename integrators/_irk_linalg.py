"""Linear algebra of the implicit Runge-Kutta stage equations.

For stage unknowns ``W_i = (K_i, Z_i)`` (stage derivatives and algebraic stages, ``p = n + m``
entries each) and a residual linearised as ``dR_i = E dW_i + dt sum_j a_ij G dW_j`` (with
``E = [dR/dK, dR/dZ]`` and ``G = [dR/dX, 0]`` frozen at one point, notes eq. 7.16, 7.58), the
simplified-Newton matrix is

    J = I_s (x) E + dt A (x) G                                           (s p x s p).

Two ways to solve ``J dW = -R``:

- ``"full"``: one LU of the ``s p x s p`` matrix (any tableau), plus one of the real block
  ``gamma / dt E + G`` when the Radau IIA error filter asks for it (``want_real_block``).
- ``"transformed"`` (Hairer-Wanner's trick, for invertible, diagonalisable ``A``: Radau IIA,
  Gauss-Legendre, implicit Euler/midpoint): with ``A^{-1} = V Lambda V^{-1}``,
  ``(V^{-1} (x) I) ((dt A)^{-1} (x) I) J (V (x) I) = blockdiag(lambda_j / dt E + G)``, so one
  real ``p x p`` LU per real eigenvalue and one complex ``p x p`` LU per conjugate pair replace
  the big factorisation. Conjugate pairs share one solve (the partner is its conjugate).

For small systems (``s p <= 24``, e.g. Radau IIA s = 3 up to p = 8) neither is used in the
Newton iterations: ``J`` is inverted once per factorisation (batched LAPACK ``inv_ex``, which
on the CPU beats both the structured path and a vectorised Gauss-Jordan elimination for every
batch size measured) and every iteration is one batched matrix-vector product
``dW = (-J^{-1}) R`` instead of a chain of small transforms and triangular solves.
"""

from __future__ import annotations

import numpy as np
import torch

_MAX_EIGVEC_COND = 1e8


class StageLinearSolver:
    """Factorises and solves the simplified-Newton system of an implicit tableau.

    Args:
        A: (s, s) numpy Butcher matrix.
        dtype, device: of the tensors to solve with.
        mode: "auto" (transformed when ``A`` is invertible and well diagonalisable, else full),
            "transformed" or "full".
    """

    def __init__(self, A: np.ndarray, dtype, device, mode: str = "auto"):
        self.s = A.shape[0]
        self.dtype, self.device = dtype, device
        self.A = torch.as_tensor(np.array(A), dtype=dtype, device=device)
        transform = _eigen_transform(A) if mode in ("auto", "transformed") else None
        if mode == "transformed" and transform is None:
            raise ValueError("the tableau's A is singular or not diagonalisable")
        self.mode = "full" if transform is None else "transformed"
        # the real block of the Radau IIA error filter, for the full factorisation; A is taken
        # as invertible by its condition number (its determinant, 3e-17 for Radau IIA s = 13,
        # shrinks with s however well conditioned A is)
        invertible = self.mode == "full" and np.linalg.cond(np.array(A, dtype=np.float64)) < 1e12
        self._full_gamma = real_eigenvalue_of_inverse(A) if invertible else None
        # the first real eigenvalue of A^{-1} in float64 (used by the Radau IIA error filter),
        # None without a real eigenvalue or outside the transformed mode
        self.real_eigenvalue = None
        if transform is not None:
            cdtype = torch.complex128 if dtype == torch.float64 else torch.complex64
            lam_r, lam_c, P_r, P_c, V_r, V_c = transform
            self.lam_r, self.P_r, self.V_r = (
                torch.as_tensor(a, dtype=dtype, device=device) for a in (lam_r, P_r, V_r)
            )
            self.lam_c, self.P_c, self.V_c = (
                torch.as_tensor(a, dtype=cdtype, device=device) for a in (lam_c, P_c, 2.0 * V_c)
            )
            self.real_eigenvalue = float(lam_r[0]) if len(lam_r) else None
        self.want_real_block = False  # set when the error filter solves with the real block
        self._eyes: dict = {}

    def factorize(self, E: torch.Tensor, G: torch.Tensor, h: torch.Tensor, parts=None):
        """LU factors of the iteration matrix.

        Args:
            E, G: (*batch, p, p) frozen derivative blocks.
            h: (*batch,) step sizes.
            parts: :meth:`prepare` of ``E, G`` when already computed.

        Returns:
            (factors, singular) with ``singular`` a (*batch,) bool mask of failed factorisations.
        """
        hb = h[..., None, None, None]
        if self.mode == "full":
            eye = torch.eye(self.s, dtype=E.dtype, device=E.device)
            big = _kron(eye, E) + hb[..., 0] * _kron(self.A, G)  # (*batch, s p, s p)
            lu, piv, info = torch.linalg.lu_factor_ex(big)
            singular = info != 0
            real_lu = real_piv = None
            if self.want_real_block:
                gamma = self._full_gamma
                real_lu, real_piv, info_r = torch.linalg.lu_factor_ex((gamma / hb[..., 0]) * E + G)
                singular = singular | (info_r != 0)
            return ("full", lu, piv, real_lu, real_piv), singular
        if self.dense(E.shape[-1]):
            return self._factorize_dense(E, G, h, self.prepare(E, G) if parts is None else parts)
        # ("transformed", LU, pivots of the real blocks, LU, pivots of the complex blocks), None
        # for a group without eigenvalues; every block (*batch, q, p, p) is lambda_j / h E + G
        singular = torch.zeros(E.shape[:-2], dtype=torch.bool, device=E.device)
        factors = ["transformed"]
        for lam in (self.lam_r, self.lam_c):
            lu = piv = None
            if lam.numel():
                Eq, Gq, hq = (_cast(a, lam.dtype) for a in (E, G, hb))
                mats = (lam[:, None, None] / hq) * Eq[..., None, :, :] + Gq[..., None, :, :]
                lu, piv, info = torch.linalg.lu_factor_ex(mats)
                singular |= (info != 0).any(-1)
            factors += [lu, piv]
        return tuple(factors), singular

    def dense(self, p: int) -> bool:
        """Whether systems with ``p`` unknowns per stage take the explicit-inverse path."""
        return self.mode == "transformed" and self.s * p <= _DENSE_MAX

    def prepare(self, E: torch.Tensor | None, G: torch.Tensor):
        """The step-size independent parts ``(I (x) E or None, A (x) G)`` of ``J``, computed
        once per Jacobian for the explicit-inverse path; ``E`` None means the identity.
        Returns None for the other paths."""
        if not self.dense(G.shape[-1]):
            return None
        return (None if E is None else self._kron_dense("eye", E)), self._kron_dense("A", G)

    def _kron_dense(self, which: str, b: torch.Tensor) -> torch.Tensor:
        """``_kron(a, b)`` for ``a`` the identity ("eye") or ``A`` ("A") and small blocks ``b``
        (*batch, p, p), as one matrix product ``b.flatten(-2) @ P`` with the constant
        ``P = a (x) [unit p x p matrices]`` (p^2, (s p)^2): every column of ``P`` has one
        nonzero, so the entries are the exact products, and on the CPU one small GEMM beats
        the five-dimensional broadcast product several times over."""
        p, s = b.shape[-1], self.s
        key = (which, p, b.dtype, b.device)
        if key not in self._eyes:
            a = torch.eye(s, dtype=b.dtype, device=b.device) if which == "eye" else self.A
            units = torch.eye(p * p, dtype=b.dtype, device=b.device).reshape(p * p, p, p)
            self._eyes[key] = _kron(a.to(b.dtype), units).reshape(p * p, -1)
        P = self._eyes[key]
        return (b.reshape(*b.shape[:-2], p * p) @ P).reshape(*b.shape[:-2], s * p, s * p)

    def _factorize_dense(self, E, G, h, parts):
        """``("dense", -J^{-1} (*batch, s p, s p), (lambda_r / h E + G)^{-1} or None)``; the
        real block's inverse (error filter of Radau IIA) only when ``want_real_block``."""
        IE, AG = parts
        hb = h[..., None, None]
        inverse, info = torch.linalg.inv_ex(
            torch.addcmul(self._eye(AG) if IE is None else IE, AG, hb)
        )
        real_inv = None
        if self.want_real_block and self.lam_r.numel():
            real_inv = self._real_block_inverse(inverse, h)
        return ("dense", inverse.neg(), real_inv), info != 0

    def _real_block_inverse(self, inverse: torch.Tensor, h: torch.Tensor) -> torch.Tensor:
        """``(lambda_r / h E + G)^{-1}`` (*batch, p, p) read off ``J^{-1}`` (*batch, s p, s p).

        With ``T = V (x) I`` and ``A^{-1} V = V Lambda``,
        ``T^{-1} ((h A)^{-1} (x) I) J T = blockdiag(lambda_j / h E + G)``, so the inverse of
        block ``r`` is ``(h / lambda_r) sum_ij (V^{-1})_ri V_jr (J^{-1})_ij`` over the
        (p, p) blocks of ``J^{-1}``: one product with a constant 0/weight matrix (a singular
        block makes ``J`` singular, which ``inv_ex`` already reports)."""
        sp = inverse.shape[-1]
        p = sp // self.s
        key = ("real_block", p, inverse.dtype, inverse.device)
        if key not in self._eyes:
            v_inv_row = self.P_r[0] @ self.A  # row r of V^{-1} = P A
            weights = torch.outer(v_inv_row, self.V_r[:, 0]).to(inverse.dtype)  # (s, s)
            eye_p = torch.eye(p, dtype=inverse.dtype, device=inverse.device)
            # M[(i, a, j, b), (a', b')] = w_ij delta_aa' delta_bb'
            M = weights[:, None, :, None, None, None] * (
                eye_p[None, :, None, None, :, None] * eye_p[None, None, None, :, None, :]
            )
            self._eyes[key] = (M.reshape(sp * sp, p * p) / self.real_eigenvalue).contiguous()
        block = inverse.reshape(*inverse.shape[:-2], sp * sp) @ self._eyes[key]
        return block.reshape(*inverse.shape[:-2], p, p) * h[..., None, None]

    def _eye(self, like: torch.Tensor) -> torch.Tensor:
        """Identity of ``like``'s matrix size, dtype and device (cached)."""
        key = (like.shape[-1], like.dtype, like.device)
        if key not in self._eyes:
            self._eyes[key] = torch.eye(key[0], dtype=key[1], device=key[2])
        return self._eyes[key]

    def solve(self, factors, R: torch.Tensor, h: torch.Tensor) -> torch.Tensor:
        """The Newton increment ``dW = -J^{-1} R``.

        Args:
            factors: from :meth:`factorize`.
            R: (*batch, s, p) stage residuals.
            h: (*batch,) step sizes.

        Returns:
            (*batch, s, p) increments.
        """
        if factors[0] == "dense":
            flat = R.reshape(*R.shape[:-2], -1, 1)
            return (factors[1] @ flat).reshape(R.shape)
        if factors[0] == "full":
            flat = R.reshape(*R.shape[:-2], -1, 1)
            return -torch.linalg.lu_solve(factors[1], factors[2], flat).reshape(R.shape)
        inv_h = (1.0 / h)[..., None, None]
        out = torch.zeros_like(R)
        groups = ((self.P_r, self.V_r, *factors[1:3]), (self.P_c, self.V_c, *factors[3:5]))
        for P, V, lu, piv in groups:
            if lu is not None:
                rhs = -_cast(inv_h, P.dtype) * (P @ _cast(R, P.dtype))
                out = out + (V @ _solve_blocks(lu, piv, rhs)).real
        return out

    def solve_real_block(self, factors, rhs: torch.Tensor) -> torch.Tensor:
        """Solve ``(lambda_r / h E + G) y = rhs`` (*batch, p) with the first real block (the
        full factorisation holds that block's own LU when ``want_real_block`` was set):
        (*batch, p)."""
        if factors[0] == "dense":
            return (factors[2] @ rhs[..., None])[..., 0]
        if factors[0] == "full":
            return torch.linalg.lu_solve(factors[3], factors[4], rhs[..., None])[..., 0]
        return _solve_blocks(factors[1], factors[2], rhs[..., None, :])[..., 0, :]


_DENSE_MAX = 24  # s p up to this size: explicit inverse of J, one matmul per Newton iteration


def real_eigenvalue_of_inverse(A) -> float | None:
    """The first real eigenvalue of ``A^{-1}`` (Radau IIA's ``gamma``, the block of its
    embedded error estimate), None where ``A^{-1}`` has none (an even number of stages)."""
    lam = np.linalg.eigvals(np.linalg.inv(np.array(A, dtype=np.float64)))
    real = lam[np.abs(lam.imag) <= 1e-12 * np.abs(lam).max()].real
    return float(real[0]) if len(real) else None


def _solve_blocks(lu, piv, rhs: torch.Tensor) -> torch.Tensor:
    """Solve with the LU factors of (*batch, q, p, p) blocks; rhs (*batch, q, p)."""
    return torch.linalg.lu_solve(lu, piv, rhs[..., None])[..., 0]


def _cast(a: torch.Tensor, dtype) -> torch.Tensor:
    """``a`` in ``dtype`` (the complex blocks' solves); no call when it already is."""
    return a if a.dtype == dtype else a.to(dtype)


def _kron(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Kronecker product of an (s, s) matrix with (*batch, p, p) blocks: (*batch, s, p, s, p)."""
    out = a[:, None, :, None] * b[..., None, :, None, :]
    s, p = a.shape[0], b.shape[-1]
    return out.reshape(*b.shape[:-2], s * p, s * p)


def _eigen_transform(A: np.ndarray):
    """Eigen-decomposition of ``A^{-1}`` arranged in real eigenvalues and conjugate pairs.

    Returns:
        ``(lam_r, lam_c, P_r, P_c, V_r, V_c)`` such that for real ``R``
        ``(A^{-1} R) = V_r diag(lam_r) P_r R + 2 Re(V_c diag(lam_c) P_c R)``, where the rows of
        ``P = V^{-1} A^{-1}`` are split like the eigenvalues, or None when ``A`` is singular or
        its eigenvector matrix is ill-conditioned.
    """
    s = A.shape[0]
    if abs(np.linalg.det(A)) < 1e-14:
        return None
    Ainv = np.linalg.inv(A)
    lam, vec = np.linalg.eig(Ainv)
    scale = max(1.0, np.abs(lam).max())
    real_idx = [i for i in range(s) if abs(lam[i].imag) <= 1e-12 * scale]
    pos_idx = [i for i in range(s) if lam[i].imag > 1e-12 * scale]
    if len(real_idx) + 2 * len(pos_idx) != s:
        return None
    cols = [vec[:, i].real for i in real_idx]
    for i in pos_idx:
        cols += [vec[:, i], vec[:, i].conj()]
    V = np.stack(cols, axis=1).astype(np.complex128)
    if np.linalg.cond(V) > _MAX_EIGVEC_COND:
        return None
    P = np.linalg.inv(V) @ Ainv
    r = len(real_idx)  # one column / row per conjugate pair (P[r::2] is empty without pairs)
    return lam[real_idx].real, lam[pos_idx], P[:r].real, P[r::2], V[:, :r].real, V[:, r::2]
