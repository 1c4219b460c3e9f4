"""Forward sensitivities of RK simulations (notes §8) against autograd, finite
differences, closed forms and the variational equations (eq. 8.8).

Typos found in the notes: eq. 8.16/8.17 use ``a_sj`` and ``b_j`` inside the stage sums (row
``i`` of A is meant) and put an identity inside ``dK_i/dp``; eq. 8.28c propagates ``B`` with
``dK/dp`` instead of ``dK/dx_k``. The corrected recursion reproduces autograd exactly below.
"""

import math

import pytest
import torch
from _shared_models import pendulum

from integrators import (
    InputValidationError,
    Status,
    TableauError,
    gauss_legendre,
    odeint,
    radau_iia,
    tableau,
)
from integrators.inputs import CollocationInput
from integrators.methods import resolve_method
from integrators.sensitivities import sensitivities, variational_sensitivities

F64 = torch.float64


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
    with pytest.raises(InputValidationError, match="another grid"):
        sensitivities(pendulum, X0, T_GRID, P, u=CollocationInput(P_IN[2], 2 * T_GRID))


def test_x0_and_t_are_checked_as_odeint_checks_them():
    """x0 and t go through odeint's state and time checks, the messages naming
    sensitivities: a non-finite x0 and a float16 x0 are refused, as are non-finite times."""
    bad = X0.clone()
    bad[..., -1] = math.nan
    with pytest.raises(InputValidationError, match="sensitivities: x0 contains a non-finite"):
        sensitivities(pendulum_free, bad, T_GRID, P)
    with pytest.raises(InputValidationError, match="sensitivities: x0 has dtype torch.float16"):
        sensitivities(pendulum_free, X0.half(), T_GRID, P)
    t = T_GRID.clone()
    t[1] = math.inf
    with pytest.raises(InputValidationError, match="sensitivities: t contains a non-finite"):
        sensitivities(pendulum_free, X0, t, P)


@pytest.mark.parametrize("method", ["rk4", "dopri5", "radau_iia"])
def test_a_model_of_the_wrong_shape_or_signature_is_named(method):
    """An output of another shape than the state, at t0 or later (rk4 / dopri5 broadcast
    (1, 1) against the (1, 2) state or raised a raw RuntimeError), and a model f(t, x, p)
    called without p (a raw TypeError) raise InputValidationError naming the shapes or the
    calling convention, for the discrete and the variational sensitivities."""
    x0 = torch.tensor([[1.0, 0.5]], dtype=torch.float64)
    t = torch.linspace(0.0, 1.0, 5, dtype=torch.float64)
    p = torch.tensor([[2.0]], dtype=torch.float64)
    shape = r"the model returned shape \(1, 1\) for a state of shape \(1, 2\) at t = 0;"
    for run in (sensitivities, variational_sensitivities):
        with pytest.raises(InputValidationError, match=shape):
            run(lambda t, x, p: -p * x[..., :1], x0, t, p, method=method)
        with pytest.raises(InputValidationError, match=r"calling the model as f\(t, x\) failed"):
            run(lambda t, x, p: -p * x, x0, t, None, method=method)

    def late_change(t, x, p):  # the state's shape up to t = 0.5, then one column
        return -p * (x if float(torch.as_tensor(t).max()) < 0.5 else x[..., :1])

    # the first call after t = 0.5, or the stacked stages of the implicit step reaching it
    late = r"shape \((3, )?1, 1\) for a state of shape \((3, )?1, 2\) at t = 0\.(5;|2.* \.\. 0\.5)"
    with pytest.raises(InputValidationError, match=late):
        sensitivities(late_change, x0, t, p, method=method)


@pytest.mark.parametrize("substeps", [2.0, 0, True, "2"])
def test_substeps_must_be_a_positive_integer(substeps):
    """substeps is checked as odeint checks it: an int >= 1, not a float, bool or string."""
    with pytest.raises(InputValidationError, match="sensitivities: substeps must be an integer"):
        sensitivities(pendulum_free, X0, T_GRID, P, substeps=substeps)


def quadratic(t, x, u, p):
    """x' = p_0 x^2 + p_1 x + u: escapes to infinity for p_0 > 0 from x_0 > 0."""
    return p[..., :1] * x**2 + p[..., 1:] * x + u


#: method -> {member of the batch below: (interval of its failure, reason in the message)}
STAGE_FAILURES = {
    "implicit_euler": {1: (1, "did not reach ||r||_inf"), 2: (0, "singular Newton matrix")},
    "radau_iia": {1: (4, "did not reach ||r||_inf")},
    "gauss_legendre": {1: (4, "did not reach ||r||_inf")},
}


@pytest.mark.parametrize("method", list(STAGE_FAILURES))
def test_a_member_whose_stage_equations_fail_stops_and_leaves_the_others_alone(method):
    """Members (x' = p_0 x^2 + p_1 x + u, h = 0.2): 0 and 3 are solved; 1 escapes to
    infinity at t = 1, and near it the stage equations lose their root (implicit Euler's
    x = x_k + h x^2 has none once x_k > 1 / (4h)); 2 is x' = 5 x, whose implicit Euler
    Newton matrix 1 - 5 h vanishes. The first failure raised ConvergenceError or
    SingularMatrixError for the whole batch. Now the failing member alone gets
    NEWTON_FAILED, NaN x, A, B, C from the end of the failing interval on and a message
    naming it, the interval, the time and the reason; every member (the failing ones up to
    their failure) equals its run alone, and derivatives=False the same states."""
    t = torch.linspace(0.0, 1.0, 6, dtype=F64)
    x0 = torch.tensor([[0.5], [1.0], [1.0], [-1.0]], dtype=F64)
    p = torch.tensor([[1.0, 0.0], [1.0, 0.0], [0.0, 5.0], [2.0, -50.0]], dtype=F64)
    u = 0.01 * torch.cos(3.0 * t)[:, None]
    res = sensitivities(quadratic, x0, t, p, u=u, method=method)
    failing = STAGE_FAILURES[method]
    expected = [Status.NEWTON_FAILED if i in failing else Status.SUCCESS for i in range(4)]
    assert res.status.tolist() == expected
    for i in range(4):
        alone = sensitivities(quadratic, x0[i : i + 1], t, p[i : i + 1], u=u, method=method)
        assert alone.status.tolist() == expected[i : i + 1]
        for name in ("x", "A", "B", "C"):
            torch.testing.assert_close(
                getattr(res, name)[i : i + 1],
                getattr(alone, name),
                rtol=0,
                atol=1e-14,
                equal_nan=True,
            )
    assert len(res.messages) == len(failing)
    for (i, (k, reason)), line in zip(failing.items(), res.messages, strict=True):
        assert line.startswith(f"sample {i}: the stage equations (eq. 8.20)") and reason in line
        assert (
            f"interval {k} (t = {float(t[k]):.6g}); its outputs from t = {float(t[k + 1]):.6g} "
            "on are NaN" in line
        )
        for value in (res.x, res.A, res.B, res.C):
            assert bool(torch.isfinite(value[i, : k + 1]).all())
            assert bool(value[i, k + 1 :].isnan().all())
    states = sensitivities(quadratic, x0, t, p, u=u, method=method, derivatives=False)
    torch.testing.assert_close(states.x, res.x, rtol=0, atol=0, equal_nan=True)
    assert states.status.tolist() == expected and states.messages == res.messages


def test_a_run_whose_members_all_fail_returns_their_statuses():
    """x' = x^2 from 2 and from 1 by implicit Euler at h = 0.2: the stage equation has no
    root once x_k > 1 / (4h) = 1.25, at the first step from 2, at the second from 1. Both
    raised ConvergenceError; now both are NEWTON_FAILED with NaN from there on (the run
    stops solving once no member is left), and an unbatched run gives a 0-dim status."""
    t = torch.linspace(0.0, 1.0, 6, dtype=F64)
    x0 = torch.tensor([[2.0], [1.0]], dtype=F64)
    res = sensitivities(lambda tt, x: x**2, x0, t, method="implicit_euler")
    assert res.status.tolist() == [Status.NEWTON_FAILED] * 2
    assert [line.split(":")[0] for line in res.messages] == ["sample 0", "sample 1"]
    assert bool(res.x[0, 1:].isnan().all()) and bool(res.x[1, 2:].isnan().all())
    assert float(res.x[1, 1, 0]) == pytest.approx((1 - math.sqrt(1 - 0.8)) / 0.4, rel=1e-12)
    assert bool(res.A[1, 2:].isnan().all()) and bool(torch.isfinite(res.A[1, :2]).all())
    alone = sensitivities(lambda tt, x: x**2, x0[0], t, method="implicit_euler")
    assert alone.status.shape == () and int(alone.status) == Status.NEWTON_FAILED
    assert alone.messages[0].startswith("sample 0: the stage equations")
    torch.testing.assert_close(alone.x, res.x[0], rtol=0, atol=0, equal_nan=True)


@pytest.mark.parametrize("method", ["rk4", "gauss_legendre", "radau_iia", "implicit_euler"])
def test_an_empty_batch_gives_empty_sensitivities(method):
    """A batch of no samples gives empty results of the right shapes (implicit methods raised
    a raw RuntimeError reducing the Newton iterations of no sample)."""
    res = sensitivities(pendulum_free, X0[:0], T_GRID, P, method=method)
    T, nx, n_p = len(T_GRID), X0.shape[-1], P.shape[-1]
    assert res.x.shape == (0, T, nx) and res.A.shape == (0, T, nx, nx)
    assert res.B.shape == (0, T, nx, n_p)


def test_a_compile_that_cannot_apply_says_why():
    """compile=True with an implicit method or with input sensitivities runs the eager
    recursion and reports why (compile_fallback was None)."""
    implicit = sensitivities(pendulum_free, X0, T_GRID, P, method="radau_iia", compile=True)
    assert implicit.stats.extra["compiled"] is False
    assert "this run has an implicit method" in implicit.stats.extra["compile_fallback"]
    u = torch.zeros(len(T_GRID), 1, dtype=F64)
    forced = sensitivities(pendulum, X0, T_GRID, P, u=u, method="rk4", compile=True)
    assert "input_sensitivities=False" in forced.stats.extra["compile_fallback"]


def _tight_newton(method, tol=1e-13) -> dict:
    """``newton_tol=tol`` for an implicit method, nothing for an explicit one (refused)."""
    tab = resolve_method(method).tableau() if isinstance(method, str) else method
    return {} if tab.is_explicit else {"newton_tol": tol}


def test_newton_tol_of_an_explicit_method_is_refused():
    """newton_tol applies to the stage equations of implicit methods; with an explicit one it
    was ignored (as odeint refuses it); an implicit method takes it."""
    with pytest.raises(InputValidationError, match="newton_tol=0.001 applies to implicit"):
        sensitivities(pendulum_free, X0, T_GRID, P, method="rk4", newton_tol=1e-3)
    tight = sensitivities(pendulum_free, X0, T_GRID, P, method="radau_iia", newton_tol=1e-12)
    default = sensitivities(pendulum_free, X0, T_GRID, P, method="radau_iia")
    torch.testing.assert_close(tight.x, default.x, rtol=1e-9, atol=1e-10)


# ------------------------------------------------- inputs by collocation (eq. 8.32-8.33)
GEN = torch.Generator().manual_seed(8)
P_IN = {q: torch.randn(len(T_GRID) - 1, q, 1, generator=GEN, dtype=F64) for q in (1, 2, 3)}


def lagrange_weights(nodes, tau: float) -> torch.Tensor:
    """l_i(tau) of the nodes by the product formula (the test's own), (q,)."""
    w = [
        math.prod((tau - nodes[m]) / (nodes[i] - nodes[m]) for m in range(len(nodes)) if m != i)
        for i in range(len(nodes))
    ]
    return torch.tensor(w, dtype=F64)


def reference_simulation(x0, p, P, nodes, tab, substeps):
    """A plain RK loop with autograd (the truth for C): on interval k the input is
    sum_i P[k, i] l_i(tau) at tau = (m + c_i) / substeps (eq. 8.32). Implicit stages: Newton
    without graph, then one Newton step with a detached exact Jacobian, whose derivative is the
    implicit-function-theorem one (eq. 3.40)."""
    a = torch.as_tensor(tab.A.copy())
    s, x, xs = tab.stages, x0, [x0]
    for k in range(len(T_GRID) - 1):
        h = (T_GRID[k + 1] - T_GRID[k]) / substeps
        for m in range(substeps):
            times = [T_GRID[k] + (m + float(c)) * h for c in tab.c]
            us = [lagrange_weights(nodes, (m + float(c)) / substeps) @ P[k] for c in tab.c]

            def residual(K, x=x, times=times, us=us, h=h):
                X = x[..., None, :] + h * (a @ K)
                F = [pendulum(times[i], X[..., i, :], us[i], p) for i in range(s)]
                return torch.stack(F, -2) - K

            if tab.is_explicit:
                K = []
                for i in range(s):
                    xi = x + h * sum(float(a[i, j]) * K[j] for j in range(i))
                    K.append(pendulum(times[i], xi, us[i], p))
                K = torch.stack(K, -2)
            else:
                Kd = x.new_zeros(*x.shape[:-1], s, x.shape[-1])
                shape = Kd.shape
                for _ in range(8):  # quadratic convergence to rounding
                    J = torch.autograd.functional.jacobian(
                        lambda v, shape=shape: residual(v.view(shape)).flatten(), Kd.flatten()
                    )
                    step = torch.linalg.solve(J, residual(Kd).detach().flatten())
                    Kd = Kd - step.view(Kd.shape)
                K = Kd - torch.linalg.solve(J, residual(Kd).flatten()).view(Kd.shape)
            x = x + h * (torch.as_tensor(tab.b.copy()) @ K)
        xs.append(x)
    return torch.stack(xs, -2)


@pytest.mark.parametrize(
    ("tab", "q", "substeps", "nodes"),
    [
        (tableau("rk4"), 3, 1, "radau"),
        (tableau("rk4"), 3, 2, (0.0, 0.5, 1.0)),
        (gauss_legendre(1), 1, 1, "legendre"),
        (radau_iia(2), 2, 2, "radau"),
    ],
    ids=["rk4-radau", "rk4-substeps-equidistant", "gauss1-legendre", "radau2-radau"],
)
def test_collocation_input_sensitivities_equal_autograd(tab, q, substeps, nodes):
    """C = dx_k/dP against autograd through an independent RK loop that evaluates the input
    polynomial of eq. 8.32 at every stage time; the random coefficients jump between intervals,
    and the stage with c_i = 1 (RK4, Radau IIA) uses the closed interval's value."""
    P_in = P_IN[q]
    u = CollocationInput(P_in, T_GRID, nodes)
    res = sensitivities(
        pendulum, X0, T_GRID, P, method=tab, u=u, substeps=substeps, **_tight_newton(tab)
    )
    ref_nodes = u.nodes.tolist()

    def sim(x0, p, coef):
        return reference_simulation(x0, p, coef, ref_nodes, tab, substeps)

    torch.testing.assert_close(res.x, sim(X0, P, P_in), rtol=0, atol=1e-13)
    jac = torch.autograd.functional.jacobian
    C_ad = jac(lambda coef: sim(X0, P, coef), P_in)  # (2, T, 2, T-1, q, 1)
    torch.testing.assert_close(res.C, C_ad, rtol=0, atol=1e-12)
    torch.testing.assert_close(res.B, jac(lambda pp: sim(X0, pp, P_in), P), rtol=0, atol=1e-12)
    assert bool(torch.all(res.C[:, 3, :, 3:] == 0))  # x_3 ignores the intervals j >= 3


def _forced(t, x, u, p):
    """pendulum_free plus an input force u[..., 0] (none for u None), elementwise over the
    leading dimensions: its stages stack."""
    force = 0.0 if u is None else u[..., 0]
    acc = -p[..., 0] * torch.sin(x[..., 0]) - p[..., 1] * x[..., 1] + force
    return torch.stack([x[..., 1], acc], -1)


def _forced_first_axis_only(t, x, u, p):
    """_forced written for (batch, nx) states (x[:, i]): wrong values, or an error, for
    stages stacked on a leading axis."""
    force = 0.0 if u is None else u[..., 0]
    acc = -p[..., 0] * torch.sin(x[:, 0]) - p[..., 1] * x[:, 1] + force
    return torch.stack([x[:, 1], acc], -1)


STAGE_INPUTS = {
    "none": None,
    "samples": U,
    "collocation": CollocationInput(P_IN[2], T_GRID, "radau"),
    "callable": lambda t: torch.cos(2.0 * t).reshape(1),
}


@pytest.mark.parametrize("kind", list(STAGE_INPUTS))
@pytest.mark.parametrize("method", ["radau_iia", "gauss_legendre"])
def test_implicit_stages_stack_with_their_inputs(kind, method):
    """Implicit tableaus evaluate all stages of a step (and their Jacobians) in one call of
    f, with the stage times, states and inputs stacked on a leading axis, wherever that
    reproduces the stage-by-stage values: x, A, B, C and the Newton work are those of a model
    that must be evaluated stage by stage, for every kind of input."""
    u = STAGE_INPUTS[kind]
    runs = []
    for f in (_forced, _forced_first_axis_only):
        model = (lambda t, x, p, f=f: f(t, x, None, p)) if u is None else f
        runs.append(
            sensitivities(
                model, X0, T_GRID, P, u=u, method=method, substeps=2, **_tight_newton(method)
            )
        )
    stacked, by_stage = runs
    assert stacked.stats.extra["stacked_stages"] and not by_stage.stats.extra["stacked_stages"]
    for name in ("x", "A", "B", "C"):
        got, ref = getattr(stacked, name), getattr(by_stage, name)
        if ref is None:
            assert got is None and kind in ("none", "callable")
            continue
        torch.testing.assert_close(got, ref, rtol=1e-12, atol=1e-12)
    assert stacked.stats.n_newton_iters == by_stage.stats.n_newton_iters
    assert stacked.stats.n_f_evals == by_stage.stats.n_f_evals


@pytest.mark.parametrize(("method", "stages"), [("gauss_legendre", 2), ("gauss_legendre", 3)])
def test_collocation_input_agrees_with_odeint_given_the_same_callable(method, stages):
    """The stages of Gauss-Legendre lie inside the steps, so odeint calling the input as
    u(t) at its stage times runs the same simulation: x and autograd through odeint's implicit
    solver (its own IFT gradients) w.r.t. the coefficients match."""
    u = CollocationInput(P_IN[2], T_GRID, "legendre")
    res = sensitivities(pendulum, X0, T_GRID, P, method=method, stages=stages, u=u, substeps=2)

    def sim(coef):
        return odeint(
            lambda t, x, uu: pendulum(t, x, uu, P),
            X0,
            T_GRID,
            method=method,
            stages=stages,
            u=CollocationInput(coef, T_GRID, "legendre"),
            substeps=2,
            adaptive=False,
            rtol=1e-10,
            atol=1e-12,
        ).x

    torch.testing.assert_close(res.x, sim(P_IN[2]), rtol=0, atol=1e-12)
    C_ad = torch.autograd.functional.jacobian(sim, P_IN[2])
    torch.testing.assert_close(res.C, C_ad, rtol=0, atol=1e-12)
    assert res.stats.n_factorizations == res.stats.n_steps + 1


def test_continuous_collocation_input_is_odeint_linear_interpolation_and_q1_is_zoh():
    """Nodes (0, 1) with P[k] = (u_k, u_{k+1}) is odeint's interpolation="linear" (also via
    the callable, the pieces being continuous); q = 1 is the piecewise-constant input of
    eq. 8.34 with the same sensitivities."""
    P_lin = torch.stack([U[:-1], U[1:]], -2)  # (T-1, 2, 1)
    res = sensitivities(pendulum, X0, T_GRID, P, u=CollocationInput(P_lin, T_GRID, (0.0, 1.0)))
    for u in (U, CollocationInput(P_lin, T_GRID, (0.0, 1.0))):
        sol = odeint(
            lambda t, x, uu: pendulum(t, x, uu, P),
            X0,
            T_GRID,
            method="rk4",
            u=u,
            interpolation="linear",
            compile=False,
        )
        torch.testing.assert_close(res.x, sol.x, rtol=0, atol=1e-13)
    # the sensitivity to the sample u_j is the sum over the coefficients equal to it
    C_samples = res.C.new_zeros(2, len(T_GRID), 2, len(T_GRID), 1)
    C_samples[..., :-1, :] += res.C[..., :, 0, :]
    C_samples[..., 1:, :] += res.C[..., :, 1, :]
    lin = torch.autograd.functional.jacobian(
        lambda v: (
            odeint(
                lambda t, x, uu: pendulum(t, x, uu, P),
                X0,
                T_GRID,
                method="rk4",
                u=v,
                interpolation="linear",
                compile=False,
            ).x
        ),
        U,
    )
    torch.testing.assert_close(C_samples, lin, rtol=0, atol=1e-12)
    zoh = sensitivities(pendulum, X0, T_GRID, P, u=U)
    one = sensitivities(pendulum, X0, T_GRID, P, u=CollocationInput(U[:-1, None], T_GRID))
    torch.testing.assert_close(one.x, zoh.x, rtol=0, atol=0)
    torch.testing.assert_close(one.C[..., 0, :], zoh.C[..., :-1, :], rtol=0, atol=0)


@pytest.mark.parametrize("method", ["rk4", "radau_iia"])
def test_collocation_input_sensitivities_match_central_finite_differences(method):
    """All 2 (T-1) q perturbed simulations in one batched call, relative 1e-6 (float64)."""
    P_in = P_IN[3]
    x0 = X0[1]
    u = CollocationInput(P_in, T_GRID, "legendre")
    res = sensitivities(pendulum, x0, T_GRID, P, method=method, u=u, **_tight_newton(method, 1e-14))
    n, step = P_in.numel(), 1e-6
    eye = step * torch.eye(n, dtype=F64).reshape(n, *P_in.shape)
    batch = torch.cat([P_in + eye, P_in - eye])  # (2n, T-1, q, 1)
    xs = sensitivities(
        pendulum,
        x0,
        T_GRID,
        P,
        method=method,
        u=CollocationInput(batch, T_GRID, "legendre"),
        **_tight_newton(method, 1e-14),
    ).x
    fd = ((xs[:n] - xs[n:]) / (2 * step)).movedim(0, -1).reshape(res.C.shape)
    assert float((res.C - fd).abs().max()) <= 1e-6 * float(res.C.abs().max())


@pytest.mark.parametrize(("method", "order"), [("rk4", 4), ("gauss_legendre", 4), ("radau_iia", 5)])
def test_piecewise_linear_input_closed_forms(method, order):
    """x' = -a x + u, u = P_k0 (1 - tau) + P_k1 tau on [t_k, t_{k+1}] (nodes (0, 1)).

    Discrete closed form of one RK step (stage vector solved as one linear system):
    x_{k+1} = R x_k + h b^T (I + h a A)^{-1} U, with the stage inputs U_i = l(tau_i) . P_k;
    it must be reproduced to rounding. Exact ODE solution: with g0 = (1 - e^{-a D}) / a and
    g1 = g0 - (1 - e^{-a D} (1 + a D)) / (a^2 D), x(t_{k+1}) = e^{-a D} x(t_k) + P_k0 (g0 - g1)
    + P_k1 g1, so dx_n/dP_j = e^{-a (t_n - t_{j+1})} (g0 - g1, g1); C converges to it at the
    method's order.
    """
    a_rate, nodes = 3.0, (0.0, 1.0)
    t = torch.linspace(0.0, 2.0, 5, dtype=F64)
    P_in = torch.randn(4, 2, 1, generator=torch.Generator().manual_seed(3), dtype=F64)
    u = CollocationInput(P_in, t, nodes)
    tab = {"rk4": tableau("rk4"), "gauss_legendre": gauss_legendre(2), "radau_iia": radau_iia(3)}
    tab = tab[method]

    def model(tt, x, uu):
        return -a_rate * x + uu

    x0 = torch.tensor([0.7], dtype=F64)
    D = 0.5
    # discrete closed form with substeps = 2
    res = sensitivities(model, x0, t, method=tab, u=u, substeps=2)
    h = D / 2
    A_rk, b_rk = torch.as_tensor(tab.A.copy()), torch.as_tensor(tab.b.copy())
    S = torch.linalg.inv(torch.eye(tab.stages, dtype=F64) + h * a_rate * A_rk)  # stage solve
    R = 1.0 - h * a_rate * (b_rk @ S @ torch.ones(tab.stages, dtype=F64))
    x = x0.clone()
    C_step = torch.zeros(2, dtype=F64)  # dx_{k+1}/dP_k
    for k in range(4):
        for m in range(2):
            L = torch.stack([lagrange_weights(nodes, (m + float(c)) / 2) for c in tab.c])
            x = R * x + h * (b_rk @ S @ (L @ P_in[k, :, 0]))
            if k == 0:
                C_step = R * C_step + h * (b_rk @ S @ L)
        torch.testing.assert_close(res.x[k + 1], x, rtol=0, atol=1e-14)
    for n in range(1, 5):
        expected = R ** (2 * (n - 1)) * C_step
        torch.testing.assert_close(res.C[n, 0, 0, :, 0], expected, rtol=1e-13, atol=1e-15)

    # exact ODE sensitivities and the convergence order
    e = math.exp(-a_rate * D)
    g0 = (1 - e) / a_rate
    g1 = g0 - (1 - e * (1 + a_rate * D)) / (a_rate**2 * D)
    exact = torch.zeros(5, 4, 2, dtype=F64)
    for n in range(1, 5):
        for j in range(n):
            exact[n, j] = math.exp(-a_rate * D * (n - 1 - j)) * torch.tensor(
                [g0 - g1, g1], dtype=F64
            )
    errors = [
        float(
            (sensitivities(model, x0, t, method=tab, u=u, substeps=m).C[:, 0, :, :, 0] - exact)
            .abs()
            .max()
        )
        for m in (4, 8)
    ]
    assert errors[1] < 1e-5
    assert order - 0.3 < math.log2(errors[0] / errors[1]) < order + 0.6, errors


@pytest.mark.parametrize("kind", ["discrete", "variational"])
def test_a_member_escaping_to_infinity_gets_a_status_a_message_and_nan(kind):
    """x' = p x^2 escapes to infinity at t = 1 / (p x0): from x0 = 1 within [0, 2], not from
    x0 = 0.2. The escaping member returned inf / NaN states and sensitivities with no status
    or message (odeint reports NON_FINITE); now its x, A and B are NaN from the first
    non-finite output time on, as odeint's x, with status NON_FINITE and one message, and the
    other member equals its run alone (closed forms x = x0 / (1 - p x0 t), dx/dx0 =
    1 / (1 - p x0 t)^2 to RK4's accuracy)."""
    t = torch.linspace(0.0, 2.0, 21, dtype=torch.float64)
    x0 = torch.tensor([[1.0], [0.2]], dtype=torch.float64)
    p = torch.tensor([1.0], dtype=torch.float64)

    def f(t, x, p):
        return p[..., :1] * x * x

    def run(x0):
        if kind == "discrete":
            return sensitivities(f, x0, t, p, method="rk4", substeps=4)
        return variational_sensitivities(f, x0, t, p, method="rk4", substeps=4)

    res = run(x0)
    assert res.status.tolist() == [int(Status.NON_FINITE), int(Status.SUCCESS)]
    assert not res.success and len(res.messages) == 1 and "sample 0" in res.messages[0]
    sim = odeint(lambda t, x: x * x, x0, t, method="rk4", substeps=4)
    late = torch.isnan(sim.x[0, :, 0])
    assert late.any() and (torch.isnan(res.x[0, :, 0]) == late).all()
    assert torch.isnan(res.A[0, late]).all() and torch.isnan(res.B[0, late]).all()
    assert torch.isfinite(res.A[0, ~late]).all() and torch.isfinite(res.B[0, ~late]).all()
    alone = run(x0[1:])
    torch.testing.assert_close(res.x[1:], alone.x, rtol=1e-14, atol=0)
    torch.testing.assert_close(res.A[1:], alone.A, rtol=1e-14, atol=0)
    exact = 0.2 / (1 - 0.2 * t)
    torch.testing.assert_close(res.x[1, :, 0], exact, rtol=1e-6, atol=0)
    torch.testing.assert_close(res.A[1, :, 0, 0], (exact / 0.2) ** 2, rtol=1e-5, atol=0)
