"""The grey-box workflow around the fit, against independent truth: fit statistics against
numpy formulas, Ctrl-C against a run stopped by its iteration limit, start values from an
identified linear model (inverse zero-order hold against python-control's sampling), zoo
cranes with per-member parameters against single simulations and the notes' crane
equations, and an output offset estimated as an ordinary parameter."""

import math

import control
import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from integrators import odeint
from integrators.errors import InputValidationError
from integrators.newton import NewtonStatus, minimize
from sysid import OE, GreyBoxModel, IOData, Param, fit, fit_quality
from sysid.continuous import d2c, start_values
from sysid.montecarlo import input_signal
from sysid.validation import fit_percent
from sysid.zoo import Crane


def first_order(t, x, u, p):
    """x' = -a x + b u."""
    return (-p["a"] * x[..., 0] + p["b"] * u[..., 0]).unsqueeze(-1)


def smd(t, x, u, p):
    """m y'' + d y' + k y = u."""
    acc = (u[..., 0] - p["d"] * x[..., 1] - p["k"] * x[..., 0]) / p["m"]
    return torch.stack([x[..., 1], acc], -1)


def record(f, params, nx, N, seed, Ts=0.1, noise=0.01, batch=(), output=(0,), hold=3):
    g = torch.Generator().manual_seed(seed)
    u = input_signal("prbs", N, batch, hold=hold, generator=g)
    truth = GreyBoxModel(
        f, dict(params), nx=nx, output=output if callable(output) else list(output)
    )
    y = truth.simulate(IOData(u, u[..., :1], Ts=Ts))
    return IOData(u, y + noise * torch.randn(y.shape, generator=g, dtype=y.dtype), Ts=Ts)


# ------------------------------------------------------------------------ fit statistics
def test_fit_quality_matches_numpy_and_skip_drops_the_first_samples():
    rng = np.random.default_rng(0)
    y = rng.standard_normal((3, 50, 2)).cumsum(1)
    yhat = y + 0.3 * rng.standard_normal(y.shape)
    skip = 7
    a, b = y[:, skip:], yhat[:, skip:]
    err = np.sqrt(((a - b) ** 2).sum(1))
    dev = np.sqrt(((a - a.mean(1, keepdims=True)) ** 2).sum(1))
    q = fit_quality(torch.tensor(y), torch.tensor(yhat), skip=skip)
    np.testing.assert_allclose(q.fit_percent.numpy(), 100 * (1 - err / dev), rtol=1e-12)
    np.testing.assert_allclose(q.rmse.numpy(), np.sqrt(((a - b) ** 2).mean(1)), rtol=1e-12)
    np.testing.assert_allclose(q.r_squared.numpy(), 1 - err**2 / dev**2, rtol=1e-12)
    # garbage in the skipped samples does not matter; fit_percent agrees
    y_bad = y.copy()
    y_bad[:, :skip] = 1e6
    q_bad = fit_quality(torch.tensor(y_bad), torch.tensor(yhat), skip=skip)
    assert torch.equal(q_bad.fit_percent, q.fit_percent)
    assert torch.equal(
        fit_percent(torch.tensor(y_bad), torch.tensor(yhat), skip=skip), q.fit_percent
    )
    with pytest.raises(InputValidationError, match="skip"):
        fit_quality(torch.tensor(y), torch.tensor(yhat), skip=49)


def test_greybox_result_reports_fit_statistics_and_validates_with_skip():
    params = {"a": 2.0, "b": 3.0}
    data = record(first_order, params, 1, 60, seed=1, batch=(2,))
    res = fit(GreyBoxModel(first_order, {"a": Param(1.0, min=0), "b": 1.0}, nx=1), data)
    yhat = GreyBoxModel(first_order, {"a": 1.0, "b": 1.0}, nx=1).simulate(data, res.params)
    y, e = data.y.numpy(), (data.y - yhat).numpy()
    dev = np.sqrt(((y - y.mean(1, keepdims=True)) ** 2).sum(1))
    fit_np = 100 * (1 - np.sqrt((e**2).sum(1)) / dev)
    np.testing.assert_allclose(res.quality.fit_percent.numpy(), fit_np, rtol=1e-9)
    np.testing.assert_allclose(res.quality.rmse.numpy(), np.sqrt((e**2).mean(1)), rtol=1e-9)
    assert float(res.quality.rmse.max()) < 0.015  # noise 0.01
    # validation data whose first 10 samples are garbage: skip=10 gives the clean numbers
    val = record(first_order, params, 1, 80, seed=2, batch=(2,))
    bad_y = val.y.clone()
    bad_y[:, :10] = 50.0
    clean = res.validate(val, skip=10)
    dirty = res.validate(IOData(val.u, bad_y, Ts=val.Ts), skip=10)
    torch.testing.assert_close(dirty.fit_percent, clean.fit_percent, rtol=0, atol=1e-12)
    yv = res.model.simulate(val, x0=torch.zeros(1))[:, 10:].numpy()
    ref = 1 - ((val.y[:, 10:].numpy() - yv) ** 2).sum(1) / (
        (val.y[:, 10:].numpy() - val.y[:, 10:].numpy().mean(1, keepdims=True)) ** 2
    ).sum(1)
    np.testing.assert_allclose(clean.r_squared.numpy(), ref, rtol=1e-9)
    assert float(res.validate(IOData(val.u, bad_y, Ts=val.Ts)).fit_percent.max()) < 0


# ------------------------------------------------------------------------ Ctrl-C
def rosenbrock_residual(theta):
    return torch.stack([10 * (theta[..., 1] - theta[..., 0] ** 2), 1 - theta[..., 0]], -1)


def test_minimize_callback_interrupt_returns_the_iterate_of_a_max_iter_run():
    th0 = torch.tensor([[-1.2, 1.0], [0.5, -0.3]], dtype=torch.float64)
    seen = []

    def stop_at_4(iteration, theta, loss):
        seen.append((iteration, loss.clone()))
        if iteration == 4:
            raise KeyboardInterrupt

    kw = dict(method="levenberg_marquardt", xtol=1e-14, ftol=1e-14, tol=0.0)
    ref = minimize(rosenbrock_residual, th0, max_iter=4, **kw)
    out = minimize(rosenbrock_residual, th0, callback=stop_at_4, catch_interrupt=True, **kw)
    assert torch.equal(out.theta, ref.theta) and torch.equal(out.J, ref.J)
    assert torch.equal(out.loss_history, ref.loss_history)
    assert (out.status == NewtonStatus.INTERRUPTED).all() and not out.converged.any()
    assert [i for i, _ in seen] == [1, 2, 3, 4]
    assert torch.equal(seen[-1][1], ref.loss)
    with pytest.raises(KeyboardInterrupt):
        minimize(rosenbrock_residual, th0, callback=stop_at_4, **kw)


def test_minimize_interrupt_inside_the_residual_keeps_the_last_accepted_iterate():
    calls = [0]

    def residual(theta):
        calls[0] += 1
        if calls[0] == 9:
            raise KeyboardInterrupt
        return rosenbrock_residual(theta)

    th0 = torch.tensor([-1.2, 1.0], dtype=torch.float64)
    kw = dict(method="levenberg_marquardt", xtol=1e-14, ftol=1e-14, tol=0.0)
    out = minimize(residual, th0, catch_interrupt=True, **kw)
    k = int(out.iterations)
    assert 0 < k < 8
    ref = minimize(rosenbrock_residual, th0, max_iter=k, **kw)
    assert torch.equal(out.theta, ref.theta) and torch.equal(out.residual, ref.residual)
    assert int(out.status) == NewtonStatus.INTERRUPTED


def test_greybox_fit_interrupted_returns_the_last_iterate_and_says_so():
    params = {"a": 2.0, "b": 3.0}
    data = record(first_order, params, 1, 40, seed=3)
    calls = [0]

    def interrupting(t, x, u, p):
        calls[0] += 1
        if calls[0] == 1500:  # within the third iteration (about 310 calls per iteration)
            raise KeyboardInterrupt
        return first_order(t, x, u, p)

    start = {"a": Param(0.3, min=0), "b": 0.5}
    with pytest.warns(Warning, match="interrupted"):
        out = fit(GreyBoxModel(interrupting, start, nx=1), data, progress=False)
    k = int(out.iterations)
    assert 0 < k < 5
    with pytest.warns(Warning):
        ref = fit(GreyBoxModel(first_order, start, nx=1), data, max_iter=k, progress=False)
    torch.testing.assert_close(out.theta, ref.theta, rtol=0, atol=0)
    assert not bool(out.converged) and bool(out.info["interrupted"])
    assert "interrupted" in out.messages[0]
    final = fit(GreyBoxModel(first_order, start, nx=1), data, progress=False)
    assert float((final.theta - out.theta).abs().max()) > 1e-3  # the work was cut short


def test_an_interrupted_fit_of_x0_says_how_to_finish_it():
    """The fitted model of an interrupted fit holds x0 as known: the advice in its message
    estimates x0 again (it said fit(result.model, data), which froze x0 at the interrupted
    value and gave standard errors 35-45 % too small); following it gives the uninterrupted
    fit."""
    data = record(first_order, {"a": 2.0, "b": 3.0}, 1, 40, seed=5)
    calls = [0]

    def interrupting(t, x, u, p):
        calls[0] += 1
        if calls[0] == 1500:
            raise KeyboardInterrupt
        return first_order(t, x, u, p)

    start = {"a": Param(0.3, min=0), "b": 0.5}
    with pytest.warns(Warning, match="interrupted"):
        out = fit(GreyBoxModel(interrupting, start, nx=1, x0="estimate"), data)
    assert "fit(result.model, data, x0='estimate')" in out.messages[0]
    finished = fit(out.model, data, x0="estimate")
    whole = fit(GreyBoxModel(first_order, start, nx=1, x0="estimate"), data)
    assert finished.parameter_names == whole.parameter_names == ["a", "b", "x0.0"]
    torch.testing.assert_close(finished.theta, whole.theta, rtol=1e-7, atol=1e-9)
    torch.testing.assert_close(finished.standard_errors, whole.standard_errors, rtol=1e-5, atol=0)


def test_a_fit_ending_on_its_iteration_limit_says_so():
    """A grey-box fit that ends on max_iter is flagged in info["iteration_limit_reached"] (as
    a polynomial model's fit is), and, where it is not converged, its message names the
    limit; a fit stopped by its own criteria is not flagged."""
    data = record(first_order, {"a": 2.0, "b": 3.0}, 1, 40, seed=6)
    model = GreyBoxModel(first_order, {"a": Param(0.3, min=0), "b": 0.5}, nx=1)
    with pytest.warns(Warning, match="iteration limit"):
        cut = fit(model, data, max_iter=1)
    assert bool(cut.info["iteration_limit_reached"]) and not bool(cut.converged)
    assert "the iteration limit (max_iter) was reached" in cut.messages[0]
    whole = fit(model, data)
    assert bool(whole.converged) and not bool(whole.info["iteration_limit_reached"])


def test_progress_bar_shows_iterations_and_loss(capsys):
    data = record(first_order, {"a": 2.0, "b": 3.0}, 1, 30, seed=4)
    fit(GreyBoxModel(first_order, {"a": Param(1.0, min=0), "b": 1.0}, nx=1), data, progress=True)
    err = capsys.readouterr().err
    assert "grey-box fit" in err and "loss=" in err
    fit(GreyBoxModel(first_order, {"a": Param(1.0, min=0), "b": 1.0}, nx=1), data)
    assert capsys.readouterr().err == ""  # None: off when stderr is not a terminal


# ------------------------------------------------------------------------ start values
@settings(max_examples=30, deadline=None)
@given(
    st.integers(1, 3),
    st.integers(0, 10_000),
    st.floats(0.01, 0.5),
)
def test_d2c_inverts_zero_order_hold_sampling(n, seed, Ts):
    rng = np.random.default_rng(seed)
    # a stable A with eigenvalues Ts |Im| < 3 (principal branch of the logarithm)
    re = -rng.uniform(0.1, 5.0, n)
    im = rng.uniform(0.0, 2.5 / Ts, n) * (rng.uniform(size=n) < 0.5)
    blocks, i = [], 0
    while i < n:
        if i + 1 < n and im[i] > 0:
            blocks.append(np.array([[re[i], im[i]], [-im[i], re[i]]]))
            i += 2
        else:
            blocks.append(np.array([[re[i]]]))
            i += 1
    T = rng.standard_normal((n, n)) + 3 * np.eye(n)
    A = (
        T
        @ np.block(
            [
                [b if j == k else np.zeros((b.shape[0], c.shape[0])) for k, c in enumerate(blocks)]
                for j, b in enumerate(blocks)
            ]
        )
        @ np.linalg.inv(T)
    )
    B, C, D = rng.standard_normal((n, 1)), rng.standard_normal((1, n)), rng.standard_normal((1, 1))
    sys_c = control.ss(A, B, C, D)
    back = d2c(control.sample_system(sys_c, Ts, "zoh"))
    scale = max(1.0, np.abs(A).max())
    np.testing.assert_allclose(back.A, A, atol=1e-10 * scale)
    np.testing.assert_allclose(back.B, B, atol=1e-10 * max(1.0, np.abs(B).max()) * scale)
    np.testing.assert_allclose(back.C, C, atol=0)
    np.testing.assert_allclose(back.D, D, atol=0)


def test_d2c_refuses_poles_without_a_real_logarithm():
    for den in ([1, 0.5], [1, 0.0]):
        with pytest.raises(InputValidationError, match="negative real axis or at 0"):
            d2c(control.tf([1], den, dt=0.1))


def smd_params(sys_c):
    """1 / (m s^2 + d s + k) = (1/m) / (s^2 + (d/m) s + k/m)."""
    num, den = np.asarray(sys_c.num[0][0]), np.asarray(sys_c.den[0][0])
    m = den[0] / num[-1]
    return {"m": m, "d": den[1] / num[-1], "k": den[2] / num[-1]}


def test_start_values_from_an_oe_fit_lead_the_grey_box_fit_to_the_truth():
    truth = {"m": 1.0, "d": 0.5, "k": 4.0}
    data = record(smd, truth, 2, 300, seed=5, Ts=0.1, noise=0.002, hold=2)
    oe = fit(OE(nb=2, nf=2, nk=1, Ts=0.1), data)
    start = start_values(oe, smd_params)
    for n, v in truth.items():
        assert abs(start[n] - v) < 0.1 * v, (n, start[n])
    model = GreyBoxModel(smd, {n: Param(start[n], min=0) for n in truth}, nx=2, output=[0])
    res = fit(model, data, progress=False)
    assert bool(res.converged)
    for j, n in enumerate(res.parameter_names):
        assert abs(float(res.theta[j]) - truth[n]) < 4 * float(res.standard_errors[j]) + 2e-3


# ------------------------------------------------------------------------ zoo cranes
def crane_notes(t, x, u, M, m, L, g=9.81):
    """The crane of eq. 2.55-2.70 written out: W(q) qdd = Q - h (eq. 2.60, 2.66) with the
    cart force u, solved by numpy-free 2x2 elimination (Cramer's rule)."""
    th, xd, thd = x[..., 1], x[..., 2], x[..., 3]
    s, c = torch.sin(th), torch.cos(th)
    w11, w12, w22 = M + m, m * L * c, m * L**2
    r1 = u[..., 0] + m * L * s * thd**2
    r2 = -m * g * L * s
    det = w11 * w22 - w12**2
    xdd = (r1 * w22 - w12 * r2) / det
    thdd = (w11 * r2 - w12 * r1) / det
    return torch.stack([xd, thd, xdd, thdd], -1)


def test_zoo_crane_with_per_member_masses_equals_single_simulations_and_the_notes():
    g = torch.Generator().manual_seed(6)
    u = 0.5 * input_signal("prbs", 40, (2,), hold=4, generator=g)
    data = IOData(u, torch.zeros(2, 40, 2), Ts=0.05)
    x0 = torch.tensor([0.0, 0.3, 0.0, 0.0], dtype=torch.float64)
    kw = dict(output=["x", "theta"], x0=x0, substeps=8)
    model = GreyBoxModel(Crane(), {"M": 1.0, "m": 0.5}, **kw)
    M = torch.tensor([1.0, 2.5], dtype=torch.float64)
    both = model.simulate(data, params={"M": M})
    for i in range(2):
        one = GreyBoxModel(Crane(M=float(M[i])), {"m": 0.5}, **kw)
        single = one.simulate(IOData(u[i], torch.zeros(40, 2), Ts=0.05))
        torch.testing.assert_close(both[i], single, rtol=0, atol=1e-13)
        # the notes' equations by a fine RK4 with the input held per sample
        t = torch.arange(40, dtype=torch.float64) * 0.05
        sol = odeint(
            lambda t, x, uu, Mi=float(M[i]): crane_notes(t, x, uu, Mi, 0.5, 1.0),
            x0,
            t,
            u=u[i],
            method="rk4",
            substeps=20,
        )
        torch.testing.assert_close(both[i], sol.x[:, :2], rtol=0, atol=1e-8)
    # and a fit of the cart mass per data set (batched parameters) recovers it
    fast = dict(output=["x", "theta"], x0=x0)
    y = GreyBoxModel(Crane(), {"M": 1.0}, **fast).simulate(data, params={"M": M})
    y = y + 1e-4 * torch.randn(y.shape, generator=g, dtype=y.dtype)
    res = fit(GreyBoxModel(Crane(), {"M": Param(1.5, min=0)}, **fast), IOData(u, y, Ts=0.05))
    assert bool((res.theta[:, 0] - M).abs().le(4 * res.standard_errors[:, 0]).all())


# ------------------------------------------------------------------------ offsets
def test_output_offset_is_an_ordinary_parameter():
    params = {"a": 2.0, "b": 3.0, "y0": 0.7}

    def h(x, u, p):
        return (x[..., 0] + p["y0"]).unsqueeze(-1)

    data = record(first_order, params, 1, 80, seed=7, output=h, noise=0.02)
    model = GreyBoxModel(first_order, {"a": Param(1.0, min=0), "b": 1.0, "y0": 0.0}, nx=1, output=h)
    res = fit(model, data, progress=False)
    j = res.parameter_names.index("y0")
    assert abs(float(res.theta[j]) - 0.7) < 3 * float(res.standard_errors[j])
    assert float(res.standard_errors[j]) < 0.02
    assert math.isfinite(float(res.quality.fit_percent))


def test_a_fitted_model_prints_and_fits_again_from_each_data_sets_estimate():
    """``result.model`` holds the estimates (one per data set of a batch, per experiment
    where so declared): it prints, and fitting it again to the same data starts each data set
    at its own optimum, so the estimates and standard errors stay (at most one step, 1e-8),
    also for a per-experiment parameter of two experiments; data of another batch are refused
    by name."""
    truth = {"a": torch.tensor([2.0, 5.0], dtype=torch.float64), "b": torch.tensor(3.0)}

    def batch_of_two(N, seed):
        g = torch.Generator().manual_seed(seed)
        u = input_signal("prbs", N, (2,), hold=3, generator=g)
        y = GreyBoxModel(first_order, {"a": 1.0, "b": 1.0}, nx=1, output=[0]).simulate(
            IOData(u, u, Ts=0.1), params=truth
        )
        return IOData(u, y + 0.01 * torch.randn(y.shape, generator=g, dtype=y.dtype), Ts=0.1)

    data = batch_of_two(60, seed=11)
    model = GreyBoxModel(
        first_order, {"a": Param(1.0, min=0), "b": Param(1.0, min=0)}, nx=1, output=[0]
    )
    first = fit(model, data, progress=False)
    assert "Param([" in repr(first.model)
    again = fit(first.model, data, progress=False)
    assert again.iterations.max() <= 1
    torch.testing.assert_close(again.theta, first.theta, rtol=1e-8, atol=0)
    torch.testing.assert_close(again.standard_errors, first.standard_errors, rtol=1e-6, atol=0)
    single = fit(model, data[0], progress=False)
    assert "Param(" in repr(single.model)
    assert fit(single.model, data[0], progress=False).iterations <= 1
    with pytest.raises(InputValidationError, match=r"parameter 'a' has values of batch \(2,\)"):
        fit(first.model, record(first_order, {"a": 2.0, "b": 3.0}, 1, 60, seed=12, batch=(3,)))
    two = IOData.experiments([data, batch_of_two(40, seed=13)])
    offset = {"a": Param(1.0, min=0), "b": Param([1.0, 1.0], per_experiment=True)}
    per_experiment = fit(GreyBoxModel(first_order, offset, nx=1, output=[0]), two, progress=False)
    assert per_experiment.model.params["b"].values.shape == (2, 2)
    refit = fit(per_experiment.model, two, progress=False)
    assert refit.iterations.max() <= 1
    torch.testing.assert_close(refit.theta, per_experiment.theta, rtol=1e-8, atol=0)
