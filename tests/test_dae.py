"""Implicit ODEs and index-1 DAEs with daeint (notes §5.1-5.4, §7.5-7.6): reduced-ODE
closed forms, Tikhonov limit, index checks, consistent initialisation, IFT gradients."""

import math
import warnings

import pytest
import torch

from integrators import (
    DAELayer,
    HighIndexError,
    HighIndexWarning,
    ImplicitDAE,
    ImplicitODE,
    InputValidationError,
    SemiExplicitDAE,
    Status,
    daeint,
    odeint,
    solve_implicit_ode,
)
from sysid.zoo.dae import AlgebraicStateDAE

pytestmark = pytest.mark.usefixtures("float64_default")

A_COEF = 2.0
U = 1.0


def eq537():
    """Notes eq. 5.37: x1' = -x1 + x2, 0 = x1 - a x2 + u (x = x1, z = x2)."""
    return SemiExplicitDAE(lambda t, x, z, u: -x + z, lambda t, x, z, u: x - A_COEF * z + u)


def eq537_exact(t, x0):
    """Reduced ODE eq. 5.38: x1' = (1/a - 1) x1 + u/a, x2 = (x1 + u)/a."""
    lam = 1 / A_COEF - 1
    x_inf = -(U / A_COEF) / lam
    x1 = x_inf + (x0 - x_inf) * torch.exp(lam * t)
    return x1, (x1 + U) / A_COEF


@pytest.mark.parametrize("adaptive", [True, False])
def test_semi_explicit_dae_537_matches_reduced_ode_538(adaptive):
    x0 = torch.tensor([[1.0], [0.5]])
    z0 = torch.tensor([[0.75], [0.75]])  # consistent: (x0 + u) / a
    t = torch.linspace(0, 2, 11)
    sol = daeint(
        eq537(),
        x0,
        z0,
        t,
        u=lambda tt: torch.full((1,), U),
        adaptive=adaptive,
        rtol=1e-8,
        atol=1e-10,
        substeps=5,
    )
    x1, x2 = eq537_exact(t, x0)
    assert sol.success
    assert float((sol.x[..., 0] - x1).abs().max()) < 1e-7
    assert float((sol.z[..., 0] - x2).abs().max()) < 1e-7
    assert float(sol.stats.extra["z0_correction"][1]) == pytest.approx(0.0, abs=1e-14)


def test_tikhonov_limit_of_536_approaches_dae_537():
    """Theorem 8: the stiff ODE eq. 5.36 (eps x2' = x1 - a x2 + u) tends to the DAE eq. 5.37;
    away from the initial layer the difference is O(eps)."""
    t = torch.linspace(0, 2, 5)
    x0 = torch.tensor([[0.2, 1.0]])
    dae = daeint(
        eq537(), x0[:, :1], x0[:, 1:], t, u=lambda tt: torch.full((1,), U), rtol=1e-9, atol=1e-11
    )
    gaps = []
    for eps in (1e-3, 1e-4):
        ode = solve_implicit_ode(
            lambda tt, x, e=eps: torch.stack(
                [-x[..., 0] + x[..., 1], (x[..., 0] - A_COEF * x[..., 1] + U) / e], -1
            ),
            x0,
            t,
            "radau_iia",
            rtol=1e-9,
            atol=1e-11,
        )
        gaps.append(float((ode.x[0, 1:, 0] - dae.x[0, 1:, 0]).abs().max()))
    assert gaps[1] < 0.2 * gaps[0] and gaps[1] < 1e-3


def eq546(t, xd, x, z, u):
    """Notes eq. 5.46: F = [x1' - z; x2' - x1; x1' + x2 - u] (index 1, Theorem 9)."""
    return torch.cat([xd[..., :1] - z, xd[..., 1:] - x[..., :1], xd[..., :1] + x[..., 1:] - u], -1)


@pytest.mark.parametrize(
    "method,stages,adaptive", [("radau_iia", 3, True), ("gauss_legendre", 2, False)]
)
def test_fully_implicit_dae_546_matches_reduced_ode_547(method, stages, adaptive):
    """Eq. 5.47: z = u - x2, x2' = x1, x1' = u - x2 -> forced harmonic oscillator."""
    u = 0.5
    x0 = torch.tensor([[0.3, 0.1]])
    t = torch.linspace(0, 3, 7)
    sol = daeint(
        ImplicitDAE(eq546),
        x0,
        torch.zeros(1, 1),
        t,
        u=lambda tt: torch.full((1,), u),
        method=method,
        stages=stages,
        adaptive=adaptive,
        substeps=20,
        rtol=1e-9,
        atol=1e-11,
    )
    x2 = u + (0.1 - u) * torch.cos(t) + 0.3 * torch.sin(t)
    x1 = -(0.1 - u) * torch.sin(t) + 0.3 * torch.cos(t)
    assert sol.success
    assert float((sol.x[0, :, 0] - x1).abs().max()) < 1e-7
    assert float((sol.x[0, :, 1] - x2).abs().max()) < 1e-7
    # Gauss's algebraic states come from the stage polynomial at tau = 1 (stage order s):
    # order reduction, as expected for collocation on DAEs
    z_tol = 1e-7 if method == "radau_iia" else 1e-4
    assert float((sol.z[0, :, 0] - (u - x2)).abs().max()) < z_tol
    # the inconsistent guess z0 = 0 was corrected to z(0) = u - x2(0) = 0.4
    assert float(sol.stats.extra["z0_correction"][0]) == pytest.approx(0.4, abs=1e-10)
    assert any("inconsistent" in m for m in sol.messages)


def test_index3_dae_548_raises_high_index_error():
    """Eq. 5.48 (x2 = u appears without z): [dF/dx' dF/dz] is singular -> index 3."""

    def F(t, xd, x, z, u):
        return torch.cat([xd[..., :1] - z, xd[..., 1:] - x[..., :1], x[..., 1:] - u], -1)

    with pytest.raises(HighIndexError, match="index > 1"):
        daeint(
            ImplicitDAE(F),
            torch.tensor([[0.3, 0.5]]),
            torch.zeros(1, 1),
            torch.linspace(0, 1, 3),
            u=lambda tt: torch.full((1,), 0.5),
        )


def test_index2_semi_explicit_dae_raises():
    """x' = z, 0 = x - sin t: dg/dz = 0 (Corollary 1 fails; index 2). The message lists the
    samples; an unbatched problem is sample (0,)."""
    prob = SemiExplicitDAE(lambda t, x, z: z, lambda t, x, z: x - torch.sin(t))
    with pytest.raises(HighIndexError, match=r"dg/dz .* for samples \[\(0,\), \(1,\)\]"):
        daeint(prob, torch.zeros(2, 1), torch.ones(2, 1), torch.linspace(0, 1, 3))
    with pytest.raises(HighIndexError, match=r"for samples \[\(0,\)\]"):
        daeint(prob, torch.zeros(1), torch.ones(1), torch.linspace(0, 1, 3))


def test_implicit_ode_with_an_algebraic_state_points_to_implicit_dae():
    """Eq. 5.2 as ImplicitODE (x2 never differentiated, index 1): dF/dx' is singular; the
    error says to put x2 in z of an ImplicitDAE, and that form integrates to the closed form
    x1 = e^{5 t}, x2 = 3 x1 (x1' = 2 x1 + x2, 0 = 3 x1 - x2)."""
    model = AlgebraicStateDAE()
    t = torch.linspace(0, 0.4, 3)
    with pytest.raises(HighIndexError) as info:
        daeint(
            ImplicitODE(lambda tt, xd, x: model.residual(tt, xd, x, None)),
            torch.tensor([1.0, 3.0]),
            None,
            t,
        )
    msg = str(info.value)
    for words in ("not an implicit ODE", "dF/dx'", "ImplicitDAE F(t, x', x, z)", "in z"):
        assert words in msg, msg
    assert "the DAE is of index > 1" not in msg

    def F(tt, xd, x, z):
        return model.residual(
            tt, torch.cat([xd, torch.zeros_like(z)], -1), torch.cat([x, z], -1), None
        )

    sol = daeint(
        ImplicitDAE(F), torch.tensor([1.0]), torch.tensor([3.0]), t, rtol=1e-10, atol=1e-12
    )
    torch.testing.assert_close(sol.x[:, 0], torch.exp(5 * t), rtol=1e-8, atol=0)
    torch.testing.assert_close(sol.z[:, 0], 3 * torch.exp(5 * t), rtol=1e-8, atol=0)


def test_index_check_during_integration_warns_and_sets_status():
    """0 = u z - x with a held input u: sample 1's u drops to 0 at t = 1, where dg/dz = u
    loses rank (the DAE stops being index 1); sample 0 keeps u = 1 and must finish."""
    t = torch.linspace(0, 2, 11)
    u = torch.stack([torch.ones(11), (t < 0.99).double()])[..., None]  # (2, T, 1)
    prob = SemiExplicitDAE(lambda t, x, z, u: -x + 0 * z, lambda t, x, z, u: u * z - x)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        sol = daeint(
            prob, torch.ones(2, 1), torch.ones(2, 1), t, u=u, adaptive=False, index_check_every=1
        )
    assert any(issubclass(w.category, HighIndexWarning) for w in caught)
    assert sol.status[0] == Status.SUCCESS and sol.status[1] != Status.SUCCESS
    assert any("index > 1" in m and "(1,)" in m and "t = 1" in m for m in sol.messages)
    torch.testing.assert_close(sol.z[0, :, 0], torch.exp(-t), rtol=1e-6, atol=1e-6)


def test_implicit_ode_equals_explicit_form():
    """Mass-matrix form (eq. 7.49) M x' = f(x) with M = [[2, 1], [0, 1]] vs x' = M^-1 f."""
    M = torch.tensor([[2.0, 1.0], [0.0, 1.0]])

    def f(x):
        return torch.stack([x[..., 1], -torch.sin(x[..., 0])], -1)

    x0 = torch.tensor([[1.0, 0.0], [0.2, 0.3]])
    t = torch.linspace(0, 3, 7)
    implicit = daeint(
        ImplicitODE(lambda t, xd, x: xd @ M.T - f(x)), x0, None, t, rtol=1e-10, atol=1e-12
    )
    Minv = torch.linalg.inv(M)
    explicit = solve_implicit_ode(
        lambda t, x: f(x) @ Minv.T, x0, t, "radau_iia", rtol=1e-10, atol=1e-12
    )
    assert implicit.z is None and implicit.success
    torch.testing.assert_close(implicit.x, explicit.x, rtol=1e-8, atol=1e-8)
    with pytest.raises(InputValidationError):
        daeint(ImplicitODE(lambda t, xd, x: xd - x), x0, torch.zeros(2, 1), t)


class Coupled(torch.nn.Module):
    """x' = -k0 x + z, 0 = x - k1 z + sin(x) (index 1 for k1 != 0)."""

    def __init__(self):
        super().__init__()
        self.k = torch.nn.Parameter(torch.tensor([1.5, 3.0]))

    def f(self, t, x, z):
        return -self.k[0] * x + z

    def g(self, t, x, z):
        return x - self.k[1] * z + torch.sin(x)

    def forward(self, t, x, z):
        return self.g(t, x, z)


@pytest.mark.parametrize("adaptive", [False, True])
def test_dae_ift_gradients_match_central_differences(adaptive, central_difference):
    model = Coupled()
    prob = SemiExplicitDAE(model.f, model.g)
    x0 = torch.tensor([[1.0], [0.4]], requires_grad=True)
    t = torch.linspace(0, 1, 3)

    def loss(x0_):
        tol = 1e-12 if not adaptive else 1e-10
        sol = daeint(
            prob, x0_, torch.zeros(2, 1), t, adaptive=adaptive, substeps=8, rtol=tol, atol=tol
        )
        return sol.x[..., -1, :].square().sum() + sol.z[..., -1, :].sum()

    gx, gk = torch.autograd.grad(loss(x0), (x0, model.k))
    fd_k = central_difference(lambda: loss(x0), model.k)
    fd_x = central_difference(lambda: loss(x0), x0)
    rel = 1e-6 if not adaptive else 1e-5
    assert float((gk - fd_k).abs().max() / gk.abs().max()) < rel
    assert float((gx - fd_x).abs().max() / gx.abs().max()) < rel


def test_dae_layer_trains_module_parameters():
    model = Coupled()
    layer = DAELayer(
        SemiExplicitDAE(model.f, model),
        t=torch.linspace(0, 1, 3),
        return_solution=False,
        adaptive=False,
        substeps=4,
    )
    assert {id(p) for p in layer.parameters()} == {id(model.k)}
    x = layer(torch.tensor([[1.0]]), torch.zeros(1, 1))
    x[..., -1, :].sum().backward()
    ref = Coupled()
    sol = daeint(
        SemiExplicitDAE(ref.f, ref.g),
        torch.tensor([[1.0]]),
        torch.zeros(1, 1),
        torch.linspace(0, 1, 3),
        adaptive=False,
        substeps=4,
    )
    sol.x[..., -1, :].sum().backward()
    torch.testing.assert_close(model.k.grad, ref.k.grad)
    assert float(model.k.grad.abs().sum()) > 0


def test_sampled_input_and_batch_of_parameters():
    """Eq. 5.37 with a zero-order-hold input sampled on t and a batch of a-values."""
    a = torch.tensor([[2.0], [4.0]])
    prob = SemiExplicitDAE(lambda t, x, z, u: -x + z, lambda t, x, z, u: x - a * z + u)
    t = torch.linspace(0, 1, 5)
    u = torch.ones(5, 1)
    sol = daeint(prob, torch.ones(2, 1), torch.zeros(2, 1), t, u=u, rtol=1e-9, atol=1e-11)
    lam = 1 / a - 1
    x_inf = -(1 / a) / lam
    exact = x_inf + (1 - x_inf) * torch.exp(lam * t)
    assert float((sol.x[..., 0] - exact).abs().max()) < 1e-7
    assert math.isclose(float(sol.z[1, 0, 0]), 0.5, abs_tol=1e-12)


def _two_mass_544_exact(x0, t, u, m2, K, rho):
    """Eq. 5.44 (x = (x2, x2'), z = x1, 0 = x2 - 2 z + u/K) with a zero-order-hold u: on each
    sample interval z = (x2 + u_k/K)/2 and x' = A x + b u_k, A = [[0, 1], [-K/(2 m2),
    -rho/m2]], b = (0, 1/(2 m2)): exact steps by the matrix exponential of [[A, b], [0, 0]]."""
    M = torch.zeros(3, 3)
    M[0, 1], M[1, 0], M[1, 1], M[1, 2] = 1.0, -K / (2 * m2), -rho / m2, 1 / (2 * m2)
    xs, x = [x0], x0
    for k in range(len(t) - 1):
        x = (torch.linalg.matrix_exp(M * (t[k + 1] - t[k])) @ torch.cat([x, u[k]]))[:2]
        xs.append(x)
    return torch.stack(xs)


@pytest.mark.parametrize("form", ["semi_explicit", "implicit"])
def test_zoh_input_jumps_restart_the_step_derivative(form):
    """A zero-order-hold input makes z jump at every sample time. The adaptive loop stops
    there and must restart with z and x' consistent with the new input: it carried the last
    stage's x' (old input) into the next error estimate, whose error then fell only like h,
    and 6 of 9 starts within 2e-5 of each other stopped with STEP_TOO_SMALL at t = 0.8.
    Truth: the exact ZOH solution of the reduced linear ODE (eq. 5.44); z at the sample times
    as the fixed-step driver reports it."""
    from sysid.zoo import TwoMassSystem

    m2, K, rho = 1.3, 20.0, 1.5
    plant = TwoMassSystem(m2=m2, K=K, rho=rho)
    if form == "semi_explicit":
        problem = SemiExplicitDAE(plant.f_544, plant.g_544)
    else:
        problem = ImplicitDAE(
            lambda t, xd, x, z, u: torch.cat(
                [xd - plant.f_544(t, x, z, u), plant.g_544(t, x, z, u)], -1
            )
        )
    t = torch.linspace(0, 1.0, 6)
    u = torch.sin(3 * t)[:, None] * 0.7 + 0.2
    x0 = torch.tensor([0.3, -0.1]) + torch.linspace(0, 2e-5, 9)[:, None] * torch.tensor([0, 1])
    with torch.no_grad():
        sol = daeint(problem, x0, torch.zeros(9, 1), t, u=u, rtol=1e-9, atol=1e-11)
    assert (sol.status == Status.SUCCESS).all(), sol.messages
    exact = torch.stack([_two_mass_544_exact(x, t, u, m2, K, rho) for x in x0])
    assert float((sol.x - exact).abs().max()) < 1e-9
    # z at a sample time holds the input of the interval ending there, as at fixed steps
    held = torch.cat([u[:1, 0], u[:-1, 0]])
    torch.testing.assert_close(sol.z[..., 0], (exact[..., 0] + held / K) / 2, rtol=0, atol=1e-9)
    with torch.no_grad():
        fixed = daeint(problem, x0, torch.zeros(9, 1), t, u=u, adaptive=False, substeps=40)
    torch.testing.assert_close(sol.z, fixed.z, rtol=0, atol=1e-7)


def test_a_stopped_member_does_not_stop_the_gradient_of_the_others():
    """0 = z^2 - x with x' = -1: the member from x0 = 1 heads for the impasse x = 0 (dg/dz = 2z
    singular) at t = 1 and runs out of step attempts on the way; the member from x0 = 4 runs to
    t = 2 with z = sqrt(4 - t). With autograd on, the output z of the stopped member, solved
    at placeholder zeros, raised from a singular LU factorisation for the whole batch. Now the
    statuses are those of a run without autograd and the healthy member's gradient is the
    closed form d(x + z)(2)/dx0 = 1 + 1 / (2 sqrt 2)."""
    problem = SemiExplicitDAE(lambda t, x, z: -torch.ones_like(x), lambda t, x, z: z * z - x)
    t = torch.linspace(0, 2, 9)
    x0 = torch.tensor([[1.0], [4.0]], requires_grad=True)
    z0 = torch.tensor([[1.0], [2.0]])
    sol = daeint(problem, x0, z0, t, rtol=1e-8, atol=1e-10, max_steps=40)
    assert sol.status.tolist() == [int(Status.MAX_STEPS), int(Status.SUCCESS)]
    (grad,) = torch.autograd.grad(sol.x[1, -1, 0] + sol.z[1, -1, 0], x0)
    assert grad[0, 0] == 0.0
    assert math.isclose(float(grad[1, 0]), 1 + 1 / (2 * math.sqrt(2)), rel_tol=1e-6)


# ------------------------------------------- fully implicit DAE losing index 1 on the way
def _crossing_dae(a, rhs_x):
    """Fully implicit DAE F(t, x', x, z) = 0 (eq. 7.53) with one state x and one algebraic z:

        F1 = x' - rhs_x(x) - (z - sin t),   F2 = phi(x) (z - sin t),   phi(x) = max(1 - x, 0).

    Index check matrix [dF/dx', dF/dz] = [[1, -1], [0, phi(x)]] (Theorem 9, eq. 5.53): index
    1 while x < 1, rank deficient once x reaches 1. On the index-1 part z = sin t and
    x' = rhs_x(x) (the reduced ODE)."""

    def F(t, xd, x, z):
        w = torch.sin(t)
        return torch.cat([xd - rhs_x(x) - (z - w), torch.clamp(1 - x, min=0.0) * (z - w)], -1)

    return ImplicitDAE(F)


def _index_messages(sol):
    """(sample, time) of every index > 1 message, parsed from ``sol.messages``."""
    import re

    found = []
    for m in sol.messages:
        if "index > 1" in m:
            when = float(re.search(r"at t = ([0-9.e+-]+)", m).group(1))
            found.append((re.search(r"samples \[(.*?)\]", m).group(1), when))
    return found


def test_implicit_dae_losing_index_one_during_adaptive_run_names_sample_and_time():
    """x' = a - x, x(0) = 0 (x = a (1 - e^{-t})), per sample a = 0.5 and 2 (batch of 2):
    sample 1 reaches x = 1 at t* = ln 2, where [dF/dx', dF/dz] loses rank; sample 0 never
    does. Adaptive Radau IIA with the index re-checked at every step start
    (index_check_every=1): HighIndexWarning, sample 1 stopped (NEWTON_FAILED) with a message
    naming sample (1,) and its own time, the start of its first step past t* (within 5e-2 of
    t*), not sample 0's time, its outputs NaN after that time; sample 0 finishes
    on its closed form (x and z = sin t to 1e-7; measured 5e-10, 4e-9), sample 1 matches its
    closed form up to t* (the solution is index 1 there)."""
    a = torch.tensor([[0.5], [2.0]])
    t = torch.linspace(0, 2, 41)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        sol = daeint(
            _crossing_dae(a, lambda x: a - x),
            torch.zeros(2, 1),
            torch.zeros(2, 1),
            t,
            adaptive=True,
            index_check_every=1,
            rtol=1e-8,
            atol=1e-10,
        )
    assert any(issubclass(w.category, HighIndexWarning) for w in caught)
    assert sol.status.tolist() == [Status.SUCCESS, Status.NEWTON_FAILED]
    t_star = math.log(2.0)
    found = _index_messages(sol)
    assert [s for s, _ in found] == ["(1,)"], sol.messages
    t_msg = found[0][1]  # measured 0.70372 (t* = 0.69315)
    assert t_star < t_msg < t_star + 5e-2, (found, t_star)
    # the message's time is where sample 1 stopped: its outputs after it are NaN (x and z)
    late = t > t_msg
    assert bool(torch.isnan(sol.x[1, late]).all() and torch.isnan(sol.z[1, late]).all())
    assert bool(torch.isfinite(sol.x[1, ~late]).all() and torch.isfinite(sol.z[1, ~late]).all())
    exact = a * (1 - torch.exp(-t))
    assert float((sol.x[0, :, 0] - exact[0]).abs().max()) < 1e-7
    assert float((sol.z[0, :, 0] - torch.sin(t)).abs().max()) < 1e-7
    before = t < t_star
    assert float((sol.x[1, before, 0] - exact[1, before]).abs().max()) < 1e-7


def test_implicit_dae_losing_index_one_on_a_fixed_grid_names_sample_and_time():
    """x' = a (x = a t from x(0) = 0) with a = 0.25 and 2: sample 1 reaches x = 1 at t = 0.5,
    a point of the fixed grid, as the held input of the semi-explicit test above. Gauss-
    Legendre (interior nodes: no stage of the step ending at 0.5 sits at x = 1, where z's
    stage would be undetermined and Newton, not the rank test, would stop the sample). The
    rank test at the step start t = 0.5 stops sample 1 with a HighIndexWarning and a message
    naming sample (1,) and t = 0.5 (where solving F2 = 0 for z at the output time also
    fails); sample 0 (x <= 0.5) finishes with x = a t, z = sin t."""
    a = torch.tensor([[0.25], [2.0]])
    t = torch.linspace(0, 2, 21)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        sol = daeint(
            _crossing_dae(a, lambda x: a + 0 * x),
            torch.zeros(2, 1),
            torch.zeros(2, 1),
            t,
            method="gauss_legendre",
            stages=2,
            adaptive=False,
            index_check_every=1,
            rtol=1e-10,
            atol=1e-12,
        )
    assert any(issubclass(w.category, HighIndexWarning) for w in caught)
    assert sol.status.tolist() == [Status.SUCCESS, Status.NEWTON_FAILED]
    assert _index_messages(sol) == [("(1,)", 0.5)], sol.messages
    torch.testing.assert_close(sol.x[0, :, 0], 0.25 * t, rtol=0, atol=1e-12)
    # z at the output times solves F2 = phi(x) (z - sin t) = 0 there: z = sin t
    torch.testing.assert_close(sol.z[0, :, 0], torch.sin(t), rtol=0, atol=1e-10)
    before = t <= 0.5
    torch.testing.assert_close(sol.x[1, before, 0], 2 * t[before], rtol=0, atol=1e-12)


def test_consistent_initial_algebraic_state_gradient_reaches_captured_tensors():
    """0 = z - p x^2 with p a captured tensor (not a module parameter): the consistent
    z(t0) = p x0^2 has dz(t0)/dp = x0^2 and dz(t0)/dx0 = 2 p x0 (the whole output z has the
    same gradients at t0 whatever the integration does later)."""
    p = torch.tensor(0.8, dtype=torch.float64, requires_grad=True)
    x0 = torch.tensor([[0.5], [1.5]], dtype=torch.float64, requires_grad=True)
    problem = SemiExplicitDAE(lambda t, x, z: -z, lambda t, x, z: z - p * x**2)
    sol = daeint(problem, x0, torch.zeros(2, 1), torch.linspace(0.0, 1.0, 3))
    g_p, g_x0 = torch.autograd.grad(sol.z[:, 0, 0].sum(), (p, x0))
    torch.testing.assert_close(g_p, (x0.detach() ** 2).sum())
    torch.testing.assert_close(g_x0, 2 * 0.8 * x0.detach())


def _cubic_constraint_reference():
    """x1' = -0.7 x1 + z + cos t, x2' = x1 - 0.5 x2, 0 = z + z^3 - x1: x by scipy DOP853 at
    1e-13 on the reduced ODE (z from the cubic by Newton), z from the cubic at those x."""
    from scipy.integrate import solve_ivp

    def z_of(x1):
        z = x1
        for _ in range(60):
            z -= (z + z**3 - x1) / (1 + 3 * z * z)
        return z

    t = [0.0, 0.4, 1.0, 2.5]
    ref = solve_ivp(
        lambda t, x: [-0.7 * x[0] + z_of(x[0]) + math.cos(t), x[0] - 0.5 * x[1]],
        (0.0, 2.5),
        [1.5, -0.3],
        t_eval=t,
        method="DOP853",
        rtol=1e-13,
        atol=1e-13,
    )
    x = torch.tensor(ref.y.T)
    return torch.tensor(t), x, torch.tensor([[z_of(float(v))] for v in x[:, 0]])


@pytest.mark.parametrize("method", ["gauss_legendre", "implicit_midpoint"])
def test_algebraic_states_at_the_output_times_keep_the_order_of_x(method, central_difference):
    """Tableaus without a stage at the step's end (Gauss-Legendre, order 4; implicit
    midpoint, order 2) would report z from the stage polynomial extrapolated to the step's
    end, of lower order, with g(x, z) != 0 (Gauss: z errors 8.5e-4, 2.5e-4, 6.7e-5 at 10, 20,
    40 substeps, order 2); z solved from g at the output times has the order of x and
    satisfies g, and its gradient matches central differences."""
    t, x_ref, z_ref = _cubic_constraint_reference()
    k = torch.tensor(0.7, requires_grad=True)

    def problem(k):
        def f(t, x, z):
            return torch.stack(
                [-k * x[..., 0] + z[..., 0] + torch.cos(t), x[..., 0] - 0.5 * x[..., 1]], -1
            )

        return SemiExplicitDAE(f, lambda t, x, z: z + z**3 - x[..., :1])

    def run(k, substeps):
        x0 = torch.tensor([1.5, -0.3])
        return daeint(problem(k), x0, torch.tensor([0.5]), t, method=method, adaptive=False,
                      substeps=substeps, rtol=1e-12, atol=1e-12)  # fmt: skip

    order = 4 if method == "gauss_legendre" else 2
    errors = []
    for substeps in (10, 20, 40):
        sol = run(k.detach(), substeps)
        assert float((sol.z + sol.z**3 - sol.x[..., :1]).abs().max()) < 1e-9
        errors.append(float((sol.z - z_ref).abs().max()))
        assert errors[-1] <= 2 * float((sol.x - x_ref).abs().max())  # z as good as x
    observed = math.log2(errors[1] / errors[2])
    assert abs(observed - order) < 0.3, errors
    (grad,) = torch.autograd.grad(run(k, 10).z[-1, 0], k)
    fd = central_difference(lambda: run(k, 10).z[-1, 0], k)
    assert abs(float(grad - fd)) < 1e-6 * abs(float(fd))


def test_layers_keep_output_times_given_as_a_list_exact():
    """ODELayer and DAELayer with t a Python list: the times stay the list's float64 values
    (they were stored in torch's default float32, 0.1 -> 0.10000000149, shifting the outputs
    by 1e-8 relative), so the layers give odeint's / daeint's results on the same list, and
    module dtype conversions (float(), double(), to(dtype)) leave them exact."""
    from integrators import ODELayer, odeint

    times = [0.0, 0.1, 0.7]
    x0 = torch.tensor([1.0])
    with torch.no_grad():
        ode = ODELayer(lambda t, x: -x, t=times, method="dopri5", rtol=1e-12, atol=1e-12)(x0)
    assert ode.t.tolist() == times
    torch.testing.assert_close(ode.x[:, 0], torch.exp(-torch.tensor(times)), rtol=1e-12, atol=0)
    ref = odeint(lambda t, x: -x, x0, times, method="dopri5", rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(ode.x, ref.x, rtol=0, atol=0)
    prob = SemiExplicitDAE(lambda t, x, z: -x + z, lambda t, x, z: x - 2 * z + 1)
    layer = DAELayer(prob, t=times, adaptive=False, substeps=8)
    with torch.no_grad():
        sol = layer(torch.tensor([1.0]), torch.zeros(1))
    assert sol.t.tolist() == times
    ref = daeint(prob, torch.tensor([1.0]), torch.zeros(1), times, adaptive=False, substeps=8)
    torch.testing.assert_close(sol.x, ref.x, rtol=0, atol=0)
    # module dtype conversions keep the times exact: float() then double() gave
    # 0.10000000149011612 (float32 rounding), so a float64 run after a float32 one was shifted
    for converted in (layer.float().double(), layer.to(torch.float16).to(torch.float64)):
        assert converted.t.dtype == torch.float64 and converted.t.tolist() == times
    with torch.no_grad():
        again = (
            ODELayer(lambda t, x: -x, t=times, method="dopri5", rtol=1e-12, atol=1e-12)
            .float()
            .double()(x0)
        )
        single = ODELayer(lambda t, x: -x, t=times, method="dopri5").float()(x0.float())
    torch.testing.assert_close(again.x, ode.x, rtol=0, atol=0)
    assert single.x.dtype == torch.float32
    torch.testing.assert_close(single.x, ode.x.float(), rtol=1e-5, atol=1e-6)


def test_dae_layer_refuses_a_bare_function_by_name():
    """DAELayer(f) with f(t, x) a plain function raised AttributeError ('function' object has
    no attribute 'modules'); it names the problem classes it needs and ODELayer."""
    t = torch.linspace(0.0, 1.0, 3)
    with pytest.raises(InputValidationError, match=r"DAELayer expects an ImplicitODE.*ODELayer"):
        DAELayer(lambda t, x: -x, t=t)


@pytest.mark.parametrize("method", ["gauss_legendre", "radau_iia"])
def test_gradient_reaches_a_sampled_input_through_the_algebraic_state(method):
    """x' = -2 x + z, 0 = z - u: the algebraic state is the input, so the DAE is the ODE
    x' = -2 x + u, and with the same fixed steps both give the same discrete solution and
    the same gradient with respect to the input samples, which central differences confirm.
    The stacked stage inputs were built without graph in the Newton iterations: u.grad was
    None."""
    dae = SemiExplicitDAE(lambda t, x, z, u: -2.0 * x + z, lambda t, x, z, u: z - u)
    t = torch.linspace(0.0, 1.0, 5, dtype=torch.float64)
    u0 = torch.tensor([[0.3], [-0.7], [1.1], [0.2], [0.5]], dtype=torch.float64)
    x0 = torch.ones(1, dtype=torch.float64)
    options = (
        dict(method=method, adaptive=False, substeps=10)
        if method == "radau_iia"
        else dict(method=method, substeps=10)
    )

    def final(u, dae_form=True):
        if dae_form:
            return daeint(dae, x0, torch.zeros(1, dtype=torch.float64), t, u=u, **options).x[-1, 0]
        return odeint(lambda t, x, u: -2.0 * x + u, x0, t, u=u, **options).x[-1, 0]

    u = u0.clone().requires_grad_()
    (grad,) = torch.autograd.grad(final(u), u)
    (ode_grad,) = torch.autograd.grad(final(u, dae_form=False), u)
    torch.testing.assert_close(grad, ode_grad, rtol=1e-10, atol=1e-12)
    h = 1e-6
    with torch.no_grad():
        fd = torch.stack(
            [
                (final(u0 + h * e[:, None]) - final(u0 - h * e[:, None])) / (2 * h)
                for e in torch.eye(5).double()
            ]
        )
    torch.testing.assert_close(grad[:, 0], fd, rtol=1e-6, atol=1e-9)
    assert float(grad[:-1].abs().min()) > 0.01


@pytest.mark.parametrize("kind", ["semi-explicit", "implicit"])
@pytest.mark.parametrize("batch", [(), (3,)])
def test_adaptive_radau_solves_z_at_output_times_inside_a_step(kind, batch):
    """x' = -k x, 0 = z - sin(20 t) - x: z varies much faster than x, so the steps the error
    estimate allows are long for z's stage polynomial, and z interpolated between its nodes
    was off by 1.1e-2 at rtol 1e-6 (|g| the same, x 4.6e-8). z at an output time inside a
    step is solved from the algebraic equations at the interpolated x (the fixed-step
    drivers' rule): as accurate as x, g satisfied, one trajectory or a batch, both DAE forms;
    its gradient equals central differences."""
    t = torch.linspace(0.0, 2.0, 21)
    k = torch.linspace(0.5, 1.5, 3)[: (batch[0] if batch else 1)].reshape(*batch, 1)

    def problem(k):
        def g(t, x, z):
            return z - torch.sin(20 * t) - x

        if kind == "semi-explicit":
            return SemiExplicitDAE(lambda t, x, z: -k * x, g)
        return ImplicitDAE(lambda t, xdot, x, z: torch.cat([xdot + k * x, g(t, x, z)], -1))

    def run(k):
        x0 = torch.ones(*batch, 1)
        return daeint(problem(k), x0, x0.clone(), t, method="radau_iia", rtol=1e-6, atol=1e-9)

    sol = run(k)
    x_exact = torch.exp(-k[..., None, :] * t[:, None])
    z_exact = torch.sin(20 * t)[:, None] + x_exact
    x_error = float((sol.x - x_exact).abs().max())
    assert x_error < 1e-6
    assert float((sol.z - z_exact).abs().max()) <= 2 * x_error
    assert float((sol.z - torch.sin(20 * t)[:, None] - sol.x).abs().max()) < 1e-12
    if batch == ():
        k_var = k.clone().requires_grad_(True)
        (grad,) = torch.autograd.grad(run(k_var).z[..., 7, 0].sum(), k_var)
        step = 1e-6
        fd = (run(k + step).z[..., 7, 0] - run(k - step).z[..., 7, 0]).sum() / (2 * step)
        assert abs(float(grad.sum() - fd)) < 1e-5 * abs(float(fd))


@pytest.mark.parametrize("scale", [1e-3, 1e-9])
@pytest.mark.parametrize("options", [{}, dict(adaptive=False, substeps=4)])
def test_consistent_start_of_a_badly_scaled_constraint(scale, options):
    """0 = scale (z - x): Newton's absolute residual test (|g| <= 1e-10) accepted a guess
    z0 = 1 + 9e-8 unchanged at scale 1e-3 and z0 = 1.05 at scale 1e-9 (z(t0) off by 0.05).
    With the equations equilibrated by their Jacobian rows the start is z(t0) = x(t0) to
    rounding, whatever the scale; the correction is reported."""

    def g(t, x, z):
        return scale * (z - x)

    guess = 1.0 + 9e-8 if scale == 1e-3 else 1.05
    sol = daeint(SemiExplicitDAE(lambda t, x, z: -z, g), torch.tensor([1.0]),
                 torch.tensor([guess]), torch.tensor([0.0, 0.5]), rtol=1e-10, atol=1e-12,
                 **options)  # fmt: skip
    assert abs(float(sol.z[0, 0]) - 1.0) < 1e-14
    assert float(sol.stats.extra["z0_correction"]) == pytest.approx(guess - 1.0, rel=1e-6)
