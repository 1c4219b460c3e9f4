"""Continuous-time models with learned parts (sysid.continuous.neural) against independent
truth: eigenvalues of the learned mass matrix, energy conservation of the exact flow, the
Euler-Lagrange equation assembled here by autograd, the grey-box model's own simulation,
finite differences (gradcheck) and the scaling laws of the normalisation."""

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from torch.func import functional_call, jacfwd

from integrators import odeint
from integrators.errors import InputValidationError
from sysid import GreyBoxModel, HybridODE, IOData, LagrangianNetwork, NeuralODE, Param
from sysid.zoo import SpringMassDamper

T0 = torch.tensor(0.0, dtype=torch.float64)


def oscillator(t, x, u, p):
    """m y'' + xi y' + K y + k3 y^3 = u."""
    acc = (u[..., 0] - p["xi"] * x[..., 1] - p["K"] * x[..., 0] - p["k3"] * x[..., 0] ** 3) / p["m"]
    return torch.stack([x[..., 1], acc], -1)


def oscillator_model(**kw):
    params = {
        "m": Param(1.3, min=0.1, max=5.0),
        "xi": Param(0.4, min=0.0),
        "K": Param(3.0),
        "k3": Param(0.7, free=False),
    }
    return GreyBoxModel(oscillator, params, nx=2, output=[0], **kw)


def rich_lagrangian(nq, nu=0, seed=0, **kw):
    """A LagrangianNetwork whose last layers are scaled up, so that M(q) and V(q) vary
    visibly with q (the initialisation is close to M = I, V = 0)."""
    model = LagrangianNetwork(nq, nu, hidden=(16, 16), seed=seed, **kw)
    with torch.no_grad():
        model.mass_net[-1].weight.mul_(60.0)
        model.potential_net[-1].weight.mul_(300.0)
        if model.dissipation_factor is not None:
            model.dissipation_factor.mul_(5.0)
    return model


# ------------------------------------------------------------------ LagrangianNetwork
@settings(max_examples=40, deadline=None)
@given(
    nq=st.integers(1, 4),
    seed=st.integers(0, 2**31 - 1),
    log_mag=st.floats(-3.0, 6.0),
    batch_seed=st.integers(0, 1000),
)
def test_mass_matrix_symmetric_positive_definite(nq, seed, log_mag, batch_seed):
    model = LagrangianNetwork(nq, hidden=(8, 8), seed=seed)
    with torch.no_grad():
        model.mass_net[-1].weight.mul_(100.0)  # far from the near-identity start
    g = torch.Generator().manual_seed(batch_seed)
    q = 10.0**log_mag * torch.randn(6, nq, generator=g, dtype=torch.float64)
    M = model.mass_matrix(q).detach()
    assert torch.isfinite(M).all()
    scale = M.abs().amax(dim=(-1, -2), keepdim=True)
    assert ((M - M.transpose(-1, -2)).abs() <= 1e-12 * scale).all()
    eig = torch.linalg.eigvalsh(M)
    assert (eig > 0).all()
    assert (eig >= model.eps * (1 - 1e-8) - 1e-14 * scale[..., 0]).all()


def euler_lagrange_accelerations(model, x, u=None):
    """qddot from M qddot = -(dM/dt) qdot + 1/2 d(qdot^T M qdot)/dq - dV/dq - R R^T qdot + B u,
    with M(q) from the model's closed form and every derivative taken here by forward-mode
    autograd, one sample at a time (independent of LagrangianSystem's reverse passes)."""
    nq = model.nq

    def one(xk, uk):
        q, v = xk[:nq], xk[nq:]
        M = model.mass_matrix(q)
        dM = jacfwd(model.mass_matrix)(q)  # (nq, nq, nq): dM_ij / dq_k
        Mdot = dM @ v
        dT_dq = 0.5 * torch.einsum("i,ijk,j->k", v, dM, v)
        dV = jacfwd(lambda qq: model.potential(qq))(q)
        rhs = -Mdot @ v + dT_dq - dV
        if model.dissipation_factor is not None:
            R = model.dissipation_factor
            rhs = rhs - R @ (R.T @ v)
        if uk is not None:
            rhs = rhs + model.input_matrix_at(q) @ uk
        return torch.linalg.solve(M, rhs)

    return torch.stack([one(x[k], None if u is None else u[k]) for k in range(x.shape[0])]).detach()


@pytest.mark.parametrize(
    "nq, nu, input_map", [(1, 0, "learned"), (3, 2, "learned"), (2, 2, "identity")]
)
def test_lagrangian_network_obeys_euler_lagrange(nq, nu, input_map):
    model = rich_lagrangian(nq, nu, seed=nq, input_map=input_map)
    g = torch.Generator().manual_seed(5)
    x = torch.randn(4, 2 * nq, generator=g, dtype=torch.float64)
    u = torch.randn(4, nu, generator=g, dtype=torch.float64) if nu else None
    dx = model(T0, x, u).detach()
    torch.testing.assert_close(dx[:, :nq], x[:, nq:], rtol=0, atol=0)
    expected = euler_lagrange_accelerations(model, x, u)
    torch.testing.assert_close(dx[:, nq:], expected, rtol=1e-10, atol=1e-12)
    assert expected.abs().max() > 0.1  # the learned terms act


def test_lagrangian_network_conserves_energy_and_dissipates():
    nq = 2
    model = rich_lagrangian(nq, dissipation=False, seed=3)
    g = torch.Generator().manual_seed(1)
    x0 = torch.randn(3, 2 * nq, generator=g, dtype=torch.float64)
    t = torch.linspace(0.0, 1.0, 11, dtype=torch.float64)
    with torch.no_grad():
        sol = odeint(model, x0, t, method="dopri5", rtol=1e-11, atol=1e-13)
        E = model.energy(sol.x)
        # a plain NeuralODE of the same size has no such invariant
        free = NeuralODE(2 * nq, 0, hidden=(16, 16), seed=3)
        free.net[-1].weight.mul_(100.0)
        E_free = model.energy(odeint(free, x0, t, method="dopri5", rtol=1e-11, atol=1e-13).x)
    span = (sol.x[..., nq:].abs().amax(-2) - sol.x[..., nq:].abs().amin(-2)).amax()
    assert span > 0.1  # the state moves
    drift = (E - E[..., :1]).abs().amax()
    assert drift <= 1e-8 * E.abs().amax()
    assert (E_free - E_free[..., :1]).abs().amax() > 1e-3 * E_free.abs().amax()

    # with dissipation: dE/dt = grad E . f(x) = -qdot^T R R^T qdot = -2 D(qdot) <= 0
    damped = rich_lagrangian(nq, dissipation=True, seed=3)
    x = torch.randn(5, 2 * nq, generator=g, dtype=torch.float64, requires_grad=True)
    (grad_e,) = torch.autograd.grad(damped.energy(x).sum(), x)
    rate = (grad_e * damped(T0, x.detach())).sum(-1).detach()
    expected = -2 * damped.dissipation(x.detach()[..., nq:]).detach()
    torch.testing.assert_close(rate, expected, rtol=1e-10, atol=1e-12)
    assert (expected < 0).all()


def test_lagrangian_network_constraints_pass_through():
    # a point on the unit circle (x, y) in a learned field: c(q) = x^2 + y^2 - 1, index-1 form
    model = rich_lagrangian(
        2, dissipation=False, seed=4, constraints=lambda q: (q**2).sum(-1, True) - 1
    )
    x0 = torch.tensor([[1.0, 0.0, 0.0, 0.7]], dtype=torch.float64)
    t = torch.linspace(0.0, 1.0, 11, dtype=torch.float64)
    with torch.no_grad():
        sol = odeint(model, x0, t, method="dopri5", rtol=1e-11, atol=1e-13)
        c, cdot = model.drift(sol.x)
        E = model.energy(sol.x)
    assert c.abs().max() < 1e-7 and cdot.abs().max() < 1e-7
    assert (E - E[..., :1]).abs().max() < 1e-7 * E.abs().max()


# ------------------------------------------------------------------ HybridODE
def simulate_contract_model(model, u, Ts, x0, substeps):
    """The contract's simulation: RK with zero-order-hold input, output(x, u)."""
    N = u.shape[-2]
    t = Ts * torch.arange(N, dtype=torch.float64)
    with torch.no_grad():
        sol = odeint(model, x0, t, method=model.method, u=u, interpolation="zoh", substeps=substeps)
        return model.output(sol.x, u)


@pytest.mark.parametrize("kind", ["function", "module"])
def test_hybrid_with_zero_residual_equals_greybox_simulation(kind):
    g = torch.Generator().manual_seed(2)
    u = torch.randn(3, 40, 1, generator=g, dtype=torch.float64)
    data = IOData(u, u, Ts=0.1)
    if kind == "function":
        physics = oscillator_model(substeps=2)
    else:
        physics = GreyBoxModel(
            SpringMassDamper(m=1.5, xi=0.3, K=2.0),
            {"m": Param(1.5, min=0.5), "xi": Param(0.3), "K": Param(2.0, free=False)},
            output=[0],
            substeps=2,
        )
    x0 = torch.tensor([0.5, -0.2], dtype=torch.float64)
    expected = physics.simulate(data, x0=x0)
    model = HybridODE(physics, hidden=(8,), nu=1, seed=0)
    got = simulate_contract_model(model, u, 0.1, x0.expand(3, 2), substeps=2)
    torch.testing.assert_close(got, expected, rtol=1e-12, atol=1e-13)
    assert expected.abs().max() > 0.1


def test_hybrid_physical_parameters_and_bounds():
    physics = oscillator_model()
    model = HybridODE(physics, hidden=(8,), nu=1, seed=0)
    raw = model.physical_parameters()
    assert list(raw) == ["m", "xi", "K"]  # the fixed k3 is not estimated
    assert all(isinstance(p, torch.nn.Parameter) for p in raw.values())
    for name, start in (("m", 1.3), ("xi", 0.4), ("K", 3.0)):
        assert math.isclose(
            float(model.to_physical(name, raw[name]).detach()), start, rel_tol=1e-14
        )
    assert float(model.physical_values()["k3"]) == 0.7
    # bounds hold for any unconstrained value
    z = torch.tensor([-40.0, -3.0, 0.0, 3.0, 40.0], dtype=torch.float64)
    m = model.to_physical("m", z)
    assert ((m >= 0.1) & (m <= 5.0)).all() and m[0] < 0.11 and m[-1] > 4.99
    assert (model.to_physical("xi", z) >= 0.0).all()
    # the physical parameters reach the right-hand side: d(xdot)/d(raw K) = -y * s_K
    x = torch.tensor([[0.8, 0.1]], dtype=torch.float64)
    u = torch.zeros(1, 1, dtype=torch.float64)
    (dK,) = torch.autograd.grad(model(T0, x, u)[0, 1], raw["K"])
    assert math.isclose(float(dK), -0.8 * 3.0 / 1.3, rel_tol=1e-12)
    with pytest.raises(InputValidationError, match="unknown physical parameter"):
        model.to_physical("k3", z)


def test_hybrid_residual_on_chosen_states():
    physics = GreyBoxModel(
        oscillator, {"m": 1.0, "xi": 0.5, "K": 2.0, "k3": 0.0}, nx=2, state_names=("y", "ydot")
    )
    model = HybridODE(physics, hidden=(8,), nu=1, residual_states=["ydot"], Ts=0.5, seed=1)
    with torch.no_grad():
        model.net[-1].bias.fill_(0.25)
    x = torch.tensor([[0.3, -0.4]], dtype=torch.float64)
    u = torch.tensor([[0.2]], dtype=torch.float64)
    P = {n: torch.tensor([v]) for n, v in {"m": 1.0, "xi": 0.5, "K": 2.0, "k3": 0.0}.items()}
    phys = oscillator(T0, x, u, {n: v.double() for n, v in P.items()})
    # the residual 0.25 / Ts = 0.5 enters ydot' only
    torch.testing.assert_close(
        model(T0, x, u).detach(), phys + torch.tensor([[0.0, 0.5]], dtype=torch.float64)
    )


# ------------------------------------------------------------------ NeuralODE
def test_neural_ode_seeded_initialisation_is_bit_reproducible():
    a, b = NeuralODE(3, 2, seed=7), NeuralODE(3, 2, seed=7)
    c = NeuralODE(3, 2, seed=8)
    sa, sb, sc = a.state_dict(), b.state_dict(), c.state_dict()
    assert all(torch.equal(sa[k], sb[k]) for k in sa)
    assert not all(torch.equal(sa[k], sc[k]) for k in sa)
    x = torch.randn(4, 3, dtype=torch.float64)
    u = torch.randn(4, 2, dtype=torch.float64)
    assert torch.equal(a(T0, x, u), b(T0, x, u))
    l1, l2 = LagrangianNetwork(2, 1, seed=3), LagrangianNetwork(2, 1, seed=3)
    assert all(torch.equal(v, l2.state_dict()[k]) for k, v in l1.state_dict().items())


def test_neural_ode_time_scale_and_normalisation():
    g = torch.Generator().manual_seed(0)
    x = torch.randn(5, 3, generator=g, dtype=torch.float64)
    u = torch.randn(5, 2, generator=g, dtype=torch.float64)
    slow, fast = NeuralODE(3, 2, Ts=0.5, seed=1), NeuralODE(3, 2, Ts=0.25, seed=1)
    f_slow = slow(T0, x, u).detach()
    torch.testing.assert_close(fast(T0, x, u).detach(), 2 * f_slow, rtol=1e-15, atol=0)
    # the initial model is close to x' = 0 on the scale x_scale / Ts
    assert f_slow.abs().max() < 0.1 / 0.5

    # scaling the data and the normalisation together scales the derivative alike
    xs = torch.tensor([2.0, 0.5, 10.0], dtype=torch.float64)
    us = torch.tensor([3.0, 0.1], dtype=torch.float64)
    xo = torch.tensor([0.1, -0.2, 1.0], dtype=torch.float64)
    base = NeuralODE(3, 2, seed=2, x_scale=xs, u_scale=us, x_offset=xo, output_network=True)
    c = torch.tensor([7.0, 0.01, 3.0], dtype=torch.float64)
    scaled = NeuralODE(
        3, 2, seed=2, x_scale=xs * c, u_scale=us * 4.0, x_offset=xo * c, output_network=True
    )
    torch.testing.assert_close(
        scaled(T0, x * c, u * 4.0).detach(), c * base(T0, x, u).detach(), rtol=1e-13, atol=0
    )
    torch.testing.assert_close(scaled.output(x * c, u * 4.0), base.output(x, u), rtol=1e-13, atol=0)


# ------------------------------------------------------------------ gradients
def _gradcheck(model, names, x, u):
    params = dict(model.named_parameters())
    chosen = tuple(params[n].detach().clone().requires_grad_(True) for n in names)

    def rhs(*values):
        return functional_call(model, dict(zip(names, values, strict=True)), (T0, x, u))

    assert torch.autograd.gradcheck(rhs, chosen, eps=1e-6, atol=1e-7, rtol=1e-6)


def test_gradients_reach_the_parameters():
    g = torch.Generator().manual_seed(3)
    neural = NeuralODE(2, 1, hidden=(4,), seed=0)
    x2 = torch.randn(3, 2, generator=g, dtype=torch.float64)
    u1 = torch.randn(3, 1, generator=g, dtype=torch.float64)
    _gradcheck(neural, ["net.0.weight", "net.2.bias"], x2, u1)

    hybrid = HybridODE(oscillator_model(), hidden=(4,), nu=1, seed=0)
    with torch.no_grad():
        hybrid.net[-1].weight.normal_(generator=g)
    _gradcheck(hybrid, ["raw.0", "raw.1", "net.0.weight", "net.2.weight"], x2, u1)

    lagr = rich_lagrangian(2, 1)
    x4 = torch.randn(3, 4, generator=g, dtype=torch.float64)
    names = ["mass_net.4.bias", "potential_net.2.bias", "dissipation_factor", "input_net.4.bias"]
    _gradcheck(lagr, names, x4, u1)


# ------------------------------------------------------------------ bad input
@pytest.mark.parametrize(
    "build, words",
    [
        (lambda: LagrangianNetwork(0), "nq must be an integer >= 1"),
        (lambda: NeuralODE(2, 1, hidden=(64, 0)), "hidden layer width"),
        (lambda: NeuralODE(2, 1, hidden="64"), "sequence of layer widths"),
        (lambda: NeuralODE(2, 1, activation="swish"), "unknown activation"),
        (lambda: NeuralODE(2, 1, Ts=-0.1), "Ts must be a finite number > 0"),
        (lambda: NeuralODE(2, 1, x_scale=[1.0, 0.0]), "x_scale must be finite and > 0"),
        (
            lambda: NeuralODE(2, 1, u_scale=[1.0, 2.0]),
            "u_scale must be a number or have shape (1,)",
        ),
        (lambda: NeuralODE(2, 1, ny=3), "output_network=True"),
        (lambda: NeuralODE(2, 1, method="auto"), "fixed-step method"),
        (lambda: NeuralODE(2, 1, method="rk5"), "unknown method"),
        (lambda: NeuralODE(2, 1, substeps=0), "substeps must be an integer >= 1"),
        (lambda: NeuralODE(2, 1, seed=1.5), "seed must be an int"),
        (lambda: LagrangianNetwork(2, 1, input_map="identity"), "needs nu = nq"),
        (lambda: LagrangianNetwork(2, 1, input_map=torch.ones(3, 1)), "finite (2, 1) matrix"),
        (lambda: LagrangianNetwork(2, eps=0.0), "eps must be a number > 0"),
        (lambda: HybridODE(oscillator), "must be a sysid.continuous.GreyBoxModel"),
        (lambda: HybridODE(oscillator_model()), "pass nu="),
        (lambda: HybridODE(oscillator_model(), nu=1, residual_states=[2]), "out of range"),
        (
            lambda: HybridODE(
                GreyBoxModel(
                    oscillator,
                    {"m": Param([1.0, 2.0], per_experiment=True), "xi": 0.1, "K": 1.0, "k3": 0.0},
                    nx=2,
                ),
                nu=1,
            ),
            "per_experiment",
        ),
    ],
)
def test_bad_construction_raises(build, words):
    with pytest.raises(InputValidationError) as info:
        build()
    assert words in str(info.value)


def test_bad_call_shapes_raise():
    neural = NeuralODE(2, 1, hidden=(4,), seed=0)
    with pytest.raises(InputValidationError, match=r"\(\*batch, nx\) = \(\*batch, 2\)"):
        neural(T0, torch.zeros(3, 3, dtype=torch.float64), torch.zeros(3, 1, dtype=torch.float64))
    with pytest.raises(InputValidationError, match="pass u of shape"):
        neural(T0, torch.zeros(3, 2, dtype=torch.float64))
    lagr = LagrangianNetwork(2, 1, hidden=(4,), seed=0)
    with pytest.raises(InputValidationError, match=r"2 nq\) = \(\*batch, 4\)"):
        lagr.energy(torch.zeros(3, 3, dtype=torch.float64))
    hybrid = HybridODE(oscillator_model(), hidden=(4,), nu=1, seed=0)
    with pytest.raises(InputValidationError, match=r"\(\*batch, nu\) = \(\*batch, 1\)"):
        hybrid(T0, torch.zeros(3, 2, dtype=torch.float64), torch.zeros(3, 2, dtype=torch.float64))
