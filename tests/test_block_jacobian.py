"""The block-sparse Jacobian of multiple shooting against its dense form, and the minimiser
run with it against the same minimiser run with the dense Jacobian."""

import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from integrators.block_jacobian import BlockJacobian
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
