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

Given the *chain* of node columns (segment ``j``'s states in row ``j``), :meth:`normal`
returns ``J' C J`` as a
:class:`~integrators.block_tridiagonal.BorderedBlockTridiagonal`, whose damped solves cost
linear time in the segment count too; without it, the dense matrix.
"""

from __future__ import annotations

import torch

from .block_tridiagonal import BorderedBlockTridiagonal
from .errors import InputValidationError

__all__ = ["BlockJacobian"]


class BlockJacobian:
    """A (*batch, m, n) Jacobian stored as dense row blocks (see the module docstring).

    Args:
        groups: ``[(values, columns), ...]``, ``values`` (*batch, B, R, k) and ``columns``
            (B, k) int64 (-1 for no column); every group has the same batch shape.
        n: the number of columns.
        rows: (m,) int64 indices of the residual rows among the stacked padded rows (None:
            all of them).
        chain: (C, b) int64 or None: columns ordered as a chain of ``C`` blocks of ``b``
            (-1: no column) such that every row block touches, besides columns outside the
            chain (the *border*), the columns of at most two consecutive chain blocks; then
            :meth:`normal` returns a
            :class:`~integrators.block_tridiagonal.BorderedBlockTridiagonal`.

    Raises:
        InputValidationError: a row block touching chain blocks that are not consecutive.
    """

    def __init__(self, groups, n: int, rows: torch.Tensor | None = None, chain=None):
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
        self.chain = None if chain is None else chain.to(self.device)
        self._layout = None if chain is None else self._structured_layout()

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

    def _structured_layout(self):
        """``(targets, border_columns, offsets)``: per group (B, k, k), where each entry of a
        block's ``values' values`` goes in the flat storage of a
        :class:`BorderedBlockTridiagonal` (border ``A``, coupling ``E``, diagonal and upper
        chain blocks, then one slot for the entries that are dropped: missing columns and
        the mirrored halves of the symmetric matrix); the (nb,) columns outside the chain;
        ``(nb, C, b, off_E, off_D, off_U, dropped)``, the offsets of ``E``, the diagonal and
        the upper blocks and the slot of the dropped entries in that storage."""
        C, b = self.chain.shape
        dev = self.device
        flat = self.chain.reshape(-1)
        present = flat[flat >= 0]
        in_chain = torch.zeros(self.n, dtype=torch.bool, device=dev)
        in_chain[present] = True
        border_columns = torch.nonzero(~in_chain).squeeze(-1)
        nb = border_columns.shape[0]
        block = torch.full((self.n + 1,), -1, dtype=torch.int64, device=dev)
        slot = torch.zeros(self.n + 1, dtype=torch.int64, device=dev)
        position = torch.arange(C * b, device=dev)
        block[present] = (position // b)[flat >= 0]
        slot[present] = (position % b)[flat >= 0]
        border = torch.full((self.n + 1,), -1, dtype=torch.int64, device=dev)
        border[border_columns] = torch.arange(nb, device=dev)
        off_E = nb * nb
        off_D = off_E + C * b * nb
        off_U = off_D + C * b * b
        dropped = off_U + C * b * b
        targets = []
        for _, c, _ in self._pieces(None):
            c1, c2 = c[:, :, None], c[:, None, :]
            k1, k2 = block[c1], block[c2]
            s1, s2 = slot[c1], slot[c2]
            o1, o2 = border[c1], border[c2]
            chain1, chain2 = k1 >= 0, k2 >= 0
            far = chain1 & chain2 & ((k1 - k2).abs() > 1)
            if bool(far.any()):
                raise InputValidationError(
                    "BlockJacobian: a row block touches chain blocks that are not "
                    "consecutive; the chain must list the columns so that each row block "
                    "meets at most two neighbouring chain blocks."
                )
            target = torch.full(c1.shape[:1] + (c.shape[1], c.shape[1]), dropped, device=dev)
            target = torch.where((o1 >= 0) & (o2 >= 0), o1 * nb + o2, target)
            target = torch.where(chain1 & (o2 >= 0), off_E + (k1 * b + s1) * nb + o2, target)
            target = torch.where(chain1 & (k2 == k1), off_D + (k1 * b + s1) * b + s2, target)
            target = torch.where(
                chain1 & chain2 & (k2 == k1 + 1), off_U + (k1 * b + s1) * b + s2, target
            )
            targets.append(target.reshape(-1))
        return targets, border_columns, (nb, C, b, off_E, off_D, off_U, dropped)

    def normal(self, weights: torch.Tensor | None = None):
        """``J' diag(weights) J``: (*batch, n, n), or a
        :class:`~integrators.block_tridiagonal.BorderedBlockTridiagonal` when the Jacobian
        has a chain; ``weights`` (*batch, m) or None (ones)."""
        n1 = self.n + 1
        if weights is None:  # ones on the residual rows, zeros on the other padded rows
            weights = torch.ones(self.rows.shape[0], dtype=self.dtype, device=self.device)
        if self.chain is None:  # the entries of each block's values' values in H (n1, n1)
            targets = [
                (c[:, :, None] * n1 + c[:, None, :]).reshape(-1) for _, c, _ in self._pieces(None)
            ]
            storage = n1 * n1
        else:
            targets, border_columns, (nb, C, b, off_E, off_D, off_U, dropped) = self._layout
            storage = dropped + 1
        flat = torch.zeros(*self.batch, storage, dtype=self.dtype, device=self.device)
        for (values, _, w), target in zip(self._pieces(weights), targets, strict=True):
            G = values.transpose(-1, -2) @ (values * w)  # (*batch, B, k, k)
            flat.index_add_(-1, target, G.flatten(-3))
        if self.chain is None:
            return flat.unflatten(-1, (n1, n1))[..., : self.n, : self.n]
        return BorderedBlockTridiagonal(
            flat[..., off_D:off_U].unflatten(-1, (C, b, b)),
            flat[..., off_U:dropped].unflatten(-1, (C, b, b)),
            flat[..., off_E:off_D].unflatten(-1, (C, b, nb)),
            flat[..., :off_E].unflatten(-1, (nb, nb)),
            self.chain,
            border_columns,
            self.n,
        )

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
        out = BlockJacobian(groups, self.n, self.rows)  # same columns: the layout carries over
        out.chain, out._layout = self.chain, self._layout
        return out
