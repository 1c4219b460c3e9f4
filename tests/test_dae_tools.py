"""sysid.dae: classification, index, index reduction, elimination, Tikhonov (notes chapter 5)."""

import numpy as np
import pytest
import scipy.linalg
import torch

from integrators import ImplicitDAE, SemiExplicitDAE, daeint, odeint
from integrators.errors import (
    ConvergenceError,
    HighIndexError,
    InputValidationError,
    SingularMatrixError,
)
from sysid import dae, zoo
from sysid.linearize import linearize, simulate_lti_zoh
from sysid.zoo import Bowl, RigidCraneCartesian
from sysid.zoo.dae import (
    AlgebraicStateDAE,
    LinearIndex1DAE,
    LinearIndex2DAE,
    LinearIndex3DAE,
    SingularlyPerturbedLinear,
    SingularMassMatrixDAE,
    TwoMassSystem,
    UnitSphereDAE,
)
from sysid.zoo.scenarios import dae_scenarios

DT = torch.float64


def _rand(*shape, seed=0):
    return torch.randn(*shape, dtype=DT, generator=torch.Generator().manual_seed(seed))


def test_definition_1_classifies_eq_5_2_and_5_3_as_daes_and_an_ode_as_ode():
    x, xdot = _rand(4, 2), _rand(4, 2, seed=1)
    none = torch.zeros(4, 0, dtype=DT)
    assert bool(dae.is_dae(AlgebraicStateDAE().residual, xdot, x, none).all())  # eq. (5.9)
    assert bool(dae.is_dae(SingularMassMatrixDAE().residual, xdot, x, none).all())  # eq. (5.11)

    def ode(t, xd, xx, z):
        return xd - torch.stack([xx[..., 1], -xx[..., 0]], -1)

    assert not bool(dae.is_dae(ode, xdot, x, none).any())
    # eq. (5.13): u xdot + x = 0 is an ODE for u != 0 and a DAE for u = 0
    switch = lambda t, xd, xx, z, u: u * xd + xx  # noqa: E731
    u = torch.tensor([[1.0], [0.0]], dtype=DT)
    res = dae.is_dae(switch, xdot[:2, :1], x[:2, :1], none[:2], u)
    assert res.tolist() == [False, True]


def test_index1_tests_theorem_9_and_corollary_1():
    x, z, u = _rand(3, 2), _rand(3, 1, seed=1), _rand(3, 1, seed=2)
    xdot = torch.zeros(3, 2, dtype=DT)
    assert bool(dae.is_index1(LinearIndex1DAE().residual, xdot, x, z, u).all())  # eq. (5.50)
    assert not bool(dae.is_index1(LinearIndex3DAE().residual, xdot, x, z, u).any())  # eq. (5.49)
    e581 = LinearIndex2DAE()
    z2 = _rand(3, 2, seed=3)
    assert not bool(dae.is_index1_semi_explicit(e581.g, x, z2, u).any())  # eq. (5.82)
    assert bool(dae.is_index1_semi_explicit(e581.reduced_g, x, z2, u).all())  # eq. (5.87)


@pytest.mark.parametrize(("example", "expected"), [(LinearIndex1DAE, 1), (LinearIndex3DAE, 3)])
def test_differential_index_of_fully_implicit_examples(example, expected):
    x, z, u = _rand(3, 2), _rand(3, 1, seed=1), _rand(3, 1, seed=2)
    index = dae.differential_index(example().residual, torch.zeros(3, 2, dtype=DT), x, z, u)
    assert index.tolist() == [expected] * 3


@pytest.mark.parametrize("example", [zoo.AlgebraicStateDAE, zoo.SingularMassMatrixDAE])
def test_differential_index_without_algebraic_states(example):
    """Implicit ODEs with a singular dF/dxdot and no algebraic states (z of width 0): the
    index of the zoo's declaration."""
    x = _rand(3, 2)
    z = torch.zeros(3, 0, dtype=DT)
    index = dae.differential_index(example().residual, torch.zeros(3, 2, dtype=DT), x, z)
    assert index.tolist() == [example.index] * 3


@pytest.mark.parametrize(("example", "expected"), [(LinearIndex2DAE, 2), (UnitSphereDAE, 2)])
def test_differential_index_and_reduction_of_semi_explicit_examples(example, expected):
    plant = example()
    x, z = _rand(3, plant.nx), _rand(3, plant.nz, seed=1)
    assert dae.semi_explicit_index(plant.f, plant.g, x, z).tolist() == [expected] * 3
    reduced = dae.reduce_index(plant.f, plant.g, x, z)
    assert reduced.index == expected and reduced.differentiations == expected - 1
    t = torch.tensor(0.0, dtype=DT)
    torch.testing.assert_close(reduced.g(t, x, z), plant.reduced_g(t, x, z))  # (5.86b)/(5.93b)
    assert bool(dae.is_index1_semi_explicit(reduced.g, x, z).all())
    # consistency conditions are the differentiated equations (§5.6)
    torch.testing.assert_close(reduced.consistency(t, x, z), plant.g(t, x, z)[..., :1])


def test_eq_5_88_reduced_multiplier_eq_5_92():
    plant = UnitSphereDAE()
    x = _rand(5, 2)
    z = plant.multiplier(x)
    res = plant.reduced_g(torch.tensor(0.0), x, z)
    torch.testing.assert_close(res, torch.zeros_like(res), rtol=0, atol=1e-12)


def test_constrained_lagrangian_models_are_index_3_and_reduce_to_the_kkt_form():
    """Eq. (5.76)-(5.79): index 3; the automatic reduction (two differentiations) reproduces
    the index-1 constraint a qddot + (d(a qdot)/dq) qdot = 0 (eq. 2.167b) and the consistency
    conditions C = [c; cdot] (eq. 2.182)."""
    for plant in (Bowl(), RigidCraneCartesian()):
        f, g = plant.index3_dae()
        x, z = _rand(2, 2 * plant.nq), _rand(2, 1, seed=1)
        assert dae.semi_explicit_index(f, g, x, z).tolist() == [3, 3]
        reduced = dae.reduce_index(f, g, x, z)
        assert reduced.index == 3
        _, g1 = plant.index1_dae()
        t = torch.tensor(0.0, dtype=DT)
        torch.testing.assert_close(reduced.g(t, x, z), g1(t, x, z), rtol=1e-12, atol=1e-12)
        q, qd = x[:, : plant.nq], x[:, plant.nq :]
        torch.testing.assert_close(reduced.consistency(t, x, z), plant.consistency(q, qd))


def test_reduction_refuses_what_it_cannot_do():
    def f(t, x, z):
        return z

    def g(t, x, z):  # dg/dz singular but every row depends on z
        return torch.cat([z[..., :1] + z[..., 1:], 2 * z[..., :1] + 2 * z[..., 1:] + x], -1)

    with pytest.raises(HighIndexError, match="algebraic manipulations"):
        dae.reduce_index(f, g, _rand(2, 1), _rand(2, 2))


def test_eliminate_linear_eq_5_30_matches_substitution_and_linearize_dae():
    gen = torch.Generator().manual_seed(4)
    a, b, c = (torch.randn(3, 3, 2, 2, dtype=DT, generator=gen) for _ in range(3))
    d, e = (
        torch.randn(3, 2, 2, dtype=DT, generator=gen),
        torch.randn(3, 2, 1, dtype=DT, generator=gen),
    )
    b = b[..., :1]
    fm = torch.randn(3, 2, 2, dtype=DT, generator=gen) + 3 * torch.eye(2, dtype=DT)
    a, c = a[0], c[0]
    ar, br, cz, dz = dae.eliminate_linear(a, b[0], c, d, e, fm)
    x, u = _rand(3, 2), _rand(3, 1, seed=5)
    z = torch.linalg.solve(fm, -(d @ x[..., None] + e @ u[..., None]))[..., 0]
    xdot = (a @ x[..., None] + b[0] @ u[..., None] + c @ z[..., None])[..., 0]
    torch.testing.assert_close((ar @ x[..., None] + br @ u[..., None])[..., 0], xdot)
    torch.testing.assert_close((cz @ x[..., None] + dz @ u[..., None])[..., 0], z)
    with pytest.raises(SingularMatrixError):
        dae.eliminate_linear(a, b[0], c, d, e, torch.zeros(3, 2, 2, dtype=DT))
    # a rank-one F in floating point (singular values 0.114 and 1.9e-18) factorises without a
    # zero pivot; its "inverse" gave Cz of order 1e17
    rank_one = torch.tensor([[0.3], [-0.1]], dtype=DT) @ torch.tensor([[0.2, 0.3]], dtype=DT)
    assert float(torch.linalg.svdvals(rank_one)[-1]) < 1e-16
    with pytest.raises(SingularMatrixError, match="smallest singular value"):
        dae.eliminate_linear(a, b[0], c, d, e, rank_one.expand(3, 2, 2))
    # eq. (5.32): the Jacobians of the linear DAE are its matrices
    f = lambda t, xx, zz, uu: (a @ xx[..., None] + b[0] @ uu[..., None] + c @ zz[..., None])[..., 0]  # noqa: E731
    g = lambda t, xx, zz, uu: (d @ xx[..., None] + e @ uu[..., None] + fm @ zz[..., None])[..., 0]  # noqa: E731
    jac = dae.linearize_dae(f, g, x, z, u)
    torch.testing.assert_close(jac["fx"], a.expand(3, 2, 2))
    torch.testing.assert_close(jac["gz"], fm)
    torch.testing.assert_close(jac["gu"], e)


def test_dae_helpers_refuse_a_scalar_input_and_take_a_width_one_vector():
    """u must be (*batch, nu): a scalar is refused by name (it crashed with an integer
    overflow in expand), one input as a vector of width 1 (or a shared (nu,) for a batch)
    gives the analytic Jacobians of x' = x z + u^2 (here fu = 2 u), 0 = z^3 + x u."""

    def f(t, x, z, u):
        return x * z + u**2

    def g(t, x, z, u):
        return z**3 + x * u

    def F(t, xdot, x, z, u):
        return torch.cat([xdot - f(t, x, z, u), g(t, x, z, u)], -1)

    x, z = torch.full((3, 1), 0.3, dtype=DT), torch.full((3, 1), 0.5, dtype=DT)
    calls = {
        "linearize_dae": lambda u: dae.linearize_dae(f, g, x, z, u),
        "linearize_implicit_dae": lambda u: dae.linearize_implicit_dae(F, x, x, z, u),
        "differential_index": lambda u: dae.differential_index(F, x, x, z, u),
        "reduce_index": lambda u: dae.reduce_index(f, g, x, z, u),
    }
    for name, call in calls.items():
        for scalar in (0.7, torch.tensor(0.7, dtype=DT)):
            with pytest.raises(InputValidationError, match=rf"{name}: u must have shape"):
                call(scalar)
        with pytest.raises(InputValidationError, match=rf"{name}: u of shape \(2, 1\)"):
            call(torch.ones(2, 1, dtype=DT))
    jac = dae.linearize_dae(f, g, x, z, torch.tensor([0.7], dtype=DT))
    torch.testing.assert_close(jac["fu"], torch.full((3, 1, 1), 1.4, dtype=DT))
    torch.testing.assert_close(jac["gu"], torch.full((3, 1, 1), 0.3, dtype=DT))
    torch.testing.assert_close(jac["gz"], torch.full((3, 1, 1), 0.75, dtype=DT))
    imp = dae.linearize_implicit_dae(F, x, x, z, torch.full((3, 1), 0.7, dtype=DT))
    torch.testing.assert_close(imp["Fu"][:, :, 0], torch.tensor([[-1.4, 0.3]] * 3, dtype=DT))
    index = dae.differential_index(F, x, x, z, torch.tensor([0.7], dtype=DT))
    assert index.tolist() == [1, 1, 1]
    assert dae.reduce_index(f, g, x, z, torch.tensor([0.7], dtype=DT)).index == 1


def test_dae_helpers_give_each_point_its_own_jacobians_for_a_shared_state():
    """A z (or x, xdot) without the batch of the other states is broadcast: each point gets
    the Jacobians of x' = (x1 z, x2), 0 = z x1 - 1 at its own x (dg/dz = x1 per point, not
    their sum over the batch), as with z expanded by hand; batches that do not broadcast are
    refused by name."""

    def f(t, x, z):
        return torch.stack([x[..., 0] * z[..., 0], x[..., 1]], -1)

    def g(t, x, z):
        return z[..., :1] * x[..., :1] - 1

    def F(t, xdot, x, z):
        return torch.cat([xdot - f(t, x, z), g(t, x, z)], -1)

    x = torch.tensor([[1.0, 2.0], [-1.0, 4.0], [5.0, 6.0]], dtype=DT)
    z, x1 = torch.tensor([0.5], dtype=DT), x[:, :1, None]
    jac = dae.linearize_dae(f, g, x, z)
    torch.testing.assert_close(jac["gz"], x1)
    torch.testing.assert_close(jac["fz"], torch.cat([x1, torch.zeros_like(x1)], -2))
    torch.testing.assert_close(jac["gx"], torch.tensor([[[0.5, 0.0]]] * 3, dtype=DT))
    imp = dae.linearize_implicit_dae(F, x[0], x, z)
    torch.testing.assert_close(imp["Fz"][:, 2:], x1)
    torch.testing.assert_close(imp["Fxdot"], torch.eye(3, 2, dtype=DT).expand(3, 3, 2))
    assert dae.is_index1_semi_explicit(g, x[:2], z).tolist() == [True, True]
    assert dae.is_index1(F, x[0], x[:2], z).tolist() == [True, True]
    singular_at_second = torch.tensor([[1.0, 0.0], [0.0, 1.0]], dtype=DT)  # dg/dz = 1, 0
    assert dae.is_index1_semi_explicit(g, singular_at_second, z).tolist() == [True, False]
    assert dae.is_dae(F, x[0], x, z).tolist() == [True] * 3
    assert dae.differential_index(F, x[0], x, z).tolist() == [1, 1, 1]
    assert dae.reduce_index(f, g, x, z).index == 1
    conditions = dae.SingularPerturbation(f, g, nx=2).tikhonov_conditions(x, z)
    assert [c.tolist() for c in conditions] == [[True] * 3, [False, True, False]]
    with pytest.raises(InputValidationError, match=r"linearize_dae: the batches of the states"):
        dae.linearize_dae(f, g, x, torch.zeros(2, 1, dtype=DT))


def test_tikhonov_eq_5_36_converges_to_dae_limit_eq_5_38():
    """Theorem 8 on eq. (5.36), a = 2, x(0) = (1, 1), u = -1: x1 of the ODE approaches the
    solution of the reduced ODE (5.38) as eps -> 0, the error shrinking like eps."""
    t = torch.linspace(0.0, 2.0, 201, dtype=DT)
    x0 = torch.tensor([[1.0, 1.0]], dtype=DT)
    u = -torch.ones(1, dtype=DT)
    a = 2.0
    lam = 1 / a - 1  # (5.38a): x1' = lam x1 + u / a
    x1_limit = (1.0 + (-1 / a) / lam) * torch.exp(lam * t) - (-1 / a) / lam
    errors = []
    for eps in (1e-1, 1e-2, 1e-3):
        plant = SingularlyPerturbedLinear(eps=eps, a=a)
        with torch.no_grad():
            sol = odeint(plant, x0, t, method="radau_iia", stages=3, u=lambda tt: u)
        errors.append(float((sol.x[0, :, 0] - x1_limit).abs().max()))
    assert errors[0] > errors[1] > errors[2]
    assert errors[2] < 2e-3 and errors[0] / errors[2] > 30
    limit = SingularlyPerturbedLinear(a=a)
    pert = dae.SingularPerturbation(limit.f, limit.g, nx=1)
    inv, stable = pert.tikhonov_conditions(_rand(3, 1), _rand(3, 1, seed=1))
    assert bool(inv.all() and stable.all())
    z = pert.slow_manifold(torch.tensor([[0.5]], dtype=DT), torch.zeros(1, 1, dtype=DT))
    torch.testing.assert_close(z, torch.tensor([[0.25]], dtype=DT))  # x2 = x1 / a (eq. 5.38b)
    s = torch.tensor([[0.5, 0.1]], dtype=DT)
    torch.testing.assert_close(
        dae.SingularPerturbation(limit.f, limit.g, nx=1, eps=1e-2)(None, s),
        SingularlyPerturbedLinear(eps=1e-2, a=a)(None, s),
    )


def _two_mass_x2(fun, y0, steps=50, dt=0.01):
    """Exact samples (ZOH = exact for constant u = 1) of a linear model given as a torch rhs
    fun(t, s, u): A, B by sysid.linearize, then the matrix exponential (eq. 1.55)."""
    y0 = torch.tensor([y0], dtype=DT)
    u = torch.ones(1, 1, dtype=DT)
    with torch.no_grad():
        a, b, _, _ = linearize(fun, y0, u)
        drift = fun(None, torch.zeros_like(y0), torch.zeros_like(u))  # affine part (zero)
        assert float(drift.abs().max()) == 0.0
        return simulate_lti_zoh(a[0], b[0], y0[0], torch.ones(steps, 1, dtype=DT), dt)


def test_two_mass_system_reductions_converge_eq_5_41_to_5_44():
    """Fig. 5.3: the ODE (5.41) tends to the ODE (5.43) as m1 -> 0 (error ~ m1), and (5.43)
    tends to the DAE (5.44) as rho/K -> 0 (typo u -> u/K fixed in both reductions)."""
    ref = _two_mass_x2(TwoMassSystem().ode_543, [1.0, 1.0, 0.0])[:, 1]
    err = []
    for m1 in (1e-2, 1e-3, 1e-4):
        x = _two_mass_x2(TwoMassSystem(m1=m1), [1.0, 1.0, 0.0, 0.0])
        err.append(float((x[:, 1] - ref).abs().max()))
    assert err[0] > 5 * err[1] > 25 * err[2]
    dae_err = []
    for rho in (1.0, 0.1, 0.01):
        plant = TwoMassSystem(K=1e3, rho=rho)
        slow = _two_mass_x2(plant.ode_543, [1.0, 1.0, 0.0])[:, 1]

        def reduced(t, s, u, p=plant):  # x1 eliminated through g_544 = 0: x1 = (x2 + u/K) / 2
            z = (s[:, :1] + u / p.K.detach()) / 2
            torch.testing.assert_close(p.g_544(t, s, z, u), torch.zeros_like(z))
            return p.f_544(t, s, z, u)

        limit = _two_mass_x2(reduced, [1.0, 0.0])[:, 0]
        dae_err.append(float((slow - limit).abs().max()))
    assert dae_err[0] > 5 * dae_err[1] > 25 * dae_err[2]


def test_slow_manifold_is_differentiable_and_names_samples_that_do_not_converge():
    """Eq. (5.38b): on the slow manifold of eq. (5.37) x2 = (x1 + u) / a, so dz/dx1 = 1/a,
    dz/du = 1/a and dz/da = -(x1 + u) / a^2 (implicit function theorem); a budget of zero
    Newton steps names the sample that is not on the manifold yet."""
    limit = SingularlyPerturbedLinear(a=2.0)
    pert = dae.SingularPerturbation(limit.f, limit.g, nx=1)
    x = torch.tensor([[0.5], [-1.0]], dtype=DT, requires_grad=True)
    u = torch.tensor([[0.2], [0.1]], dtype=DT, requires_grad=True)
    z = pert.slow_manifold(x, torch.zeros(2, 1, dtype=DT), u)
    torch.testing.assert_close(z, (x + u).detach() / 2.0, rtol=0, atol=1e-12)
    gx, gu, ga = torch.autograd.grad(z.sum(), (x, u, limit.a))
    torch.testing.assert_close(gx, torch.full_like(gx, 0.5), rtol=0, atol=1e-12)
    torch.testing.assert_close(gu, torch.full_like(gu, 0.5), rtol=0, atol=1e-12)
    # the plant's parameter a, read by its bound method g: dz/da = -(x + u) / a^2
    assert ga.item() == pytest.approx(-float((x + u).sum()) / 4.0, rel=1e-12)
    z0 = torch.tensor([[0.35], [0.0]], dtype=DT)  # sample 0 starts on the manifold
    with pytest.raises(ConvergenceError, match=r"slow_manifold: .* batch indices \[\[1\]\]"):
        pert.slow_manifold(x.detach(), z0, u.detach(), max_iter=0)


def test_index_reduction_keeps_the_explicit_time_dependence_of_g():
    """x1' = x2, x2' = z, 0 = x1 - sin t (a prescribed path, index 3): each differentiation
    adds dg/dt, so the reduced equation is z + sin t = 0 and the hidden constraints are
    x1 - sin t and x2 - cos t, sample by sample in a batch; the reduced DAE integrates to the
    path (x1 = sin t, z = -sin t). dg/dt was dropped: z = 0 and x1 = t."""

    def f(t, x, z):
        return torch.stack([x[..., 1], z[..., 0]], -1)

    def g(t, x, z):
        return x[..., :1] - torch.sin(t)

    t = torch.tensor(0.4, dtype=torch.float64)
    reduced = dae.reduce_index(
        f,
        g,
        torch.tensor([0.3, 0.9], dtype=torch.float64),
        torch.tensor([0.1], dtype=torch.float64),
        t=t,
    )
    assert reduced.index == 3
    x = torch.tensor([[0.3, 0.9], [0.1, 0.2]], dtype=torch.float64)
    z = torch.tensor([[0.1], [0.5]], dtype=torch.float64)
    torch.testing.assert_close(reduced.g(t, x, z), z + torch.sin(t))
    hidden = torch.stack([x[:, 0] - torch.sin(t), x[:, 1] - torch.cos(t)], -1)
    torch.testing.assert_close(reduced.consistency(t, x, z), hidden)
    times = torch.linspace(0.0, 2.0, 5, dtype=torch.float64)
    x0, z0 = torch.tensor([0.0, 1.0], dtype=torch.float64), torch.zeros(1, dtype=torch.float64)
    sol = daeint(SemiExplicitDAE(reduced.f, reduced.g), x0, z0, times, rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(sol.x[:, 0], torch.sin(times), atol=1e-9, rtol=0)
    torch.testing.assert_close(sol.z[:, 0], -torch.sin(times), atol=1e-9, rtol=0)


@pytest.mark.parametrize("example", [LinearIndex2DAE, UnitSphereDAE])
def test_reduced_functions_take_no_time_as_time_zero(example):
    plant = example()
    x, z = _rand(3, plant.nx), _rand(3, plant.nz, seed=1)
    reduced = dae.reduce_index(plant.f, plant.g, x, z)
    t0 = torch.tensor(0.0, dtype=DT)
    torch.testing.assert_close(reduced.g(None, x, z), plant.reduced_g(t0, x, z))
    torch.testing.assert_close(reduced.consistency(None, x, z), plant.g(t0, x, z)[..., :1])
    torch.testing.assert_close(reduced.g(0.0, x, z), reduced.g(t0, x, z))


@pytest.mark.parametrize("scenario", dae_scenarios(), ids=lambda sc: sc.name)
def test_zoo_dae_jacobians_match_central_differences_and_poles_match_the_pencil(
    scenario, central_jacobian
):
    """Every zoo DAE: the Jacobians of linearize_dae / linearize_implicit_dae (eq. 5.31-5.32)
    at two points equal central differences of f, g (or F); the
    eigenvalues of eliminate_linear's A (eq. 5.30) are the finite generalised eigenvalues of
    the pencil ([[fx, fz], [gx, gz]], diag(I, 0)) by scipy's QZ (the scenarios are index-1
    forms: dg/dz is invertible)."""
    plant = scenario.build().to(DT)
    problem = scenario.problem(plant)
    x = torch.tensor(scenario.x0, dtype=DT).repeat(2, 1)
    z = torch.tensor(scenario.z0, dtype=DT).repeat(2, 1)
    x[1] *= 0.9
    z[1] += 0.05
    t = torch.tensor(0.3, dtype=DT)
    u = None if scenario.u is None else scenario.u(t).reshape(1, -1).repeat(2, 1)
    extra = () if u is None else (u,)
    if isinstance(problem, ImplicitDAE):
        xdot = torch.full_like(x, 0.1)
        jac = dae.linearize_implicit_dae(problem.F, xdot, x, z, u, t=t)
        points = {"Fxdot": xdot, "Fx": x, "Fz": z, "Fu": u}
        for name, point in points.items():
            if point is not None:
                ref = central_jacobian(lambda: problem.F(t, xdot, x, z, *extra), point)
                torch.testing.assert_close(jac[name], ref, rtol=1e-7, atol=1e-8)
        return
    jac = dae.linearize_dae(problem.f, problem.g, x, z, u, t=t)
    for name, fn in (("f", problem.f), ("g", problem.g)):
        for var, point in (("x", x), ("z", z), ("u", u)):
            if point is not None:
                ref = central_jacobian(lambda fn=fn: fn(t, x, z, *extra), point)
                torch.testing.assert_close(jac[name + var], ref, rtol=1e-7, atol=1e-8)
    n, m = x.shape[-1], z.shape[-1]
    for k in range(2):
        ar = dae.eliminate_linear(
            jac["fx"][k], jac["fu"][k], jac["fz"][k], jac["gx"][k], jac["gu"][k], jac["gz"][k]
        )[0]
        pencil = np.block(
            [
                [jac["fx"][k].numpy(), jac["fz"][k].numpy()],
                [jac["gx"][k].numpy(), jac["gz"][k].numpy()],
            ]
        )
        mass = np.diag([1.0] * n + [0.0] * m)
        values = scipy.linalg.eigvals(pencil, mass)
        finite = np.sort_complex(values[np.isfinite(values)])
        assert finite.size == n
        ours = np.sort_complex(np.linalg.eigvals(ar.numpy()))
        np.testing.assert_allclose(ours, finite, rtol=1e-8, atol=1e-8 * (1 + abs(finite).max()))
