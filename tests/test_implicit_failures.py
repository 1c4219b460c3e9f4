"""Per-sample failures of the implicit solvers: the outputs after the failure time are NaN
(x and z, and dense output), on every driver, with status and a message naming the sample and
the time; the finite outputs keep finite, correct gradients (also for a parameter shared by
the failed and the healthy members).

Problem: ``x' = p x^2``, ``x(t) = x0 / (1 - p x0 t)``, which escapes to infinity at
``t = 1 / (p x0)``; a fixed implicit step has no stage solution once ``h p x`` is too large.
"""

from __future__ import annotations

import re

import pytest
import torch

from integrators import SemiExplicitDAE, daeint
from integrators.implicit import solve_implicit_ode
from integrators.solution import Status

T_OUT = torch.linspace(0.0, 1.5, 7, dtype=torch.float64)  # step 0.25
P = 1.0


def _x0(batch, failing):
    """The failing initial state alone, or as member 1 of a batch of 3 (the others finish)."""
    if batch is None:
        return torch.tensor([failing], dtype=torch.float64)
    return torch.tensor([[-1.0], [failing], [0.2]], dtype=torch.float64)


def _exact(x0, p, t):
    """(*batch, T, 1) closed form."""
    return x0[..., None, :] / (1 - p * x0[..., None, :] * t[:, None])


def _stop_time(sol, sample):
    """The time named by the failed sample's message."""
    name = f"sample ({sample},)"
    msgs = [m for m in sol.messages if name in m]
    assert msgs, sol.messages
    return float(re.search(r"t = ([0-9.e+-]+)", msgs[0]).group(1))


def _check_outputs(sol, batch, t_stop_range):
    """Status, message and NaN pattern; returns the (*batch, T) mask of finite outputs."""
    k = 0 if batch is None else 1
    fail = sol.status if batch is None else sol.status[1]
    assert int(fail) != Status.SUCCESS
    if batch is not None:
        assert sol.status[[0, 2]].tolist() == [Status.SUCCESS, Status.SUCCESS]
    t_stop = _stop_time(sol, k)
    assert t_stop_range[0] <= t_stop <= t_stop_range[1]
    late = T_OUT > t_stop + 1e-6  # the message rounds t to 6 digits
    member = (lambda v: v) if batch is None else (lambda v: v[1])
    for out in (sol.x, sol.z) if sol.z is not None else (sol.x,):
        assert bool(torch.isnan(member(out)[late]).all()), member(out)
        assert bool(torch.isfinite(member(out)[~late]).all()), member(out)
        if batch is not None:
            assert bool(torch.isfinite(out[[0, 2]]).all())
    if sol.interpolant is not None:  # dense output follows the same rule
        torch.testing.assert_close(sol.at(T_OUT), sol.x, equal_nan=True)
    return torch.isfinite(sol.x).all(-1)


def _masked_grads(run, x0, p, mask):
    """Gradient over (x0, p) of the sum of the outputs under ``mask`` (finite ones)."""
    x0 = x0.clone().requires_grad_(True)
    p = torch.tensor(p, dtype=torch.float64, requires_grad=True)
    out = run(x0, p)
    loss = sum(torch.where(mask[..., None], v, 0.0).sum() for v in out)
    return torch.autograd.grad(loss, (x0, p))


def _fd_grads(run, x0, p, mask, eps=1e-6):
    """Central differences of the same masked loss (the mask fixed)."""

    def loss(x0v, pv):
        with torch.no_grad():
            out = run(x0v, torch.tensor(pv, dtype=torch.float64))
        return float(sum(torch.where(mask[..., None], v, 0.0).sum() for v in out))

    g_x0 = torch.zeros_like(x0)
    for j in range(x0.numel()):
        e = torch.zeros(x0.numel(), dtype=x0.dtype)
        e[j] = eps
        e = e.reshape(x0.shape)
        g_x0.view(-1)[j] = (loss(x0 + e, p) - loss(x0 - e, p)) / (2 * eps)
    g_p = (loss(x0, p + eps) - loss(x0, p - eps)) / (2 * eps)
    return g_x0, torch.tensor(g_p, dtype=torch.float64)


@pytest.mark.parametrize("batch", [None, 3])
@pytest.mark.parametrize("host_loop", [False, True])
def test_adaptive_radau_failure_is_nan_beyond_the_failure_time(batch, host_loop):
    """x0 = 0.7 escapes at t = 1/0.7 = 1.4286; with rtol = 1e-9 adaptive Radau IIA needs more
    than max_steps = 200 steps to get there and stops (MAX_STEPS) after t = 1 (1.15 measured)
    on every driver (the other members need 123 and 45 steps). Its outputs after the stop
    are NaN, the earlier ones finite and exact (1e-6), and the gradient of their sum over
    (x0, p) equals the closed form's (1e-5), with p shared by the failed and the healthy
    members."""
    driver = "torch" if not host_loop else "host" if batch else "host, one trajectory"
    x0 = _x0(batch, 0.7)

    def run(x0v, pv):
        sol = solve_implicit_ode(
            lambda t, x: pv * x**2, x0v, T_OUT, "radau_iia", rtol=1e-9, atol=1e-11,
            host_loop=host_loop, max_steps=200,
        )  # fmt: skip
        assert sol.stats.extra["driver"] == driver
        return sol

    sol = run(x0, P)
    assert int(sol.status.reshape(-1)[0 if batch is None else 1]) == Status.MAX_STEPS
    mask = _check_outputs(sol, batch, (1.0, 1.43))
    exact = _exact(x0, P, T_OUT)
    torch.testing.assert_close(sol.x[mask], exact[mask], rtol=1e-6, atol=0)
    got = _masked_grads(lambda a, b: (run(a, b).x,), x0, P, mask)
    truth = _masked_grads(lambda a, b: (_exact(a, b, T_OUT),), x0, P, mask)
    for g, g_true in zip(got, truth, strict=True):
        assert bool(torch.isfinite(g).all())
        torch.testing.assert_close(g, g_true, rtol=1e-5, atol=0)


@pytest.mark.parametrize("batch", [None, 3])
@pytest.mark.parametrize(
    "method, options, t_stop",
    [
        ("implicit_euler", {}, 0.25),  # x1 = x0 + h x1^2 has no root once 4 h x0 > 1
        ("gauss_legendre", {}, 1.0),
        ("radau_iia", {"adaptive": False}, 1.0),
    ],
)
def test_fixed_step_failure_is_nan_beyond_the_failed_step(method, options, t_stop, batch):
    """x0 = 0.8, h = 0.25: the stage equations of the step from ``t_stop`` have no solution
    (NEWTON_FAILED); the outputs after ``t_stop`` are NaN, the earlier ones finite, and the
    gradient of their sum over (x0, p) equals central differences of that sum (1e-6)."""
    x0 = _x0(batch, 0.8)

    def run(x0v, pv):
        return solve_implicit_ode(lambda t, x: pv * x**2, x0v, T_OUT, method, **options)

    sol = run(x0, P)
    assert int(sol.status.reshape(-1)[0 if batch is None else 1]) == Status.NEWTON_FAILED
    mask = _check_outputs(sol, batch, (t_stop, t_stop))
    got = _masked_grads(lambda a, b: (run(a, b).x,), x0, P, mask)
    for g, g_fd in zip(got, _fd_grads(lambda a, b: (run(a, b).x,), x0, P, mask), strict=True):
        assert bool(torch.isfinite(g).all())
        torch.testing.assert_close(g, g_fd.to(g.dtype), rtol=1e-6, atol=1e-8)


@pytest.mark.parametrize("batch", [None, 3])
@pytest.mark.parametrize("adaptive", [True, False])
def test_daeint_failure_is_nan_beyond_the_failure_time_in_x_and_z(adaptive, batch):
    """``x' = z, 0 = z - p x^2`` (z = p x^2): the same escape as the ODE. Adaptive Radau IIA
    (x0 = 0.7, max_steps = 200: stops after t = 1; gradients against the closed form, 1e-5)
    and fixed
    Gauss-Legendre (x0 = 0.8, NEWTON_FAILED at t = 1; gradients against differences): x and
    z NaN after the failure time, finite before."""
    x0 = _x0(batch, 0.7 if adaptive else 0.8)
    options = (
        dict(rtol=1e-9, atol=1e-11, max_steps=200) if adaptive else dict(method="gauss_legendre")
    )

    def run(x0v, pv):
        problem = SemiExplicitDAE(lambda t, x, z: z, lambda t, x, z: z - pv * x**2)
        return daeint(problem, x0v, torch.zeros_like(x0v), T_OUT, adaptive=adaptive, **options)

    sol = run(x0, P)
    mask = _check_outputs(sol, batch, (1.0, 1.43) if adaptive else (1.0, 1.0))
    both = lambda a, b: (run(a, b).x, run(a, b).z)  # noqa: E731
    got = _masked_grads(both, x0, P, mask)
    if adaptive:

        def exact(a, b):
            x = _exact(a, b, T_OUT)
            return x, b * x**2

        truth = _masked_grads(exact, x0, P, mask)
        tol = dict(rtol=1e-5, atol=0)
    else:
        truth = _fd_grads(both, x0, P, mask)
        tol = dict(rtol=1e-6, atol=1e-8)
    for g, g_true in zip(got, truth, strict=True):
        assert bool(torch.isfinite(g).all())
        torch.testing.assert_close(g, g_true.to(g.dtype), **tol)


@pytest.mark.parametrize("host_loop", [False, True])
def test_adaptive_radau_escape_to_infinity_is_nan_beyond_the_escape(host_loop):
    """x' = x^2 from x0 = 1 escapes at t = 1 (the other member, x0 = -1, decays): the sample
    stops there (STEP_TOO_SMALL or NON_FINITE) and its output at t = 2 is NaN, not the huge
    last state; x(0) stays finite."""
    x0 = torch.tensor([[1.0], [-1.0]], dtype=torch.float64)
    t = torch.tensor([0.0, 2.0], dtype=torch.float64)
    sol = solve_implicit_ode(lambda tt, x: x**2, x0, t, "radau_iia", host_loop=host_loop)
    assert int(sol.status[0]) in (Status.STEP_TOO_SMALL, Status.NON_FINITE)
    assert 0.99 < _stop_time(sol, 0) <= 1.0
    assert bool(torch.isnan(sol.x[0, 1]).all() and torch.isfinite(sol.x[0, 0]).all())
    torch.testing.assert_close(sol.x[1, -1, 0], torch.tensor(-1 / 3, dtype=torch.float64))


@pytest.mark.parametrize("kind, host_loop", [("ode", False), ("ode", True), ("dae", None)])
def test_adaptive_radau_non_finite_model_gets_its_own_message(kind, host_loop):
    """x' = -x + 0 log(x - 0.5) from x0 = 1 is NaN from t = ln 2 on (the other member,
    x0 = 5, stays finite): sample 0 stops there as NON_FINITE with a message about inf/nan in
    the model, not the step-size text of STEP_TOO_SMALL; before the stop x = e^{-t}."""
    x0 = torch.tensor([[1.0], [5.0]], dtype=torch.float64)
    t = torch.linspace(0.0, 2.0, 5, dtype=torch.float64)
    if kind == "ode":
        sol = solve_implicit_ode(
            lambda tt, x: -x + 0 * torch.log(x - 0.5), x0, t, "radau_iia", host_loop=host_loop
        )
    else:
        prob = SemiExplicitDAE(lambda tt, x, z: -z + 0 * torch.log(x - 0.5), lambda tt, x, z: z - x)
        sol = daeint(prob, x0, x0.clone(), t)
    assert sol.status.tolist() == [Status.NON_FINITE, Status.SUCCESS]
    assert len(sol.messages) == 1 and "NON_FINITE" in sol.messages[0], sol.messages
    assert "inf/nan" in sol.messages[0] and "non-smooth" not in sol.messages[0]
    assert _stop_time(sol, 0) == pytest.approx(0.693147, abs=1e-6)
    torch.testing.assert_close(sol.x[0, :2, 0], torch.exp(-t[:2]), rtol=1e-5, atol=0)
    assert bool(torch.isnan(sol.x[0, 2:]).all() and torch.isfinite(sol.x[1]).all())
