"""ODE test plants of sysid.zoo.ode against closed forms, scipy and the notes."""

import numpy as np
import pytest
import scipy.integrate
import scipy.linalg
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from integrators.errors import InputValidationError
from sysid.zoo import (
    LinearTestEquation,
    Lorenz,
    NonlinearExample,
    Quadratic,
    SqrtAbs,
    StiffLinear,
    StiffVanDerPol,
    VanDerPol,
)

DT = torch.float64


def _scipy_solution(plant, x0, t, method="DOP853", rtol=1e-12, atol=1e-12):
    def rhs(_t, x):
        with torch.no_grad():
            return plant(torch.tensor(_t), torch.tensor(x, dtype=DT)).numpy()

    sol = scipy.integrate.solve_ivp(
        rhs, (t[0], t[-1]), x0, t_eval=t, method=method, rtol=rtol, atol=atol
    )
    assert sol.success
    return sol.y.T


def test_stiff_linear_exact_matches_scipy_expm_and_solve_ivp():
    plant = StiffLinear(eps=5e-4)
    a = plant.matrix().detach().numpy()
    x0 = torch.tensor([[1.0, -0.5, 0.3, 0.2], [0.0, 1.0, -1.0, 2.0]], dtype=DT)
    t = np.linspace(0.0, 0.05, 11)
    exact = plant.exact(torch.tensor(t), x0).detach().numpy()
    assert exact.shape == (2, 11, 4)
    for i in range(2):
        ref = np.stack([scipy.linalg.expm(a * tk) @ x0[i].numpy() for tk in t])
        np.testing.assert_allclose(exact[i], ref, rtol=1e-10, atol=1e-12)
        num = scipy.integrate.solve_ivp(
            lambda _t, x: a @ x,
            (0, 0.05),
            x0[i].numpy(),
            method="Radau",
            t_eval=t,
            jac=a,
            rtol=1e-9,
            atol=1e-11,
        ).y.T
        np.testing.assert_allclose(exact[i], num, rtol=1e-5, atol=1e-7)


def test_stiff_linear_is_stiff_as_in_fig_6_16():
    """The stiff reading of eq. (6.42) (fast block scaled by 1/eps, the notes' typo fixed):
    eigenvalues (-0.1 +- i)/eps, and RK4 is stable at dt slightly below 1.5e-3 but unstable a
    little above, as Fig. 6.16 says."""
    eps = 5e-4
    lam = np.linalg.eigvals(StiffLinear(eps).matrix().detach().numpy())
    fast = lam[np.abs(lam) > 100]
    np.testing.assert_allclose(sorted(fast.imag), [-1 / eps, 1 / eps], rtol=1e-2)
    np.testing.assert_allclose(fast.real, -0.1 / eps, rtol=1e-2)

    def rk4_amplification(dt):
        z = fast * dt
        return np.max(np.abs(1 + z + z**2 / 2 + z**3 / 6 + z**4 / 24))

    assert rk4_amplification(1.3e-3) < 1.0
    assert rk4_amplification(1.6e-3) > 1.0


def test_stiff_linear_batched_eps_parameter():
    eps = torch.tensor([[1e-3], [1e-2]], dtype=DT)
    plant = StiffLinear(eps)
    x = torch.randn(2, 4, dtype=DT, generator=torch.Generator().manual_seed(0))
    xdot = plant(torch.tensor(0.0), x)
    for i, e in enumerate([1e-3, 1e-2]):
        ref = StiffLinear(e)(torch.tensor(0.0), x[i])
        torch.testing.assert_close(xdot[i], ref)


def test_linear_test_equation_exact_batched():
    lam = torch.tensor([[-2.0], [0.5]], dtype=DT)
    plant = LinearTestEquation(lam)
    x0 = torch.tensor([[1.0], [3.0]], dtype=DT)
    t = torch.linspace(0, 2, 5, dtype=DT)
    exact = plant.exact(t, x0)
    ref = x0[:, None, :] * torch.exp(lam[:, None, :] * t[None, :, None])
    torch.testing.assert_close(exact, ref)
    num = _scipy_solution(LinearTestEquation(0.5), np.array([3.0]), t.numpy())
    np.testing.assert_allclose(exact[1].detach().numpy(), num, rtol=1e-9)


@settings(max_examples=15, deadline=None)
@given(st.floats(-3.0, 0.9))
def test_quadratic_exact_matches_solve_ivp(x0):
    plant = Quadratic()
    t = np.linspace(0.0, 1.0, 6)
    exact = plant.exact(torch.tensor(t), torch.tensor([[x0]], dtype=DT))[0].numpy()
    np.testing.assert_allclose(exact[:, 0], x0 / (1 - x0 * t), rtol=1e-14)
    num = _scipy_solution(plant, np.array([x0]), t)
    np.testing.assert_allclose(exact, num, rtol=1e-8, atol=1e-10)


def test_quadratic_escape_time_raises():
    """Eq. (1.44)-(1.45): x0 = 1 escapes at t = 1."""
    t = torch.linspace(0.0, 1.5, 4, dtype=DT)
    with pytest.raises(InputValidationError, match="escapes"):
        Quadratic().exact(t, torch.tensor([[0.5], [1.0]], dtype=DT))
    assert float(Quadratic.escape_time(torch.tensor(1.0, dtype=DT))) == 1.0


def test_sqrt_abs_exact_solutions_satisfy_ode_and_are_not_unique():
    plant = SqrtAbs()
    t = torch.linspace(0.0, 4.0, 401, dtype=DT)
    x0 = torch.tensor([[2.0], [-1.0], [0.0]], dtype=DT)
    for dwell in (0.0, 0.7):
        x = plant.exact(t, x0, dwell=dwell)[..., 0]
        dxdt = torch.diff(x, dim=-1) / torch.diff(t)
        mid = plant(None, 0.5 * (x[:, 1:] + x[:, :-1]))
        torch.testing.assert_close(dxdt, mid, atol=2e-2, rtol=0)
    zero_start = [plant.exact(t, x0[2:], dwell=d)[0, -1, 0] for d in (0.0, 1.0)]
    torch.testing.assert_close(zero_start[0], torch.tensor(4.0, dtype=DT))  # (t/2)^2 at t=4
    torch.testing.assert_close(zero_start[1], torch.tensor(2.25, dtype=DT))  # eq. 1.47, t0=1
    num = _scipy_solution(plant, np.array([2.0]), t.numpy())
    np.testing.assert_allclose(plant.exact(t, x0[:1])[0].numpy(), num, rtol=1e-8)


def test_van_der_pol_matches_formula_and_stiff_scaling():
    x = torch.randn(7, 2, dtype=DT, generator=torch.Generator().manual_seed(1))
    mu = torch.linspace(0.5, 3.0, 7, dtype=DT)[:, None]
    xdot = VanDerPol(mu)(torch.tensor(0.0), x)
    x1, x2 = x[:, 0], x[:, 1]
    torch.testing.assert_close(xdot[:, 0], mu[:, 0] * (1 - x2**2) * x1 - x2)
    torch.testing.assert_close(xdot[:, 1], x1)
    ydot = StiffVanDerPol(eps=1e-3)(torch.tensor(0.0), x)
    torch.testing.assert_close(ydot[:, 1], ((1 - x1**2) * x2 - x1) / 1e-3)
    torch.testing.assert_close(ydot[:, 0], x2)


def test_lorenz_equilibria_and_parameter_gradient():
    sigma, rho, beta = 10.0, 28.0, 3.0
    plant = Lorenz(sigma, rho, beta)
    c = np.sqrt(beta * (rho - 1))
    eq = torch.tensor([[0, 0, 0], [c, c, rho - 1], [-c, -c, rho - 1]], dtype=DT)
    torch.testing.assert_close(plant(torch.tensor(0.0), eq), torch.zeros(3, 3, dtype=DT))
    x = torch.tensor([[1.0, 2.0, 3.0]], dtype=DT)
    plant(torch.tensor(0.0), x)[0, 0].backward()
    assert float(plant.sigma.grad) == pytest.approx(2.0 - 1.0)


def test_nonlinear_example_linearization_eq_1_39_by_finite_differences():
    plant = NonlinearExample()
    x = torch.randn(5, 2, dtype=DT, generator=torch.Generator().manual_seed(2))
    a, b, c, d = plant.closed_form_linearization(x)
    h = 1e-6
    for j in range(2):
        e = torch.zeros(2, dtype=DT)
        e[j] = h
        fd = (plant(None, x + e) - plant(None, x - e)) / (2 * h)
        torch.testing.assert_close(a[:, :, j], fd, atol=1e-8, rtol=1e-8)
        fd_h = (plant.output(x + e) - plant.output(x - e)) / (2 * h)
        torch.testing.assert_close(c[:, :, j], fd_h, atol=1e-8, rtol=1e-8)
    u = torch.ones(5, 1, dtype=DT)
    fd_u = (plant(None, x, u * h) - plant(None, x, -u * h)) / (2 * h)
    torch.testing.assert_close(b[..., 0], fd_u, atol=1e-8, rtol=1e-8)
    assert torch.all(d == 0)
    u_bar = torch.tensor([[0.3], [-1.2]], dtype=DT)
    x_bar = plant.steady_state(u_bar)
    torch.testing.assert_close(plant(None, x_bar, u_bar), torch.zeros(2, 2, dtype=DT))
    a_bar, _, c_bar, _ = plant.closed_form_linearization(x_bar)
    # Typo in eq. (1.42): A[0, 0] = 1 - u_bar^2 at x_bar = [0, u_bar] (eq. 1.39), not 1; the
    # printed A = [[1, -1], [1, 0]] holds only for u_bar = 0.
    a_ref = torch.tensor([[1.0, -1.0], [1.0, 0.0]], dtype=DT).repeat(2, 1, 1)
    a_ref[:, 0, 0] = 1 - u_bar[:, 0] ** 2
    torch.testing.assert_close(a_bar, a_ref)
    torch.testing.assert_close(c_bar[:, 0, 1], 3 * u_bar[:, 0] ** 2)  # eq. (1.42)


def test_float32_states_work_with_float64_parameters():
    x = torch.randn(4, 2, generator=torch.Generator().manual_seed(3))
    for plant in (VanDerPol(2.0), StiffVanDerPol(1e-2), NonlinearExample()):
        out = plant(torch.tensor(0.0), x)
        assert out.dtype == torch.float32
        ref = plant(torch.tensor(0.0), x.double())
        torch.testing.assert_close(out.double(), ref, rtol=1e-5, atol=1e-5)
    xs = StiffLinear().exact(torch.linspace(0, 0.01, 3), torch.ones(2, 4))
    assert xs.dtype == torch.float32 and torch.isfinite(xs).all()


def test_per_member_parameters_are_columns_and_a_flat_vector_is_refused():
    """A per-member scalar parameter has shape (*batch, 1): mu = [1, 2, 3] as a column gives
    each Van der Pol plant its own x1' = mu (1 - x2^2) x1 - x2 (eq. 6.43); the flat (3,)
    vector, which gave every plant mu = 1, is refused by name, as is a flat eps of
    StiffLinear's matrix."""
    x = torch.tensor([[0.5, 1.5]] * 3, dtype=torch.float64)
    mu = torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64)
    rhs = VanDerPol(mu[:, None])(0.0, x)
    torch.testing.assert_close(rhs[:, 0], mu * (1 - 1.5**2) * 0.5 - 1.5)
    with pytest.raises(InputValidationError, match=r"shape \(\*batch, 1\), got \(3,\)"):
        VanDerPol(mu)(0.0, x)
    with pytest.raises(InputValidationError, match=r"got \(3,\)"):
        StiffLinear(torch.tensor([1e-3, 1e-2, 1e-1])).matrix()
