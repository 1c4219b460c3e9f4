"""The block-sparse Jacobian of multiple shooting against its dense form, and the minimiser
run with it against the same minimiser run with the dense Jacobian."""

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from integrators.block_jacobian import BlockJacobian
from integrators.errors import InputValidationError
from integrators.newton import minimize

F64 = torch.float64


def _random_blocks(seed: int, batch=(3,), n=7):
    """Two groups of blocks whose columns repeat within the group, include -1 (no column),
    and padded rows that are no residual but hold nonzero values (they must not count)."""
    g = torch.Generator().manual_seed(seed)
    groups = []
    for B, R, k in ((4, 5, 3), (3, 2, 4)):
        values = torch.randn(*batch, B, R, k, generator=g, dtype=F64)
        columns = torch.randint(-1, n, (B, k), generator=g)
        groups.append((values, columns))
    n_padded = 4 * 5 + 3 * 2
    rows = torch.sort(torch.randperm(n_padded, generator=g)[: n_padded - 5]).values
    return BlockJacobian(groups, n, rows), groups, rows


def _dense_reference(groups, rows, n):
    """The dense Jacobian assembled entry by entry (the definition)."""
    batch = groups[0][0].shape[:-3]
    padded = []
    for values, columns in groups:
        B, R, k = values.shape[-3:]
        for b in range(B):
            block = torch.zeros(*batch, R, n, dtype=F64)
            for i in range(k):
                if columns[b, i] >= 0:
                    block[..., columns[b, i]] += values[..., b, :, i]
            padded.append(block)
    return torch.cat(padded, -2)[..., rows, :]


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 10_000))
def test_block_products_equal_the_dense_ones(seed):
    J, groups, rows = _random_blocks(seed)
    D = _dense_reference(groups, rows, J.n)
    torch.testing.assert_close(J.dense(), D, rtol=0, atol=0)
    assert J.shape == D.shape
    g = torch.Generator().manual_seed(seed + 1)
    w = torch.rand(*D.shape[:-1], generator=g, dtype=F64)
    v = torch.randn(*D.shape[:-1], generator=g, dtype=F64)
    Dt = D.transpose(-1, -2)
    torch.testing.assert_close(J.normal(), Dt @ D, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(J.normal(w), Dt @ (D * w[..., None]), rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(J.rmatvec(v), (Dt @ v[..., None])[..., 0], rtol=1e-12, atol=1e-12)
    other, _, _ = _random_blocks(seed + 2)
    pairs = zip(other.groups, groups, strict=True)
    other = BlockJacobian([(v2, c) for (v2, _), (_, c) in pairs], J.n, rows)
    keep = torch.tensor([True, False, True])
    torch.testing.assert_close(
        J.where(keep, other).dense(), torch.where(keep[:, None, None], D, other.dense())
    )


def test_levenberg_marquardt_with_block_jacobian_follows_the_dense_iteration():
    """A separable least-squares problem (shared parameter a, per-block offsets b_j:
    r_ji = a t_ji + b_j - y_ji): the block Jacobian gives the dense run's iterates."""
    g = torch.Generator().manual_seed(0)
    batch, S, R = 2, 5, 6
    t = torch.randn(batch, S, R, generator=g, dtype=F64)
    y = torch.sin(2.0 * t) + 0.3 * torch.randn(batch, S, R, generator=g, dtype=F64)
    n = 1 + S

    def residual(theta):
        a, b = theta[..., :1, None], theta[..., 1:, None]
        return (torch.sin(a * t) + b - y).flatten(-2)

    def dense(theta):
        a = theta[..., :1, None]
        J = torch.zeros(batch, S, R, n, dtype=F64)
        J[..., 0] = t * torch.cos(a * t)
        for j in range(S):
            J[:, j, :, 1 + j] = 1.0
        return residual(theta), J.flatten(1, 2)

    columns = torch.stack([torch.zeros(S, dtype=torch.int64), torch.arange(1, S + 1)], -1)

    def blocks(theta):
        a = theta[..., :1, None]
        values = torch.stack([t * torch.cos(a * t), torch.ones_like(t)], -1)  # (b, S, R, 2)
        return residual(theta), BlockJacobian([(values, columns)], n)

    theta0 = torch.full((batch, n), 0.5, dtype=F64)
    kw = dict(method="levenberg_marquardt", xtol=1e-14, ftol=1e-14)
    ref = minimize(residual, theta0, jacobian=dense, **kw)
    out = minimize(residual, theta0, jacobian=blocks, **kw)
    assert out.converged.all()
    torch.testing.assert_close(out.theta, ref.theta, rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(out.iterations, ref.iterations)
    torch.testing.assert_close(out.J.dense(), ref.J, rtol=1e-10, atol=1e-12)


def _chained_blocks(seed: int, batch=(3,), C=5, b=3, nb=2):
    """A Jacobian over ``nb`` border columns and a chain of ``C`` blocks of ``b`` columns
    (some slots without a column, columns in scrambled order), whose row blocks touch the
    border and the chain blocks ``j`` (and, in the second group, ``j + 1``)."""
    g = torch.Generator().manual_seed(seed)
    n_chain = C * b - 2
    n = nb + n_chain
    order = torch.randperm(n, generator=g)
    border, chain_cols = order[:nb], order[nb:]
    slots = torch.cat([chain_cols, torch.full((2,), -1)])[torch.randperm(C * b, generator=g)]
    chain = slots.reshape(C, b)
    groups = []
    for width, R in ((1, 4), (2, 3)):  # blocks over nodes j (outputs) and j, j+1 (defects)
        B = C - width + 1
        nodes = torch.stack([chain[j : j + width].reshape(-1) for j in range(B)])
        columns = torch.cat([border.expand(B, nb), nodes], -1)
        values = torch.randn(*batch, B, R, columns.shape[-1], generator=g, dtype=F64)
        groups.append((values, columns))
    n_padded = C * 4 + (C - 1) * 3
    rows = torch.sort(torch.randperm(n_padded, generator=g)[: n_padded - 3]).values
    return groups, rows, n, chain


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 10_000))
def test_a_chained_normal_matrix_and_its_damped_solve_equal_the_dense_ones(seed):
    groups, rows, n, chain = _chained_blocks(seed)
    J = BlockJacobian(groups, n, rows, chain)
    D = _dense_reference(groups, rows, n)
    g = torch.Generator().manual_seed(seed + 1)
    w = torch.rand(*D.shape[:-1], generator=g, dtype=F64)
    reference = D.transpose(-1, -2) @ (D * w[..., None])
    H = J.normal(w)
    torch.testing.assert_close(H.dense(), reference, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(H.diagonal(), reference.diagonal(dim1=-2, dim2=-1))
    rhs = torch.randn(*D.shape[:-2], n, generator=g, dtype=F64)
    shift = torch.tensor([1e-6, 1.0, 10.0], dtype=F64)
    x, ok = H.solve(rhs, shift)
    assert ok.all()
    shifted = reference + shift[:, None, None] * torch.eye(n, dtype=F64)
    torch.testing.assert_close(x, torch.linalg.solve(shifted, rhs), rtol=1e-8, atol=1e-10)
    other_J = BlockJacobian([(2 * v, c) for v, c in groups], n, rows, chain)
    other = other_J.normal(w)
    keep = torch.tensor([True, False, True])
    expected = torch.where(keep[:, None, None], reference, 4 * reference)
    torch.testing.assert_close(H.where(keep, other).dense(), expected)
    torch.testing.assert_close(J.where(keep, other_J).normal(w).dense(), expected)


def test_a_chained_solve_flags_a_matrix_that_is_not_positive_definite():
    groups, rows, n, chain = _chained_blocks(0)
    H = BlockJacobian(groups, n, rows, chain).normal()
    x, ok = H.solve(torch.ones(3, n, dtype=F64), torch.tensor([1.0, -1e6, 1.0], dtype=F64))
    assert ok.tolist() == [True, False, True]


def test_a_row_block_over_chain_blocks_that_are_not_neighbours_is_refused():
    groups, rows, n, chain = _chained_blocks(0)
    values, columns = groups[0]
    columns = columns.clone()
    columns[0, -1] = chain[3][chain[3] >= 0][0]  # block 0 also touching chain block 3
    with pytest.raises(InputValidationError, match="consecutive"):
        BlockJacobian([(values, columns)], n, None, chain)


def test_levenberg_marquardt_with_a_chained_jacobian_follows_the_dense_iteration():
    """Multiple shooting of x' = -a x in closed form: segment j from node s_j gives
    outputs s_j exp(-a t_i) and the defect s_j exp(-a T) - s_{j+1}; the chained Jacobian
    (block tridiagonal normal matrix) gives the dense run's iterates."""
    g = torch.Generator().manual_seed(1)
    batch, S, R, T = 2, 6, 4, 0.5
    t = torch.linspace(0, T, R + 1, dtype=F64)[:-1]
    truth = torch.exp(-0.7 * T * torch.arange(S, dtype=F64))
    y = truth[:, None] * torch.exp(-0.7 * t) + 0.01 * torch.randn(batch, S, R, generator=g)
    n = 1 + S

    def residual(theta):
        a, s = theta[..., :1, None], theta[..., 1:]
        out = (s[..., None] * torch.exp(-a * t) - y).flatten(-2)
        defect = s[..., :-1] * torch.exp(-a[..., 0] * T) - s[..., 1:]
        return torch.cat([out, defect], -1)

    def jacobians(theta, chain):
        a, s = theta[..., :1, None], theta[..., 1:]
        e = torch.exp(-a * t)  # (batch, 1, R)
        out = torch.stack([-t * s[..., None] * e, e.expand(batch, S, R)], -1)
        eT = torch.exp(-a[..., 0] * T)  # (batch, 1)
        d = torch.stack(
            [-T * s[..., :-1] * eT, eT.expand(batch, S - 1), -torch.ones(batch, S - 1, dtype=F64)],
            -1,
        )
        cols_out = torch.stack([torch.zeros(S, dtype=torch.int64), torch.arange(1, S + 1)], -1)
        cols_d = torch.stack(
            [torch.zeros(S - 1, dtype=torch.int64), torch.arange(1, S), torch.arange(2, S + 1)], -1
        )
        groups = [(out, cols_out), (d[..., None, :], cols_d)]
        return residual(theta), BlockJacobian(groups, n, None, chain)

    theta0 = torch.cat([torch.full((batch, 1), 0.3, dtype=F64), y[..., 0]], -1)
    kw = dict(method="levenberg_marquardt", xtol=1e-14, ftol=1e-14)
    chain = torch.arange(1, S + 1)[:, None]
    ref = minimize(residual, theta0, jacobian=lambda th: jacobians(th, None), **kw)
    out = minimize(residual, theta0, jacobian=lambda th: jacobians(th, chain), **kw)
    assert out.converged.all() and ref.converged.all()
    torch.testing.assert_close(out.theta, ref.theta, rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(out.iterations, ref.iterations)
    torch.testing.assert_close(out.hessian.dense(), ref.hessian, rtol=1e-10, atol=1e-12)


def test_a_chain_without_border_and_without_batch_dimensions():
    """Only node columns (no free parameter, x0 estimated) and one data set."""
    groups, rows, n, chain = _chained_blocks(5, batch=(), nb=0)
    H = BlockJacobian(groups, n, rows, chain).normal()
    D = _dense_reference(groups, rows, n)
    reference = D.T @ D
    torch.testing.assert_close(H.dense(), reference, rtol=1e-12, atol=1e-12)
    rhs = torch.randn(n, generator=torch.Generator().manual_seed(6), dtype=F64)
    x, ok = H.solve(rhs, torch.tensor(0.1, dtype=F64))
    assert bool(ok)
    shifted = reference + 0.1 * torch.eye(n, dtype=F64)
    torch.testing.assert_close(x, torch.linalg.solve(shifted, rhs), rtol=1e-8, atol=1e-10)
