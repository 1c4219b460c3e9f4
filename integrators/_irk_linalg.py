"""Linear algebra of the implicit Runge-Kutta stage equations.

For stage unknowns ``W_i = (K_i, Z_i)`` (stage derivatives and algebraic stages, ``p = n + m``
entries each) and a residual linearised as ``dR_i = E dW_i + dt sum_j a_ij G dW_j`` (with
``E = [dR/dK, dR/dZ]`` and ``G = [dR/dX, 0]`` frozen at one point, notes eq. 7.16, 7.58), the
simplified-Newton matrix is

    J = I_s (x) E + dt A (x) G                                           (s p x s p).

Two ways to solve ``J dW = -R``:

- ``"full"``: one LU of the ``s p x s p`` matrix (any tableau).
- ``"transformed"`` (Hairer-Wanner's trick, for invertible, diagonalisable ``A``: Radau IIA,
  Gauss-Legendre, implicit Euler/midpoint): with ``A^{-1} = V Lambda V^{-1}``,
  ``(V^{-1} (x) I) ((dt A)^{-1} (x) I) J (V (x) I) = blockdiag(lambda_j / dt E + G)``, so one
  real ``p x p`` LU per real eigenvalue and one complex ``p x p`` LU per conjugate pair replace
  the big factorisation. Conjugate pairs share one solve (the partner is its conjugate).
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
        if transform is not None:
            cdtype = torch.complex128 if dtype == torch.float64 else torch.complex64
            lam_r, lam_c, P_r, P_c, V_r, V_c = transform

            def real(a):
                return torch.as_tensor(a, dtype=dtype, device=device)

            def cplx(a):
                return torch.as_tensor(a, dtype=cdtype, device=device)

            self.lam_r, self.P_r, self.V_r = real(lam_r), real(P_r), real(V_r)
            self.lam_c, self.P_c, self.V_c = cplx(lam_c), cplx(P_c), cplx(2.0 * V_c)
            self.cdtype = cdtype

    @property
    def real_eigenvalue(self) -> float | None:
        """The first real eigenvalue of ``A^{-1}`` (used by the Radau IIA error filter)."""
        if self.mode != "transformed" or self.lam_r.numel() == 0:
            return None
        return float(self.lam_r[0])

    def factorize(self, E: torch.Tensor, G: torch.Tensor, h: torch.Tensor):
        """LU factors of the iteration matrix.

        Args:
            E, G: (*batch, p, p) frozen derivative blocks.
            h: (*batch,) step sizes.

        Returns:
            (factors, singular) with ``singular`` a (*batch,) bool mask of failed factorisations.
        """
        hb = h[..., None, None, None]
        if self.mode == "full":
            s, p = self.s, E.shape[-1]
            eye = torch.eye(s, dtype=E.dtype, device=E.device)
            big = _kron(eye, E) + hb[..., 0] * _kron(self.A, G)
            lu, piv, info = torch.linalg.lu_factor_ex(big.reshape(*E.shape[:-2], s * p, s * p))
            return ("full", lu, piv), info != 0
        singular = torch.zeros(E.shape[:-2], dtype=torch.bool, device=E.device)
        factors = ["transformed"]
        if self.lam_r.numel():
            mats = (self.lam_r[:, None, None] / hb) * E[..., None, :, :] + G[..., None, :, :]
            fac, sing = _factor_blocks(mats)
            factors += list(fac)
            singular |= sing.any(-1)
        else:
            factors += [None, None, None]
        if self.lam_c.numel():
            Ec, Gc = E.to(self.cdtype)[..., None, :, :], G.to(self.cdtype)[..., None, :, :]
            mats = (self.lam_c[:, None, None] / hb.to(self.cdtype)) * Ec + Gc
            fac, sing = _factor_blocks(mats)
            factors += list(fac)
            singular |= sing.any(-1)
        else:
            factors += [None, None, None]
        return tuple(factors), singular

    def solve(self, factors, R: torch.Tensor, h: torch.Tensor) -> torch.Tensor:
        """The Newton increment ``dW = -J^{-1} R``.

        Args:
            factors: from :meth:`factorize`.
            R: (*batch, s, p) stage residuals.
            h: (*batch,) step sizes.

        Returns:
            (*batch, s, p) increments.
        """
        if factors[0] == "full":
            _, lu, piv = factors
            flat = R.reshape(*R.shape[:-2], -1, 1)
            return -torch.linalg.lu_solve(lu, piv, flat).reshape(R.shape)
        fac_r, fac_c = factors[1:4], factors[4:7]
        inv_h = (1.0 / h)[..., None, None]
        out = torch.zeros_like(R)
        if fac_r[0] is not None:
            rhs = -inv_h * (self.P_r @ R)
            out = out + (self.V_r @ _solve_blocks(fac_r, rhs))
        if fac_c[0] is not None:
            Rc = R.to(self.cdtype)
            rhs = -inv_h.to(self.cdtype) * (self.P_c @ Rc)
            out = out + (self.V_c @ _solve_blocks(fac_c, rhs)).real
        return out

    def solve_real_block(self, factors, rhs: torch.Tensor) -> torch.Tensor:
        """Solve ``(lambda_r / h E + G) y = rhs`` with the first real block: (*batch, p)."""
        return _solve_blocks(factors[1:4], rhs[..., None, :])[..., 0, :]


_SMALL = 8  # blocks up to this size are inverted by vectorised Gauss-Jordan in big batches
_BIG_BATCH = 32


def _factor_blocks(mats: torch.Tensor):
    """Factor (*batch, q, p, p) blocks: ``("lu", LU, pivots)`` or ``("inv", inverse, None)``.

    LAPACK's batched LU runs one small factorisation after another; for many tiny blocks a
    Gauss-Jordan inverse vectorised over the batch (p steps of whole-batch tensor ops) is much
    faster, and applying it is a batched matmul.

    Returns:
        (factors, singular) with ``singular`` of shape (*batch, q).
    """
    p = mats.shape[-1]
    if p <= _SMALL and mats[..., 0, 0].numel() >= _BIG_BATCH:
        inv, singular = _gauss_jordan_inverse(mats)
        return ("inv", inv, None), singular
    lu, piv, info = torch.linalg.lu_factor_ex(mats)
    return ("lu", lu, piv), info != 0


def _solve_blocks(factors, rhs: torch.Tensor) -> torch.Tensor:
    """Solve with factors from :func:`_factor_blocks`; rhs (*batch, q, p)."""
    kind, a, b = factors
    if kind == "inv":
        return (a @ rhs[..., None])[..., 0]
    return torch.linalg.lu_solve(a, b, rhs[..., None])[..., 0]


def _gauss_jordan_inverse(mats: torch.Tensor):
    """Inverse of (..., p, p) matrices by Gauss-Jordan with partial pivoting, vectorised.

    Returns:
        (inverse, singular) with ``singular`` (...,) true where a pivot was exactly zero.
    """
    p = mats.shape[-1]
    eye = torch.eye(p, dtype=mats.dtype, device=mats.device)
    aug = torch.cat([mats, eye.expand_as(mats)], dim=-1)  # (..., p, 2p)
    rows = torch.arange(p, device=mats.device)
    singular = torch.zeros(mats.shape[:-2], dtype=torch.bool, device=mats.device)
    for k in range(p):
        piv = aug[..., k:, k].abs().argmax(-1) + k  # (...)
        perm = torch.where(rows == k, piv[..., None], torch.where(rows == piv[..., None], k, rows))
        aug = torch.gather(aug, -2, perm[..., None].expand_as(aug))
        pivot = aug[..., k, k]
        zero = pivot == 0
        singular |= zero
        row = aug[..., k, :] / torch.where(zero, torch.ones_like(pivot), pivot)[..., None]
        factor = aug[..., :, k]
        updated = aug - factor[..., :, None] * row[..., None, :]
        aug = torch.where((rows == k)[:, None], row[..., None, :], updated)
    return aug[..., p:], singular


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
    r = len(real_idx)
    lam_r = lam[real_idx].real
    lam_c = lam[pos_idx]
    P_r = P[:r].real
    P_c = P[r::2] if pos_idx else np.zeros((0, s), dtype=np.complex128)
    V_r = V[:, :r].real
    V_c = V[:, r::2] if pos_idx else np.zeros((s, 0), dtype=np.complex128)
    return lam_r, lam_c, P_r, P_c, V_r, V_c
