"""The method registry (``integrators.methods``): one resolution of every method name, options
refused where they do not apply, and every step-size controller serving every adaptive
method."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.integrate import solve_ivp

from integrators import (
    InputValidationError,
    TableauError,
    daeint,
    odeint,
    radau_iia,
    sensitivities,
    tableau,
)
from integrators.controllers import GustafssonController, IController, PIController
from integrators.implicit import solve_implicit_ode
from integrators.methods import METHOD_NAMES, OPTION_KINDS, resolve_method
from integrators.problems import ImplicitODE

DT = torch.float64
T = torch.linspace(0.0, 1.0, 6, dtype=DT)
X0 = torch.tensor([[1.0, 0.0], [0.5, -0.5]], dtype=DT)


def decay(t, x):
    return -x


def van_der_pol(mu):
    def f(t, x):
        return torch.stack([x[..., 1], mu * (1 - x[..., 0] ** 2) * x[..., 1] - x[..., 0]], -1)

    return f


#: an explicitly given value of every option of odeint that some method refuses
GIVEN = dict(
    substeps=20,
    compile=True,
    checkpoint=True,
    rtol=1e-6,
    atol=1e-9,
    controller=PIController(),
    dt0=0.1,
    max_steps=1000,
)
#: every registry entry and a tableau object of each kind
METHODS = [
    *METHOD_NAMES,
    tableau("rk4"),
    tableau("dopri5"),
    tableau("implicit_euler"),
    radau_iia(3),
]


def _label(method):
    return method if isinstance(method, str) else f"tableau {method.name}"


def _refused():
    """(method, option) for every option that does not apply to the method's default run."""
    cases = []
    for method in METHODS:
        entry = resolve_method(method)
        cases += [(method, opt) for opt in OPTION_KINDS if entry.kind not in OPTION_KINDS[opt]]
        if entry.default_stages is None:
            cases.append((method, "stages"))
    return cases


@pytest.mark.parametrize(
    "method, option", _refused(), ids=[f"{_label(m)}-{o}" for m, o in _refused()]
)
def test_every_option_that_does_not_apply_is_refused_naming_method_and_option(method, option):
    value = 3 if option == "stages" else GIVEN[option]
    name = resolve_method(method).name
    with pytest.raises(InputValidationError) as info:
        odeint(decay, X0, T, method=method, **{option: value})
    message = str(info.value)
    assert f"{option}=" in message and repr(name) in message, message


def test_the_refused_cases_cover_each_kind():
    """Sanity of the generated cases: each kind refuses what it does not use."""
    refused = {(_label(m), o) for m, o in _refused()}
    assert {("rk4", "rtol"), ("rk4", "max_steps"), ("rk4", "controller")} <= refused
    assert {("dopri5", "stages"), ("dopri5", "compile"), ("dopri5", "substeps")} <= refused
    assert {("radau_iia", "compile"), ("gauss_legendre", "max_steps")} <= refused
    assert ("radau_iia", "controller") not in refused and ("radau_iia", "stages") not in refused


def test_dopri5_with_stages_names_the_method_and_the_option():
    with pytest.raises(InputValidationError, match=r"stages=3 .*'dopri5'"):
        odeint(decay, X0, T, method="dopri5", stages=3)


def test_options_of_the_default_run_are_accepted():
    """Every option that applies is accepted (the refusals above are not blanket ones)."""
    for method in METHODS:
        entry = resolve_method(method)
        given = {o: v for o, v in GIVEN.items() if entry.kind in OPTION_KINDS[o]}
        given.pop("checkpoint", None)  # needs autograd to matter; accepted, see test_explicit
        given.pop("compile", None)
        sol = odeint(decay, X0, T, method=method, **given)
        assert sol.success, (_label(method), sol.messages)
        torch.testing.assert_close(sol.x[..., -1, :], X0 * np.exp(-1.0), rtol=1e-2, atol=1e-6)


def test_fixed_step_run_of_an_adaptive_method_refuses_adaptive_options():
    with pytest.raises(InputValidationError, match=r"max_steps=10 .*'dopri5'"):
        odeint(decay, X0, T, method="dopri5", adaptive=False, max_steps=10)
    with pytest.raises(InputValidationError, match=r"controller=.*'radau_iia'"):
        odeint(decay, X0, T, method="radau_iia", adaptive=False, controller=PIController())


def _scipy_vdp(mu, x0, t):
    def f(_, x):
        return [x[1], mu * (1 - x[0] ** 2) * x[1] - x[0]]

    out = solve_ivp(f, (t[0], t[-1]), x0, method="Radau", t_eval=t, rtol=1e-12, atol=1e-12)
    return out.y.T


@pytest.mark.parametrize("controller", [PIController(), IController()])
def test_radau_follows_a_user_controller_to_the_scipy_reference(controller):
    """Van der Pol, mu = 10 (stiff-ish), Radau IIA driven by an I / PI controller: the torch
    driver runs it, the steps differ from Gustafsson's, and the result matches scipy's Radau
    at rtol = 1e-12 within a small multiple of the tolerance 1e-7."""
    mu, t = 10.0, torch.linspace(0.0, 3.0, 7, dtype=DT)
    x0 = torch.tensor([[2.0, 0.0], [1.0, 1.0]], dtype=DT)
    opts = dict(method="radau_iia", rtol=1e-7, atol=1e-9)
    sol = odeint(van_der_pol(mu), x0, t, controller=controller, **opts)
    default = odeint(van_der_pol(mu), x0, t, **opts)
    assert sol.success, sol.messages
    assert sol.stats.extra["driver"] == "torch"
    assert sol.stats.extra["controller"] == repr(controller)
    assert not torch.equal(sol.stats.n_steps, default.stats.n_steps)
    for k in range(x0.shape[0]):
        ref = _scipy_vdp(mu, x0[k].numpy(), t.numpy())
        err = np.abs(sol.x[k].numpy() - ref) / (1e-9 / 1e-7 + np.abs(ref))
        assert err.max() < 50 * 1e-7, err.max()


def test_the_default_radau_controller_is_gustafsson_in_every_driver():
    """An explicit GustafssonController() is the default: the same steps as no controller,
    in the host and the torch drivers."""
    f = van_der_pol(5.0)
    x0 = torch.tensor([[2.0, 0.0]], dtype=DT)
    for host_loop in (True, False):
        opts = dict(method="radau_iia", rtol=1e-6, atol=1e-8, host_loop=host_loop)
        plain = odeint(f, x0, T, **opts)
        given = odeint(f, x0, T, controller=GustafssonController(), **opts)
        assert torch.equal(plain.stats.n_steps, given.stats.n_steps)
        assert torch.equal(plain.x, given.x)


@pytest.mark.parametrize("x0", [[[2.0, 0.0]], [[2.0, 0.0], [1.0, 1.0]]], ids=["one", "batch"])
def test_a_users_gustafsson_controller_drives_every_kernel(x0):
    """GustafssonController(max_factor=1.2): its bound holds on the numpy kernels (one
    trajectory and batched) as on the torch kernel, which take the same steps; different
    steps from the default's."""
    f, x0 = van_der_pol(5.0), torch.tensor(x0, dtype=DT)
    opts = dict(method="radau_iia", rtol=1e-6, atol=1e-8)
    rule = GustafssonController(max_factor=1.2)
    runs = {h: odeint(f, x0, T, controller=rule, host_loop=h, **opts) for h in (True, False)}
    default = odeint(f, x0, T, host_loop=True, **opts)
    assert runs[True].stats.extra["driver"].startswith("host")
    assert torch.equal(runs[True].stats.n_steps, runs[False].stats.n_steps)
    assert runs[True].stats.n_steps.sum() > default.stats.n_steps.sum()
    torch.testing.assert_close(runs[True].x, runs[False].x, rtol=1e-9, atol=1e-12)


def test_a_user_controller_cannot_run_in_the_host_loop():
    with pytest.raises(InputValidationError, match="host_loop=False"):
        odeint(decay, X0, T, method="radau_iia", controller=PIController(), host_loop=True)


def test_daeint_takes_a_controller():
    """x' = -x as an implicit ODE x' + x = 0 with a PI controller: exp(-t) to tolerance."""
    problem = ImplicitODE(lambda t, xdot, x: xdot + x)
    sol = daeint(problem, X0, None, T, controller=PIController(), rtol=1e-8, atol=1e-10)
    assert sol.stats.extra["driver"] == "torch"
    torch.testing.assert_close(sol.x, X0[:, None] * torch.exp(-T)[:, None], rtol=1e-6, atol=0)


def test_unknown_methods_fail_alike_at_every_entry_point():
    """One resolution: the same TableauError from odeint, solve_implicit_ode, daeint and
    sensitivities."""
    problem = ImplicitODE(lambda t, xdot, x: xdot + x)
    calls = [
        lambda: odeint(decay, X0, T, method="rk5"),
        lambda: solve_implicit_ode(decay, X0, T, "rk5"),
        lambda: daeint(problem, X0, None, T, method="rk5"),
        lambda: sensitivities(decay, X0, T, method="rk5"),
    ]
    for call in calls:
        with pytest.raises(TableauError, match="unknown method 'rk5'; use a ButcherTableau"):
            call()


def test_sensitivities_refuse_stages_of_a_fixed_tableau_and_auto():
    with pytest.raises(InputValidationError, match=r"stages=3 .*'rk4'"):
        sensitivities(decay, X0, T, method="rk4", stages=3)
    with pytest.raises(TableauError, match="'auto' has no tableau"):
        sensitivities(decay, X0, T, method="auto")
