"""Jacobians of sample-wise maps (integrators.jacobians): the four strategies of
``batch_jacobian`` against each other, a closed form and central differences; ``jacobian_rows``
with several inputs, unused inputs and a differentiable result."""

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from integrators import InputValidationError, batch_jacobian, jacobian_rows, newton, odeint
from integrators.jacobians import gradients
from integrators.sensitivities import sensitivities
from sysid.zoo import Crane

F64 = torch.float64


def _map(weights, bias):
    """y = tanh(x W^T + b) * x[..., :1]: sample-wise, broadcasts over leading dimensions."""

    def fn(x):
        return torch.tanh(x @ weights.T + bias) * x[..., :1]

    return fn


def _closed_form(weights, bias, x):
    """dy/dx of :func:`_map`: diag(1 - tanh^2) W x_0 + tanh e_0^T."""
    z = torch.tanh(x @ weights.T + bias)
    J = (1 - z * z)[..., :, None] * weights * x[..., :1, None]
    J[..., :, 0] += z
    return J


@settings(max_examples=25, deadline=None)
@given(
    m=st.integers(1, 4),
    n=st.integers(1, 4),
    batch=st.lists(st.integers(1, 3), min_size=0, max_size=2),
    seed=st.integers(0, 2**16),
)
def test_strategies_agree_with_the_closed_form_and_differences(m, n, batch, seed):
    g = torch.Generator().manual_seed(seed)
    weights = torch.randn(m, n, generator=g, dtype=F64)
    bias = torch.randn(m, generator=g, dtype=F64)
    x = torch.randn(*batch, n, generator=g, dtype=F64)
    fn = _map(weights, bias)
    truth = _closed_form(weights, bias, x)
    for strategy in ("vmap", "rows", "stacked", "forward"):
        y, J = batch_jacobian(fn, x, strategy=strategy)
        assert not J.requires_grad and not y.requires_grad
        torch.testing.assert_close(y, fn(x), rtol=1e-14, atol=1e-15)  # stacked: a GEMM
        torch.testing.assert_close(J, truth, rtol=1e-12, atol=1e-13)
    _, known = batch_jacobian(fn, x, strategy="stacked", outputs=m)
    torch.testing.assert_close(known, truth, rtol=1e-12, atol=1e-13)
    d = 1e-6
    fd = torch.stack(
        [(fn(x + d * e) - fn(x - d * e)) / (2 * d) for e in torch.eye(n, dtype=F64)], -1
    )
    torch.testing.assert_close(truth, fd, rtol=1e-6, atol=1e-8)


def test_maps_that_ignore_x_or_its_batch():
    """A constant without batch dimensions is broadcast to the batch, with zero Jacobians; a
    map of part of x has zero columns for the rest."""
    x = torch.randn(3, 2, dtype=F64)
    for strategy in ("vmap", "rows", "stacked", "forward"):
        y, J = batch_jacobian(lambda z: torch.ones(2, dtype=F64), x, strategy=strategy)
        assert y.shape == (3, 2) and torch.equal(J, torch.zeros(3, 2, 2, dtype=F64))
        y, J = batch_jacobian(lambda z: 3.0 * z[..., 1:], x, strategy=strategy)
        torch.testing.assert_close(J, torch.tensor([[[0.0, 3.0]]], dtype=F64).expand(3, 1, 2))


def test_inference_mode_is_refused_by_name_and_no_grad_works():
    """torch.inference_mode() switches autograd off, so every autograd Jacobian would be zero
    (forward sensitivities of zero, Newton matrices of the identity, a Lagrangian plant's
    mass matrix): the Jacobian, Newton, the sensitivities, an implicit integrator and a
    Lagrangian plant refuse it by name; under torch.no_grad() they give the right numbers."""
    x = torch.tensor([[0.5, -1.0], [2.0, 0.3]], dtype=F64)

    def cube(z):
        return z**3 - 2.0

    def decay(t, x, p):
        return -p * x

    t = torch.linspace(0.0, 1.0, 5, dtype=F64)
    p = torch.tensor([2.0], dtype=F64)
    crane = Crane().to(F64)  # its equations of motion are formed by autograd
    state = torch.tensor([[0.1, 0.3, 0.0, 0.2]], dtype=F64)
    calls = {
        "batch_jacobian": lambda: batch_jacobian(cube, x),
        "newton": lambda: newton(cube, x.abs() + 1.0),
        "sensitivities": lambda: sensitivities(decay, x, t, p, substeps=4, compile=False),
        "odeint": lambda: odeint(lambda t, z: -50.0 * z, x, t, method="radau_iia"),
        "Lagrangian plant": lambda: crane(0.0, state),
    }
    for name, call in calls.items():
        with torch.inference_mode(), pytest.raises(InputValidationError, match="inference_mode"):
            call()
        with torch.no_grad():
            result = call()
        if name == "batch_jacobian":
            torch.testing.assert_close(result[1], torch.diag_embed(3 * x**2))
        elif name == "newton":
            assert bool(result.converged.all())
            torch.testing.assert_close(result.x, torch.full_like(x, 2 ** (1 / 3)))
        elif name == "sensitivities":
            expected = -t[:, None] * torch.exp(-2.0 * t[:, None]) * x[:, None, :]
            torch.testing.assert_close(result.B[..., 0], expected, rtol=1e-4, atol=1e-8)
        elif name == "odeint":
            expected = torch.exp(-50.0 * t[:, None]) * x[:, None, :]
            torch.testing.assert_close(result.x, expected, rtol=1e-3, atol=1e-6)
        else:
            torch.testing.assert_close(result, crane(0.0, state), rtol=0, atol=0)


def test_unknown_strategy_is_refused_by_name():
    with pytest.raises(InputValidationError, match="unknown strategy 'jvp'"):
        batch_jacobian(torch.sin, torch.zeros(2, 1), strategy="jvp")


def test_jacobian_rows_several_inputs_unused_inputs_and_second_derivatives():
    """y = [x0^2 u, sin(x1)] at a batch: dy/dx, dy/du, zeros for an input y ignores, and with
    create_graph=True the derivative of dy0/dx0 = 2 x0 u with respect to u is 2 x0."""
    x = torch.tensor([[0.5, -1.0], [2.0, 0.3]], dtype=F64, requires_grad=True)
    u = torch.tensor([[3.0], [-2.0]], dtype=F64, requires_grad=True)
    unused = torch.zeros(2, 4, dtype=F64, requires_grad=True)
    y = torch.stack([x[:, 0] ** 2 * u[:, 0], torch.sin(x[:, 1])], -1)
    jx, ju, jw = jacobian_rows(y, (x, u, unused), create_graph=True)
    expected_x = torch.zeros(2, 2, 2, dtype=F64)
    expected_x[:, 0, 0] = 2 * x[:, 0] * u[:, 0]
    expected_x[:, 1, 1] = torch.cos(x[:, 1])
    torch.testing.assert_close(jx, expected_x.detach())
    torch.testing.assert_close(ju[:, :, 0], torch.stack([x[:, 0] ** 2, 0 * x[:, 0]], -1).detach())
    assert torch.equal(jw, torch.zeros(2, 2, 4, dtype=F64))
    (d2,) = torch.autograd.grad(jx[:, 0, 0].sum(), u)
    torch.testing.assert_close(d2[:, 0], 2 * x[:, 0].detach())
    # an output that depends on no input: zeros of the right shapes
    (z,) = jacobian_rows(torch.ones(2, 3, dtype=F64), (x,))
    assert z.shape == (2, 3, 2) and not z.any()


def test_gradients_fill_zeros_and_keep_the_graph():
    """A vector-Jacobian product with zeros for unused inputs and for an output without a
    graph; one tensor in, one gradient out; the graph stays for a second call."""
    x = torch.tensor([1.0, 2.0], dtype=F64, requires_grad=True)
    unused = torch.ones(3, dtype=F64, requires_grad=True)
    y = x**2
    gx, gu = gradients(y, (x, unused), torch.tensor([1.0, -1.0], dtype=F64))
    torch.testing.assert_close(gx, torch.tensor([2.0, -4.0], dtype=F64))
    assert torch.equal(gu, torch.zeros(3, dtype=F64))
    again = gradients(y.sum(), x)  # the graph of y is still there
    assert isinstance(again, torch.Tensor)
    torch.testing.assert_close(again, 2 * x.detach())
    assert torch.equal(gradients(torch.ones(2, dtype=F64).sum(), x), torch.zeros(2, dtype=F64))


def test_an_output_with_a_batch_of_its_own_is_refused_by_name():
    """A map whose parameters carry a batch that x lacks would sum the members' Jacobians."""
    rates = torch.tensor([[1.0], [2.0], [3.0]], dtype=F64)
    for strategy in ("vmap", "rows", "stacked", "forward"):
        with pytest.raises(InputValidationError, match="batch dimensions must be x's"):
            batch_jacobian(lambda z: rates * z, torch.ones(1, dtype=F64), strategy=strategy)
    _, J = batch_jacobian(lambda z: rates * z, torch.ones(3, 1, dtype=F64))
    torch.testing.assert_close(J, rates[:, :, None])
