"""A Jacobian made of dense row blocks, each touching a few columns (multiple shooting).

The residuals of a multiple-shooting fit (the course notes (Modelling and Simulation), the
Gauss-Newton method of §3.5 on segments with free initial states) have a Jacobian whose rows
of segment ``j`` depend only on the parameters and on node ``j`` (its continuity defect also
on node ``j + 1``): with ``S`` segments of ``nx`` states almost all of the ``S nx`` node
columns of a row are zero. Stored dense, forming ``J' J`` costs ``m n^2`` per iteration and
the Jacobian ``m n`` memory, both growing with the square of the segment count; stored as
blocks, both are linear in the record length.

A :class:`BlockJacobian` is a list of groups; a group is ``values`` (*batch, B, R, k), B
blocks of R rows over k columns each, with ``columns`` (B, k) giving the column of each of a
block's k entries (-1: a quantity that is not free, dropped). Stacking the groups' rows in
order gives the *padded* rows; ``rows`` (m,) picks the Jacobian's rows among them (padded
rows that are no residual hold zeros).
"""

from __future__ import annotations

import torch

__all__ = ["BlockJacobian"]


class BlockJacobian:
    """A (*batch, m, n) Jacobian stored as dense row blocks (see the module docstring).

    Args:
        groups: ``[(values, columns), ...]``, ``values`` (*batch, B, R, k) and ``columns``
            (B, k) int64 (-1 for no column); every group has the same batch shape.
        n: the number of columns.
        rows: (m,) int64 indices of the residual rows among the stacked padded rows (None:
            all of them).
    """

    def __init__(self, groups, n: int, rows: torch.Tensor | None = None):
        self.groups = [(v, c.to(v.device)) for v, c in groups]
        self.n = int(n)
        values = self.groups[0][0]
        self.batch = values.shape[:-3]
        self.dtype, self.device = values.dtype, values.device
        self.n_padded = sum(v.shape[-3] * v.shape[-2] for v, _ in self.groups)
        self.rows = (
            torch.arange(self.n_padded, device=self.device)
            if rows is None
            else rows.to(self.device)
        )

    @property
    def shape(self) -> torch.Size:
        return torch.Size((*self.batch, self.rows.shape[0], self.n))

    def _padded(self, v: torch.Tensor) -> torch.Tensor:
        """(*batch, m) row values placed in the padded rows (zeros elsewhere)."""
        out = v.new_zeros(*v.shape[:-1], self.n_padded)
        out[..., self.rows] = v
        return out

    def _pieces(self, v: torch.Tensor | None):
        """Per group: its values, its columns with -1 sent to the spare column ``n``, and the
        padded row values ``v`` of its rows as (*batch, B, R, 1) (None without ``v``); the
        padded rows that are no residual get zero."""
        padded = None if v is None else self._padded(v)
        start = 0
        for values, columns in self.groups:
            B, R = values.shape[-3:-1]
            piece = None
            if padded is not None:
                piece = padded[..., start : start + B * R].unflatten(-1, (B, R, 1))
            start += B * R
            yield values, torch.where(columns < 0, self.n, columns), piece

    def normal(self, weights: torch.Tensor | None = None) -> torch.Tensor:
        """``J' diag(weights) J``: (*batch, n, n); ``weights`` (*batch, m) or None (ones)."""
        n1 = self.n + 1
        if weights is None:  # ones on the residual rows, zeros on the other padded rows
            weights = torch.ones(self.rows.shape[0], dtype=self.dtype, device=self.device)
        H = torch.zeros(*self.batch, n1 * n1, dtype=self.dtype, device=self.device)
        for values, columns, w in self._pieces(weights):
            G = values.transpose(-1, -2) @ (values * w)  # (*batch, B, k, k)
            index = (columns[:, :, None] * n1 + columns[:, None, :]).reshape(-1)
            H.index_add_(-1, index, G.flatten(-3))
        return H.unflatten(-1, (n1, n1))[..., : self.n, : self.n]

    def rmatvec(self, v: torch.Tensor) -> torch.Tensor:
        """``J' v``: (*batch, n) for ``v`` (*batch, m)."""
        g = torch.zeros(*self.batch, self.n + 1, dtype=self.dtype, device=self.device)
        for values, columns, piece in self._pieces(v):
            contribution = (values * piece).sum(-2)  # (*batch, B, k)
            g.index_add_(-1, columns.reshape(-1), contribution.flatten(-2))
        return g[..., : self.n]

    def dense(self) -> torch.Tensor:
        """The (*batch, m, n) dense Jacobian."""
        parts = []
        for values, columns, _ in self._pieces(None):
            B, R, k = values.shape[-3:]
            block = values.new_zeros(*self.batch, B, R, self.n + 1)
            block.scatter_add_(-1, columns[:, None, :].expand(*self.batch, B, R, k), values)
            parts.append(block.flatten(-3, -2))
        return torch.cat(parts, -2)[..., self.rows, : self.n]

    def where(self, keep: torch.Tensor, other: BlockJacobian) -> BlockJacobian:
        """This Jacobian for the batch members where ``keep`` (*batch,) holds, ``other``'s for
        the rest (the same structure)."""
        mask = keep[..., None, None, None]
        pairs = zip(self.groups, other.groups, strict=True)
        groups = [(torch.where(mask, a, b), c) for (a, c), (b, _) in pairs]
        return BlockJacobian(groups, self.n, self.rows)
