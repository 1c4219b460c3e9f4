"""Symmetric matrices that are block tridiagonal with a dense border, and their damped solves.

The normal matrix ``J' C J`` of a multiple-shooting fit (the course notes (Modelling and
Simulation), Gauss-Newton / Levenberg-Marquardt of §3.5, eq. 3.58-3.61, on segments with
free initial states) couples every node state only with the nodes of the neighbouring
segments (through the continuity defects) and with the parameters. Ordered as a *chain* of
``C`` node blocks of ``b`` states followed by the ``nb`` *border* columns (the parameters),

    H = [[D, E],        D: block tridiagonal, blocks D_jj and D_j,j+1 (b x b)
         [E', A]]       E: (C b) x nb, A: nb x nb,

and ``(H + s I) x = g`` is solved by the block Cholesky factorisation of that ordering:
``D + s I = L_D L_D'`` block by block along the chain (``L_D`` block lower bidiagonal), the
Schur complement ``A + s I - W' W`` with ``W = L_D^{-1} E`` factorised densely, then forward
and back substitution. The cost is linear in the chain length, ``C (b^3 + b^2 nb)``, against
``(C b + nb)^3 / 3`` for a dense Cholesky factorisation, and the matrix takes ``C b (2 b + nb)``
numbers instead of ``(C b + nb)^2``.

Chain slots that hold no column (a state that is not estimated) are carried as decoupled
unknowns with a unit diagonal and a zero right-hand side: their solution is zero.
"""

from __future__ import annotations

import torch

__all__ = ["BorderedBlockTridiagonal"]


class BorderedBlockTridiagonal:
    """A symmetric (*batch, n, n) matrix stored as its chain blocks and border.

    Args:
        diagonal_blocks: ``D_jj`` (*batch, C, b, b).
        upper_blocks: ``D_j,j+1`` (*batch, C, b, b); the last block is not used.
        coupling: ``E`` (*batch, C, b, nb), the chain rows of the border columns.
        border: ``A`` (*batch, nb, nb).
        chain: (C, b) int64, the matrix column of each chain slot (-1: none).
        border_columns: (nb,) int64, the matrix columns of the border.
        n: the matrix size; every column is in the chain or the border, once.
    """

    def __init__(self, diagonal_blocks, upper_blocks, coupling, border, chain, border_columns, n):
        self.diagonal_blocks, self.upper_blocks = diagonal_blocks, upper_blocks
        self.coupling, self.border = coupling, border
        self.chain, self.border_columns, self.n = chain, border_columns, int(n)
        self.batch = border.shape[:-2]
        self.present = chain >= 0  # (C, b)

    @property
    def shape(self) -> torch.Size:
        return torch.Size((*self.batch, self.n, self.n))

    def diagonal(self) -> torch.Tensor:
        """The (*batch, n) diagonal in column order."""
        out = self.border.new_zeros(*self.batch, self.n)
        out[..., self.border_columns] = self.border.diagonal(dim1=-2, dim2=-1)
        chain_diagonal = self.diagonal_blocks.diagonal(dim1=-2, dim2=-1)  # (*batch, C, b)
        out[..., self.chain[self.present]] = chain_diagonal[..., self.present]
        return out

    def dense(self) -> torch.Tensor:
        """The (*batch, n, n) matrix."""
        C, b = self.chain.shape
        nb = self.border_columns.shape[0]
        size = C * b + nb
        P = self.border.new_zeros(*self.batch, size, size)  # chain order, then the border
        for j in range(C):
            rows = slice(j * b, (j + 1) * b)
            P[..., rows, rows] = self.diagonal_blocks[..., j, :, :]
            if j + 1 < C:
                nxt = slice((j + 1) * b, (j + 2) * b)
                P[..., rows, nxt] = self.upper_blocks[..., j, :, :]
                P[..., nxt, rows] = self.upper_blocks[..., j, :, :].transpose(-1, -2)
        E = self.coupling.flatten(-3, -2)
        P[..., : C * b, C * b :] = E
        P[..., C * b :, : C * b] = E.transpose(-1, -2)
        P[..., C * b :, C * b :] = self.border
        order = torch.cat([self.chain.reshape(-1), self.border_columns])
        keep = order >= 0
        out = P.new_zeros(*self.batch, self.n, self.n)
        index = order[keep]
        out[..., index[:, None], index[None, :]] = P[..., keep, :][..., :, keep]
        return out

    def where(self, keep: torch.Tensor, other: BorderedBlockTridiagonal):
        """This matrix for the batch members where ``keep`` (*batch,) holds, ``other``'s for
        the rest (the same structure)."""
        k3 = keep[..., None, None, None]
        return BorderedBlockTridiagonal(
            torch.where(k3, self.diagonal_blocks, other.diagonal_blocks),
            torch.where(k3, self.upper_blocks, other.upper_blocks),
            torch.where(k3, self.coupling, other.coupling),
            torch.where(keep[..., None, None], self.border, other.border),
            self.chain,
            self.border_columns,
            self.n,
        )

    def solve(self, g: torch.Tensor, shift: torch.Tensor):
        """``x = (H + shift I)^{-1} g`` by the block Cholesky factorisation (module
        docstring): ``g`` (*batch, n), ``shift`` (*batch,). Returns ``(x, ok)``, ``ok``
        (*batch,) False where ``H + shift I`` is numerically not positive definite (``x``
        is then not usable)."""
        C, b = self.chain.shape
        nb = self.border_columns.shape[0]
        eye_b = torch.eye(b, dtype=g.dtype, device=g.device)
        # absent chain slots: a unit diagonal, decoupled, zero right-hand side
        absent = (~self.present).to(g.dtype)  # (C, b)
        present = self.present.to(g.dtype)
        D = (
            self.diagonal_blocks
            + torch.diag_embed(absent)
            + (shift[..., None, None, None] * eye_b * present[:, :, None])
        )
        g_chain = g[..., self.chain.clamp_min(0)] * present  # (*batch, C, b)
        g_border = g[..., self.border_columns]
        # factorise along the chain, carrying L_D^{-1} [E | g_chain]
        rhs = torch.cat([self.coupling, g_chain[..., None]], -1)  # (*batch, C, b, nb + 1)
        ok = torch.ones(self.batch, dtype=torch.bool, device=g.device)
        diag_factors, sub_factors, forward = [], [], []
        sub = carried = None
        for j in range(C):
            M = D[..., j, :, :]
            r = rhs[..., j, :, :]
            if sub is not None:
                M = M - sub @ sub.transpose(-1, -2)
                r = r - sub @ carried
            L, info = torch.linalg.cholesky_ex(M)
            ok &= info == 0
            carried = torch.linalg.solve_triangular(L, r, upper=False)
            diag_factors.append(L)
            forward.append(carried)
            if j + 1 < C:  # L_{j+1,j} = (L_jj^{-1} D_j,j+1)'
                upper = self.upper_blocks[..., j, :, :]
                sub = torch.linalg.solve_triangular(L, upper, upper=False).transpose(-1, -2)
                sub_factors.append(sub)
        Y = torch.stack(forward, -3)  # (*batch, C, b, nb + 1): [W | y_chain]
        W, y_chain = Y[..., :nb].flatten(-3, -2), Y[..., nb].flatten(-2)
        eye_n = torch.eye(nb, dtype=g.dtype, device=g.device)
        schur = self.border + shift[..., None, None] * eye_n - W.transpose(-1, -2) @ W
        L_S, info = torch.linalg.cholesky_ex(schur)
        ok &= info == 0
        rhs_border = (g_border - (W.transpose(-1, -2) @ y_chain[..., None])[..., 0])[..., None]
        x_border = torch.cholesky_solve(rhs_border, L_S)[..., 0]  # (*batch, nb)
        residual = (y_chain - (W @ x_border[..., None])[..., 0]).unflatten(-1, (C, b))
        x_chain = [None] * C
        below = None
        for j in range(C - 1, -1, -1):  # back substitution with L_D'
            r = residual[..., j, :, None]
            if below is not None:
                r = r - sub_factors[j].transpose(-1, -2) @ below
            below = torch.linalg.solve_triangular(diag_factors[j].transpose(-1, -2), r, upper=True)
            x_chain[j] = below[..., 0]
        x_chain = torch.stack(x_chain, -2)  # (*batch, C, b)
        x = g.new_zeros(*self.batch, self.n)
        x[..., self.border_columns] = x_border
        x[..., self.chain[self.present]] = x_chain[..., self.present]
        return x, ok
