"""Forward sensitivities of RK simulations (notes §8) against autograd, finite
differences, closed forms and the variational equations (eq. 8.8).

Typos found in the notes: eq. 8.16/8.17 use ``a_sj`` and ``b_j`` inside the stage sums (row
``i`` of A is meant) and put an identity inside ``dK_i/dp``; eq. 8.28c propagates ``B`` with
``dK/dp`` instead of ``dK/dx_k``. The corrected recursion reproduces autograd exactly below.
"""

import math

import pytest
import torch

from integrators import (
    SingularMatrixError,
    TableauError,
    gauss_legendre,
    odeint,
)
from integrators.sensitivities import sensitivities, variational_sensitivities

F64 = torch.float64


def pendulum(t, x, u, p):
    """Damped, forced pendulum: theta'' = -p0 sin(theta) - p1 theta' + u + 0.1 t."""
    return torch.stack(
        [
            x[..., 1],
            -p[..., 0] * torch.sin(x[..., 0]) - p[..., 1] * x[..., 1] + u[..., 0] + 0.1 * t,
        ],
        -1,
    )


def pendulum_free(t, x, p):
    return torch.stack([x[..., 1], -p[..., 0] * torch.sin(x[..., 0]) - p[..., 1] * x[..., 1]], -1)


T_GRID = torch.linspace(0.0, 1.5, 7, dtype=F64)
X0 = torch.tensor([[0.5, 0.0], [1.0, -0.3]], dtype=F64)
P = torch.tensor([9.81, 0.3], dtype=F64)
U = torch.cos(2.0 * T_GRID)[:, None]


def simulate(x0, p, u, method, substeps=1):
    return odeint(
        lambda t, x, uu: pendulum(t, x, uu, p),
        x0,
        T_GRID,
        method=method,
        u=u,
        substeps=substeps,
        compile=False,
    ).x


@pytest.mark.parametrize(
    ("method", "substeps"), [("euler", 1), ("heun", 2), ("kutta3", 1), ("rk4", 1), ("rk4", 3)]
)
def test_forward_sensitivities_equal_autograd_jacobians_of_odeint(method, substeps):
    res = sensitivities(pendulum, X0, T_GRID, P, u=U, method=method, substeps=substeps)
    torch.testing.assert_close(res.x, simulate(X0, P, U, method, substeps), rtol=0, atol=1e-13)
    jac = torch.autograd.functional.jacobian
    Jx0 = jac(lambda z: simulate(z, P, U, method, substeps), X0)  # (2, T, 2, 2, 2)
    A_ad = torch.stack([Jx0[b, :, :, b, :] for b in range(2)])
    torch.testing.assert_close(res.A, A_ad, rtol=0, atol=1e-12)
    B_ad = jac(lambda q: simulate(X0, q, U, method, substeps), P)
    torch.testing.assert_close(res.B, B_ad, rtol=0, atol=1e-12)
    C_ad = jac(lambda v: simulate(X0, P, v, method, substeps), U)
    torch.testing.assert_close(res.C, C_ad, rtol=0, atol=1e-12)
    assert bool(torch.all(res.C[:, 3, :, 3:] == 0))  # causality: x_k ignores u_j, j >= k


def test_parameter_sensitivities_match_central_finite_differences():
    res = sensitivities(pendulum_free, X0, T_GRID, P, method="rk4")
    h = 1e-6
    for j in range(2):
        e = torch.zeros(2, dtype=F64)
        e[j] = h
        plus = sensitivities(pendulum_free, X0, T_GRID, P + e).x
        minus = sensitivities(pendulum_free, X0, T_GRID, P - e).x
        fd = (plus - minus) / (2 * h)
        torch.testing.assert_close(res.B[..., j], fd, rtol=1e-6, atol=1e-8)


def test_linear_system_has_closed_form_sensitivities():
    """x' = M x, M = [[0, 1], [-p0, -p1]]: A_k = R(h M)^k with the RK4 polynomial R."""
    M = torch.tensor([[0.0, 1.0], [-P[0], -P[1]]], dtype=F64)

    def linear(t, x, p):
        return torch.stack([x[..., 1], -p[..., 0] * x[..., 0] - p[..., 1] * x[..., 1]], -1)

    h = float(T_GRID[1] - T_GRID[0])
    res = sensitivities(linear, X0, T_GRID, P, method="rk4")
    hM = h * M
    R = sum(torch.linalg.matrix_power(hM, j) / math.factorial(j) for j in range(5))
    for k in range(len(T_GRID)):
        torch.testing.assert_close(res.A[:, k], torch.linalg.matrix_power(R, k).expand(2, 2, 2))


def test_variational_equations_with_the_same_method_coincide():
    """Explicit RK commutes with linearisation: eq. 8.8 integrated by the same method and grid
    gives the discrete sensitivities (the notes show it for Euler, §8.2)."""
    for method in ("euler", "rk4"):
        disc = sensitivities(pendulum, X0, T_GRID, P, u=U, method=method)
        var = variational_sensitivities(pendulum, X0, T_GRID, P, u=U, method=method)
        torch.testing.assert_close(var.x, disc.x, rtol=0, atol=1e-13)
        torch.testing.assert_close(var.A, disc.A, rtol=0, atol=1e-12)
        torch.testing.assert_close(var.B, disc.B, rtol=0, atol=1e-12)


def test_variational_sensitivities_converge_to_the_discrete_ones_as_dt_shrinks():
    """Heun on eq. 8.8 vs exact RK4 sensitivities: the gap shrinks at Heun's order 2."""
    t = torch.tensor([0.0, 1.0, 2.0], dtype=F64)
    gaps = []
    for m in (8, 16, 32):
        disc = sensitivities(pendulum_free, X0, t, P, method="rk4", substeps=m)
        var = variational_sensitivities(pendulum_free, X0, t, P, method="heun", substeps=m)
        gaps.append(max(float((var.A - disc.A).abs().max()), float((var.B - disc.B).abs().max())))
    orders = [math.log2(gaps[i] / gaps[i + 1]) for i in range(2)]
    assert all(1.8 < q < 2.3 for q in orders), (gaps, orders)


def test_float32_and_shared_parameters():
    res = sensitivities(pendulum_free, X0.float(), T_GRID.float(), P.float())
    ref = sensitivities(pendulum_free, X0, T_GRID, P)
    assert res.A.dtype == torch.float32
    torch.testing.assert_close(res.B, ref.B.float(), rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize(("method", "stages"), [("gauss_legendre", 2), ("radau_iia", 3)])
def test_implicit_step_sensitivities_by_the_ift_match_autograd_of_odeint(method, stages):
    """Eq. 8.24-8.28 vs reverse-mode autograd through the implicit solver of odeint (its own
    IFT gradients, with its Newton iteration converged to rtol 1e-10), one factorisation of the
    Newton matrix per step (plus one to start the first step's iteration)."""
    res = sensitivities(pendulum, X0, T_GRID, P, u=U, method=method, stages=stages)

    def sim(x0, p, u):
        return odeint(
            lambda t, x, uu: pendulum(t, x, uu, p),
            x0,
            T_GRID,
            method=method,
            stages=stages,
            u=u,
            adaptive=False,
            rtol=1e-10,
            atol=1e-12,
        ).x

    torch.testing.assert_close(res.x, sim(X0, P, U), rtol=0, atol=1e-10)
    jac = torch.autograd.functional.jacobian
    Jx0 = jac(lambda z: sim(z, P, U), X0)
    torch.testing.assert_close(
        res.A, torch.stack([Jx0[b, :, :, b, :] for b in range(2)]), rtol=0, atol=1e-10
    )
    torch.testing.assert_close(res.B, jac(lambda q: sim(X0, q, U), P), rtol=0, atol=1e-10)
    torch.testing.assert_close(res.C, jac(lambda v: sim(X0, P, v), U), rtol=0, atol=1e-10)
    assert res.stats.n_steps == len(T_GRID) - 1
    assert res.stats.n_factorizations == res.stats.n_steps + 1


def test_implicit_sensitivities_match_finite_differences_and_the_linear_closed_form():
    res = sensitivities(
        pendulum_free, X0, T_GRID, P, method="radau_iia", substeps=2, newton_tol=1e-14
    )
    h = 1e-6
    for j in range(2):
        e = torch.zeros(2, dtype=F64)
        e[j] = h
        plus, minus = (
            sensitivities(
                pendulum_free, X0, T_GRID, q, method="radau_iia", substeps=2, newton_tol=1e-14
            ).x
            for q in (P + e, P - e)
        )
        torch.testing.assert_close(res.B[..., j], (plus - minus) / (2 * h), rtol=1e-6, atol=1e-8)
    # x' = M x: one Gauss step is x+ = R x, R = I + h (b^T kron I)(I - h A kron M)^{-1}(1 kron M)
    M = torch.tensor([[0.0, 1.0], [-P[0], -P[1]]], dtype=F64)
    tab = gauss_legendre(3)
    a, b = torch.as_tensor(tab.A.copy()), torch.as_tensor(tab.b.copy())
    dt = float(T_GRID[1] - T_GRID[0])
    eye = torch.eye(2, dtype=F64)
    stage = torch.linalg.solve(
        torch.eye(6, dtype=F64) - dt * torch.kron(a, M), torch.kron(torch.ones(3, 1, dtype=F64), M)
    )
    R = eye + dt * torch.kron(b[None], eye) @ stage
    lin = sensitivities(lambda t, x: x @ M.T, X0, T_GRID, method=tab)
    for k in range(len(T_GRID)):
        torch.testing.assert_close(
            lin.A[:, k], torch.linalg.matrix_power(R, k).expand(2, 2, 2), rtol=1e-13, atol=1e-13
        )
    torch.testing.assert_close(
        lin.x, (lin.A @ X0[:, None, :, None])[..., 0], rtol=1e-13, atol=1e-13
    )
    assert lin.stats.n_factorizations == len(T_GRID)  # one per step, one to start


def test_stale_newton_matrix_is_refreshed_and_counted():
    """x' = -u x with u switching 1 <-> 200 (ZOH): the previous step's Newton matrix contracts
    too slowly after a switch and is refreshed (counted); implicit Euler's closed form
    x_{k+1} = x_k / (1 + h u_k) gives x and the input sensitivities dx_n/du_j =
    -h x_n / (1 + h u_j) (j < n) exactly."""
    t = torch.linspace(0.0, 1.0, 6, dtype=F64)
    u = torch.tensor([1.0, 200.0, 1.0, 200.0, 1.0, 1.0], dtype=F64)[:, None]
    x0 = torch.tensor([1.0, -2.0], dtype=F64)[:, None]
    res = sensitivities(lambda tt, x, uu: -uu * x, x0, t, u=u, method="implicit_euler")
    h = 0.2
    factor = 1.0 / (1.0 + h * u[:-1, 0])
    x_ref = x0 * torch.cat([torch.ones(1, dtype=F64), torch.cumprod(factor, 0)])
    torch.testing.assert_close(res.x[..., 0], x_ref, rtol=1e-14, atol=0)
    C_ref = torch.zeros(2, 6, 6, dtype=F64)
    for n in range(6):
        C_ref[:, n, :n] = -h * x_ref[:, n, None] * factor[:n]
    torch.testing.assert_close(res.C[:, :, 0, :, 0], C_ref, rtol=1e-13, atol=1e-15)
    assert res.stats.n_factorizations > res.stats.n_steps + 1


def test_errors():
    with pytest.raises(TableauError, match="unknown"):
        sensitivities(pendulum_free, X0, T_GRID, P, method="rk5")
    with pytest.raises(ValueError, match="strictly increasing"):
        sensitivities(pendulum_free, X0, T_GRID.flip(0), P)
    with pytest.raises(ValueError, match="sampled u"):
        sensitivities(pendulum, X0, T_GRID, P, u=U[:3])
    with pytest.raises(SingularMatrixError, match=r"singular in step 0 of interval 0"):
        # implicit Euler on x' = x / h: the Newton matrix 1 - h / h vanishes
        sensitivities(lambda t, x: x / 0.25, X0, T_GRID, method="implicit_euler")
