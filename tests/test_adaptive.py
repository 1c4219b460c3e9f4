"""Adaptive Dormand-Prince 5(4) (notes §6.5, eqs. 6.44-6.45): accuracy against scipy's DOP853,
dense output, per-sample batching, failure statuses, gradients and float32."""

import math
import re

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.integrate import solve_ivp

from integrators import (
    ButcherTableau,
    IController,
    InputValidationError,
    PIController,
    Status,
    odeint,
    solve_adaptive,
    tableau,
)
from integrators.dense import continuous_extension, dopri5_dense_weights
from integrators.inputs import bind_rhs
from sysid.zoo import LinearTestEquation, Lorenz, Quadratic, VanDerPol

pytestmark = pytest.mark.usefixtures("float64_default")


def _reference(f, x0, t, rtol=1e-13, atol=1e-13):
    """scipy DOP853 on one sample: (len(t), nx)."""

    def fn(tt, y):
        with torch.no_grad():
            return f(torch.tensor([[tt]]), torch.tensor(y)[None])[0].numpy()

    out = solve_ivp(fn, (t[0], t[-1]), x0, method="DOP853", rtol=rtol, atol=atol, t_eval=t)
    assert out.success
    return out.y.T


def _weighted_error(x, ref, tol):
    return float(np.max(np.abs(x - ref) / (tol + tol * np.abs(ref))))


# --------------------------------------------------------------------------- the tableau
def test_dopri5_pair_orders_5_and_4_not_both_5():
    """Typo in the notes (after eq. 6.44): 'both steps are of order 5'. The b row has order 5,
    the embedded b_hat row only order 4 -- which is what makes b - b_hat an error estimate."""
    tab = tableau("dopri5")
    assert tab.order == 5
    assert tab.embedded_order == 4
    assert np.max(np.abs(tab.order_residuals(5, tab.b_err))) > 1e-4
    assert tab.is_fsal  # eq. 6.45: K_7 of step k is K_1 of step k + 1


# ----------------------------------------------------------------- continuous extension
@pytest.mark.parametrize("theta", [0.1, 0.35, 0.5, 0.8, 1.0])
def test_dense_weights_satisfy_order_conditions_up_to_4(theta):
    """sum_i b_i(theta) Phi_i(tau) = theta^|tau| / gamma(tau) for |tau| <= 4, not for 5."""
    tab = tableau("dopri5")
    ext = continuous_extension(tab)
    w = ext.stage_weights([theta])[0]
    for q in range(1, 5):
        assert np.max(np.abs(tab.order_residuals(q, w / theta**q))) < 1e-12
    if theta < 1.0:
        assert np.max(np.abs(tab.order_residuals(5, w / theta**5))) > 1e-5


def test_dense_weights_hermite_conditions():
    """b(1) = b (reproduces x_{k+1}), b'(0) = e_1 (slope K_1), b'(1) = e_7 (slope K_7)."""
    tab = tableau("dopri5")
    w = dopri5_dense_weights()
    np.testing.assert_allclose(w.sum(axis=1), tab.b, atol=1e-15)
    np.testing.assert_allclose(w[:, 0], np.eye(7)[0], atol=1e-15)
    np.testing.assert_allclose(w @ np.arange(1, 5), np.eye(7)[6], atol=1e-14)


def test_interpolant_has_order_4():
    """One step of size h on x' = x^2 (eq. 1.44, exact 1/(1/x0 - t)): the interpolant's error
    at theta = 0.37 is O(h^5) (local error of a 4th-order continuous extension)."""
    f = Quadratic()
    x0 = torch.tensor([[0.5]])
    errors, hs = [], [0.4, 0.2, 0.1, 0.05]
    for h in hs:
        sol = solve_adaptive(f, x0, torch.tensor([0.0, h]), rtol=1.0, atol=1.0, dt0=h)
        assert int(sol.stats.n_steps[0]) == 1
        s = 0.37 * h
        errors.append(abs(float(sol.at(s)[0, 0, 0]) - 1.0 / (2.0 - s)))
        # theta = 1 reproduces the step's end point to rounding
        assert float(sol.at(h)[0, 0, 0]) == pytest.approx(float(sol.x[0, -1, 0]), abs=1e-15)
    slopes = np.diff(np.log(errors)) / np.diff(np.log(hs))
    assert np.all(slopes > 4.6), slopes


# ----------------------------------------------------------------------- accuracy
@pytest.mark.parametrize(
    "plant,x0,horizon",
    [(VanDerPol(1.0), [2.0, 0.0], 5.0), (Lorenz(), [1.0, 1.0, 1.0], 1.0)],
    ids=["vanderpol", "lorenz"],
)
def test_dopri5_meets_tolerance_and_error_decreases(plant, x0, horizon):
    t = np.linspace(0.0, horizon, 41)
    ref = _reference(plant, x0, t)
    errors = []
    for tol in (1e-5, 1e-8):
        sol = solve_adaptive(plant, torch.tensor([x0]), torch.tensor(t), rtol=tol, atol=tol)
        assert sol.success
        x = sol.x[0].detach().numpy()
        assert _weighted_error(x, ref, tol) < 30.0
        errors.append(np.max(np.abs(x - ref)))
    assert errors[1] < errors[0] / 100.0


@pytest.mark.parametrize(
    "plant,x0,horizon",
    [(VanDerPol(1.0), [2.0, 0.0], 5.0), (Lorenz(beta=3.0), [1.0, 1.0, 1.0], 1.0)],
    ids=["vanderpol", "lorenz"],
)
def test_dopri5_meets_tolerance_1e10(plant, x0, horizon):
    """rtol = atol = 1e-10 on Van der Pol (eq. 6.43, mu = 1, t in [0, 5]) and Lorenz (eq. 6.9,
    sigma = 10, rho = 28, beta = 3 as in the notes, x0 = (1, 1, 1), t in [0, 1]) against
    scipy's DOP853 at 1e-13 on 41 output times: max |x - ref| / (tol + tol |ref|) <= 10
    (measured 2.5 and 2.8: margins 4x and 3.6x)."""
    t = np.linspace(0.0, horizon, 41)
    ref = _reference(plant, x0, t)
    with torch.no_grad():
        sol = solve_adaptive(plant, torch.tensor([x0]), torch.tensor(t), rtol=1e-10, atol=1e-10)
    assert sol.success
    assert _weighted_error(sol.x[0].numpy(), ref, 1e-10) <= 10.0


def test_dense_output_off_grid_matches_reference():
    plant, x0 = VanDerPol(1.0), [2.0, 0.0]
    sol = solve_adaptive(plant, torch.tensor([x0]), torch.tensor([0.0, 6.0]), rtol=1e-8, atol=1e-8)
    s = np.sort(np.random.default_rng(0).uniform(0.0, 6.0, 25))
    ref = _reference(plant, x0, np.concatenate([[0.0], s]))[1:]
    x = sol.at(torch.tensor(s))[0].detach().numpy()
    assert _weighted_error(x, ref, 1e-8) < 30.0
    # the end point of the dense output is the last state
    assert torch.equal(sol.at(6.0)[:, 0], sol.x[:, -1])
    with pytest.raises(InputValidationError, match="covers"):
        sol.at(6.5)


@pytest.mark.parametrize("controller", [IController(), PIController(), PIController(0.7, -0.4)])
def test_i_and_pi_controllers_meet_tolerance(controller):
    plant, x0, t = VanDerPol(1.0), [2.0, 0.0], np.linspace(0.0, 5.0, 21)
    ref = _reference(plant, x0, t)
    sol = solve_adaptive(
        plant, torch.tensor([x0]), torch.tensor(t), rtol=1e-7, atol=1e-7, controller=controller
    )
    assert _weighted_error(sol.x[0].detach().numpy(), ref, 1e-7) < 30.0


def test_stats_count_fsal_evaluations():
    """FSAL: 6 new evaluations per attempt, plus f(x0) and the initial-step probe."""
    mu = torch.tensor([[0.5], [3.0]])
    sol = solve_adaptive(VanDerPol(mu), torch.tensor([[2.0, 0.0]] * 2), torch.tensor([0.0, 3.0]))
    attempts = sol.stats.n_steps + sol.stats.n_rejected
    assert torch.equal(sol.stats.n_f_evals, 2 + 6 * attempts)
    assert sol.stats.extra["n_rhs_calls"] == 2 + 6 * sol.stats.extra["n_iterations"]
    assert int(sol.stats.n_steps[1]) > int(sol.stats.n_steps[0])


# ------------------------------------------------------------------- batch invariance
def test_batch_members_get_their_own_steps():
    """Easy and hard Van der Pol members in one batch: each gets exactly the answer and the
    step counts it gets alone (per-sample step size, error norm and decisions)."""
    mus = [0.3, 18.0, 1.0, 6.0]
    x0 = torch.tensor([[2.0, 0.0], [0.5, 1.0], [0.0, 2.0], [1.0, -1.0]])
    t = torch.linspace(0.0, 6.0, 13)
    batch = solve_adaptive(VanDerPol(torch.tensor(mus)[:, None]), x0, t, rtol=1e-6, atol=1e-9)
    assert batch.success
    for i, mu in enumerate(mus):
        alone = solve_adaptive(
            VanDerPol(torch.tensor([[mu]])), x0[i : i + 1], t, rtol=1e-6, atol=1e-9
        )
        torch.testing.assert_close(batch.x[i], alone.x[0], rtol=0.0, atol=1e-12)
        for name in ("n_steps", "n_rejected", "n_f_evals"):
            assert int(getattr(batch.stats, name)[i]) == int(getattr(alone.stats, name)[0])
        s = torch.tensor([0.123, 4.567, 5.9])
        torch.testing.assert_close(batch.at(s)[i], alone.at(s)[0], rtol=0.0, atol=1e-12)
    steps = batch.stats.n_steps
    assert int(steps[1]) > 3 * int(steps[0])


def test_multi_dimensional_batch_shape():
    mu = torch.tensor([[0.5, 2.0, 4.0], [1.0, 3.0, 8.0]])[..., None]  # (2, 3, 1)
    x0 = torch.tensor([2.0, 0.0]).expand(2, 3, 2)
    sol = solve_adaptive(VanDerPol(mu), x0, torch.linspace(0.0, 2.0, 5))
    assert sol.x.shape == (2, 3, 5, 2) and sol.status.shape == (2, 3)
    flat = solve_adaptive(
        VanDerPol(mu.reshape(6, 1)), x0.reshape(6, 2), torch.linspace(0.0, 2.0, 5)
    )
    torch.testing.assert_close(sol.x.reshape(6, 5, 2), flat.x, rtol=0.0, atol=1e-12)


def test_tensor_tolerances_per_component_and_per_sample():
    """Tensor rtol/atol broadcast to the states (*batch, nx): per component (nx,) and per
    sample (*batch, 1) tolerances whose entries all equal the scalar give exactly the scalar
    run; a shape that does not broadcast raises naming both shapes."""
    mu = torch.tensor([[0.5, 2.0, 4.0], [1.0, 3.0, 8.0]])[..., None]  # (2, 3, 1)
    x0 = torch.tensor([2.0, 0.0]).expand(2, 3, 2)
    t = torch.linspace(0.0, 2.0, 5)
    scalar = solve_adaptive(VanDerPol(mu), x0, t, rtol=1e-6, atol=1e-8)
    for rtol, atol in (
        (1e-6, torch.full((2,), 1e-8)),
        (torch.full((2, 3, 1), 1e-6), torch.full((2, 3, 1), 1e-8)),
        (torch.full((3, 2), 1e-6), torch.full((2, 3, 2), 1e-8)),
    ):
        sol = solve_adaptive(VanDerPol(mu), x0, t, rtol=rtol, atol=atol)
        assert torch.equal(sol.x, scalar.x)
        assert torch.equal(sol.stats.n_steps, scalar.stats.n_steps)
    with pytest.raises(
        InputValidationError, match=r"atol of shape \(3,\) does not broadcast to \(2, 3, 2\)"
    ):
        solve_adaptive(VanDerPol(mu), x0, t, atol=torch.full((3,), 1e-8))
    with pytest.raises(
        InputValidationError, match=r"rtol of shape \(2, 1, 2, 2\) does not broadcast"
    ):
        solve_adaptive(VanDerPol(mu), x0, t, rtol=torch.full((2, 1, 2, 2), 1e-6))


# ----------------------------------------------------------------------- failures
def test_max_steps_status_message_and_nan_tail():
    mu = torch.tensor([[0.2], [20.0]])
    x0 = torch.tensor([[2.0, 0.0], [2.0, 0.0]])
    t = torch.linspace(0.0, 30.0, 31)
    sol = solve_adaptive(VanDerPol(mu), x0, t, rtol=1e-6, atol=1e-6, max_steps=250)
    assert sol.status.tolist() == [Status.SUCCESS, Status.MAX_STEPS]
    assert len(sol.messages) == 1 and "sample 1" in sol.messages[0]
    reached = float(sol.stats.extra["t_reached"][1])
    assert 0.0 < reached < 30.0 and f"t = {reached:.6g}"[:8] in sol.messages[0]
    beyond = t > reached
    assert torch.isnan(sol.x[1, beyond]).all() and torch.isfinite(sol.x[1, ~beyond]).all()
    assert torch.isfinite(sol.x[0]).all()
    assert int(sol.stats.n_steps[1] + sol.stats.n_rejected[1]) == 250


def test_finite_escape_time_is_reported_while_other_member_succeeds():
    """x' = x^2 (eq. 1.44): x0 = 1 escapes at t = 1; x0 = -1 decays as -1/(1 + t)."""
    x0 = torch.tensor([[1.0], [-1.0]])
    t = torch.linspace(0.0, 2.0, 9)
    sol = solve_adaptive(Quadratic(), x0, t, rtol=1e-8, atol=1e-8)
    assert int(sol.status[0]) in (Status.NON_FINITE, Status.STEP_TOO_SMALL)
    assert int(sol.status[1]) == Status.SUCCESS
    reached = float(sol.stats.extra["t_reached"][0])
    assert abs(reached - 1.0) < 1e-3
    assert "sample 0" in sol.messages[0]
    stated = float(re.search(r"t = ([0-9.e+-]+)", sol.messages[0]).group(1))
    assert abs(stated - 1.0) < 1e-3
    torch.testing.assert_close(sol.x[1, :, 0], -1.0 / (1.0 + t), rtol=1e-7, atol=1e-8)
    assert torch.isnan(sol.x[0, t > 1.0]).all()
    early = t < 0.9
    torch.testing.assert_close(sol.x[0, early, 0], 1.0 / (1.0 - t[early]), rtol=1e-6, atol=0.0)


def test_non_finite_initial_derivative():
    def f(t, x):
        return 1.0 / x

    sol = solve_adaptive(f, torch.tensor([[0.0], [1.0]]), torch.tensor([0.0, 1.0]))
    assert sol.status.tolist() == [Status.NON_FINITE, Status.SUCCESS]
    assert "sample 0" in sol.messages[0] and "initial" in sol.messages[0]
    assert float(sol.x[1, -1, 0]) == pytest.approx(math.sqrt(3.0), rel=1e-6)


def test_non_finite_trials_are_rejected_then_reported_as_non_finite():
    """f is NaN for t > 0.5 in sample 0 only: its trials past 0.5 are rejected until the step
    underflows (NON_FINITE at t = 0.5); sample 1 (x' = -x) is untouched, gradients finite."""

    def f(t, x):
        return torch.where((t > 0.5) & (x[..., :1] > 0), torch.nan, -x)

    x0 = torch.tensor([[1.0], [-1.0]], requires_grad=True)
    sol = solve_adaptive(f, x0, torch.linspace(0.0, 1.0, 5))
    assert sol.status.tolist() == [Status.NON_FINITE, Status.SUCCESS]
    assert float(sol.stats.extra["t_reached"][0]) == pytest.approx(0.5, abs=1e-12)
    assert "sample 0" in sol.messages[0] and "t = 0.5" in sol.messages[0]
    assert float(sol.x[1, -1, 0].detach()) == pytest.approx(-math.exp(-1.0), rel=1e-6)
    (grad,) = torch.autograd.grad(sol.x[0, 1, 0] + sol.x[1, -1, 0], x0)
    torch.testing.assert_close(
        grad[:, 0], torch.tensor([math.exp(-0.25), math.exp(-1.0)]), rtol=1e-6, atol=0.0
    )


def test_rejects_tableau_without_embedded_pair():
    with pytest.raises(InputValidationError, match="b_err"):
        solve_adaptive(
            VanDerPol(), torch.tensor([[1.0, 0.0]]), torch.tensor([0.0, 1.0]), tableau("rk4")
        )


# ------------------------------------------------------------------ other pairs
def test_non_fsal_pair_with_hermite_dense_output():
    """Heun-Euler 2(1) (not FSAL): f(x_{k+1}) is the extra stage and next K_1; the cubic
    Hermite interpolant is 3rd order, so dense output matches the step accuracy."""
    heun_euler = ButcherTableau(
        [[0.0, 0.0], [1.0, 0.0]], [0.5, 0.5], b_err=[1.0, 0.0], name="heun_euler"
    )
    ext = continuous_extension(heun_euler)
    assert ext.extra_eval and ext.order == 2 and heun_euler.embedded_order == 1
    lam = -torch.tensor([[0.5], [2.0]])
    t = torch.linspace(0.0, 2.0, 7)

    def f(tt, x):
        return lam * x

    sol = solve_adaptive(f, torch.ones(2, 1), t, heun_euler, rtol=1e-5, atol=1e-7)
    assert sol.success
    exact = torch.exp(lam * t)
    assert float((sol.x[..., 0] - exact).abs().max()) < 3e-4
    assert torch.equal(sol.stats.n_f_evals, 2 + 2 * (sol.stats.n_steps + sol.stats.n_rejected))


# --------------------------------------------------------------- autograd, float32
def test_gradient_wrt_x0_matches_finite_differences():
    plant = VanDerPol(1.0)
    t = torch.tensor([0.0, 2.0])
    x0 = torch.tensor([[1.5, -0.5]], requires_grad=True)
    out = solve_adaptive(plant, x0, t, rtol=1e-10, atol=1e-10).x[0, -1]
    jac = torch.stack([torch.autograd.grad(out[i], x0, retain_graph=True)[0][0] for i in range(2)])
    fd = torch.zeros(2, 2)
    eps = 1e-5
    for j in range(2):
        d = torch.zeros(1, 2)
        d[0, j] = eps
        with torch.no_grad():
            up = solve_adaptive(plant, x0 + d, t, rtol=1e-10, atol=1e-10).x[0, -1]
            dn = solve_adaptive(plant, x0 - d, t, rtol=1e-10, atol=1e-10).x[0, -1]
        fd[:, j] = (up - dn) / (2 * eps)
    torch.testing.assert_close(jac, fd, rtol=1e-4, atol=1e-5)


def test_gradient_wrt_parameter_matches_finite_differences():
    mu = torch.nn.Parameter(torch.tensor(0.8))
    plant = VanDerPol(1.0)
    plant.mu = mu
    t = torch.tensor([0.0, 1.5])
    x0 = torch.tensor([[2.0, 0.0]])
    out = solve_adaptive(plant, x0, t, rtol=1e-10, atol=1e-10).x[0, -1].sum()
    (grad,) = torch.autograd.grad(out, mu)
    vals = []
    for m in (0.8 + 1e-5, 0.8 - 1e-5):
        with torch.no_grad():
            vals.append(
                float(solve_adaptive(VanDerPol(m), x0, t, rtol=1e-10, atol=1e-10).x[0, -1].sum())
            )
    assert float(grad) == pytest.approx((vals[0] - vals[1]) / 2e-5, rel=1e-4)


def _dopri5_accepted_steps(sol):
    """Start times and sizes (numpy) of the accepted steps of a one-sample dopri5 solution.
    Not public: read from the dense-output closure ``sol.interpolant`` (``start`` and ``h``,
    (batch, records) tensors of ``integrators.adaptive._StepRecord``), where rejected trials
    and the closing record have ``h = 0``."""
    cells = sol.interpolant.__code__.co_freevars, sol.interpolant.__closure__
    cells = {name: cell.cell_contents for name, cell in zip(*cells, strict=True)}
    start, h = cells["start"][0].numpy(), cells["h"][0].numpy()
    return start[h > 0], h[h > 0]


def test_dopri5_gradients_equal_fixed_grid_gradients_and_central_differences(
    central_difference, accepted_grid, same_values_and_gradients
):
    """Gradients through odeint(method="dopri5") at rtol = atol = 1e-8 on Van der Pol (eq. 6.43,
    mu = 2 an nn.Parameter), x0 = (2, 0), t in [0, 3], loss L = x1(3) + x2(3) + x1(3)^2, with
    respect to x0 and mu. Central differences of the adaptive solver are polluted by its step
    sequence moving with the perturbation (3e-7 relative here), so the truth uses the same
    steps: (a) the dopri5 tableau at fixed steps (odeint(method=tableau("dopri5"),
    adaptive=False)) on exactly the accepted step times (74 steps) gives the same x(T) to
    1e-12 relative (measured 4e-15); (b) backpropagation through the adaptive run (step sizes
    detached) gives its gradients to 1e-10 (measured 1.5e-13); (c) those equal central
    differences of the fixed-grid run to 1e-6 relative (the acceptance bound; measured 4e-9).
    """
    model = VanDerPol(2.0)
    x0 = torch.tensor([[2.0, 0.0]], requires_grad=True)
    t_end = 3.0

    def loss(x_end):
        return x_end.sum() + x_end[0] ** 2

    sol = odeint(model, x0, torch.tensor([0.0, t_end]), method="dopri5", rtol=1e-8, atol=1e-8)
    assert sol.success
    start, h = _dopri5_accepted_steps(sol)
    grid = accepted_grid(start, h, int(sol.stats.n_steps[0]), t_end)
    fixed = odeint(model, x0, grid, method=tableau("dopri5"), adaptive=False)
    g_fixed = same_values_and_gradients(sol.x[0, -1], fixed.x[0, -1], loss, (x0, model.mu))

    def fixed_loss():
        with torch.no_grad():
            x_end = odeint(model, x0, grid, method=tableau("dopri5"), adaptive=False).x[0, -1]
            return loss(x_end)

    for param, g in zip((x0, model.mu), g_fixed, strict=True):
        fd = central_difference(fixed_loss, param)
        assert float((g - fd).abs().max() / g.abs().max()) < 1e-6


def test_float32_works():
    plant, x0, t = VanDerPol(1.0), [2.0, 0.0], np.linspace(0.0, 5.0, 11)
    ref = _reference(plant, x0, t)
    sol = solve_adaptive(
        plant,
        torch.tensor([x0], dtype=torch.float32),
        torch.tensor(t, dtype=torch.float32),
        rtol=1e-5,
        atol=1e-5,
    )
    assert sol.x.dtype == torch.float32 and sol.success
    assert _weighted_error(sol.x[0].detach().double().numpy(), ref, 1e-5) < 30.0


# ----------------------------------------------------------------------- via odeint
def test_odeint_dopri5_dispatches_here():
    mu = torch.tensor([[0.5], [5.0]])
    x0 = torch.tensor([[2.0, 0.0], [1.0, 1.0]])
    t = torch.linspace(0.0, 4.0, 9)
    via_odeint = odeint(VanDerPol(mu), x0, t, method="dopri5", rtol=1e-7, atol=1e-9)
    direct = solve_adaptive(bind_rhs(VanDerPol(mu), None, t), x0, t, rtol=1e-7, atol=1e-9)
    torch.testing.assert_close(via_odeint.x, direct.x, rtol=0.0, atol=1e-13)
    assert torch.equal(via_odeint.stats.n_steps, direct.stats.n_steps)


def test_odeint_dopri5_with_callable_input_per_sample_times():
    """A forced Van der Pol x1' = mu (1 - x2^2) x1 - x2 + u(t), u = 0.5 sin(2t): the input
    callable receives the (*batch, 1) per-sample stage times."""
    t = np.linspace(0.0, 4.0, 9)

    def u(tt):
        return 0.5 * torch.sin(2.0 * tt)

    sol = odeint(
        VanDerPol(1.0),
        torch.tensor([[2.0, 0.0], [0.0, 1.0]]),
        torch.tensor(t),
        method="dopri5",
        u=u,
        rtol=1e-9,
        atol=1e-9,
    )
    for i, x0 in enumerate([[2.0, 0.0], [0.0, 1.0]]):

        def fn(tt, y):
            return [(1 - y[1] ** 2) * y[0] - y[1] + 0.5 * np.sin(2 * tt), y[0]]

        ref = solve_ivp(fn, (0.0, 4.0), x0, method="DOP853", rtol=1e-13, atol=1e-13, t_eval=t).y.T
        assert _weighted_error(sol.x[i].detach().numpy(), ref, 1e-9) < 30.0


def test_sync_period_does_not_change_the_answer():
    """Finished samples take zero steps, so checking 'all done?' rarely changes nothing."""
    mu = torch.tensor([[0.5], [4.0]])
    x0 = torch.tensor([[2.0, 0.0], [1.0, 1.0]])
    t = torch.linspace(0.0, 3.0, 7)
    every = solve_adaptive(VanDerPol(mu), x0, t, check_every=1)
    rarely = solve_adaptive(VanDerPol(mu), x0, t, check_every=50)
    assert torch.equal(every.x, rarely.x)
    assert torch.equal(every.stats.n_f_evals, rarely.stats.n_f_evals)
    assert rarely.stats.extra["n_iterations"] % 50 == 0


@settings(max_examples=8, deadline=None)
@given(
    lams=st.lists(st.floats(-40.0, 2.0), min_size=2, max_size=4),
    tol=st.sampled_from([1e-4, 1e-7, 1e-10]),
)
def test_dahlquist_batch_meets_tolerance_and_is_invariant(lams, tol):
    """x' = lam x (eq. 6.40) with exact x0 exp(lam t): every member within a small multiple of
    the tolerance, and solving the last member alone reproduces its steps."""
    lam = torch.tensor(lams)[:, None]
    plant = LinearTestEquation(lam)
    x0 = torch.ones(len(lams), 1)
    t = torch.linspace(0.0, 1.0, 6)
    sol = solve_adaptive(plant, x0, t, rtol=tol, atol=tol)
    exact = plant.exact(t, x0)
    assert sol.success
    assert float(((sol.x - exact).abs() / (tol + tol * exact.abs())).max().detach()) < 30.0
    alone = solve_adaptive(LinearTestEquation(lam[-1:]), x0[-1:], t, rtol=tol, atol=tol)
    torch.testing.assert_close(sol.x[-1], alone.x[0], rtol=0.0, atol=1e-12)
    assert int(sol.stats.n_steps[-1]) == int(alone.stats.n_steps[0])
    assert int(sol.stats.n_rejected[-1]) == int(alone.stats.n_rejected[0])
