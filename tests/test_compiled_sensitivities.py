"""The compiled interval kernel of explicit sensitivities against the eager recursion.

The kernel (``integrators.sensitivities._interval_kernel``) propagates ``[A B]`` in forward
mode (the course notes (Modelling and Simulation), eq. 8.17-8.18) and runs each output interval
as one compiled function; it must give the eager path's states and sensitivities for every
kind of model: a plain function, an ``nn.Module`` whose parameters a grey-box model substitutes,
and a model calling autograd inside ``f`` (which the compiler refuses: it runs eagerly and says
why).
"""

import importlib
import types

import pytest
import torch
from _shared_models import pendulum

from integrators.inputs import CollocationInput
from integrators.sensitivities import sensitivities
from sysid import GreyBoxModel, IOData, Param
from sysid.continuous.fit import _FIT_EVALUATIONS, _check_start, _Problem
from sysid.zoo import SpringMassDamper, VanDerPol

F64 = torch.float64


def _collocation_case():
    g = torch.Generator().manual_seed(3)
    t = torch.linspace(0.0, 2.0, 21, dtype=F64)
    coeff = torch.randn(3, 20, 2, 1, generator=g, dtype=F64)
    u = CollocationInput(coeff, t, nodes=torch.tensor([0.0, 1.0], dtype=F64))
    x0 = torch.tensor([[0.5, 0.0], [1.0, -0.3], [-0.2, 0.4]], dtype=F64)
    p = torch.tensor([[9.81, 0.3], [4.0, 0.1], [1.0, 0.0]], dtype=F64)
    return x0, t, p, u


@pytest.mark.parametrize("derivatives", [True, False])
def test_compiled_kernel_of_a_function_model_equals_the_eager_recursion(derivatives):
    x0, t, p, u = _collocation_case()
    kw = dict(u=u, method="rk4", substeps=2, input_sensitivities=False, derivatives=derivatives)
    eager = sensitivities(pendulum, x0, t, p, compile=False, **kw)
    fast = sensitivities(pendulum, x0, t, p, compile=True, **kw)
    assert fast.stats.extra["compiled"] and fast.stats.extra["compile_fallback"] is None
    assert fast.stats.n_steps == eager.stats.n_steps == 40
    torch.testing.assert_close(fast.x, eager.x, rtol=1e-13, atol=1e-14)
    if derivatives:
        torch.testing.assert_close(fast.A, eager.A, rtol=1e-12, atol=1e-13)
        torch.testing.assert_close(fast.B, eager.B, rtol=1e-12, atol=1e-13)
    else:
        assert fast.A is None and fast.B is None


def _jacobian(model):
    g = torch.Generator().manual_seed(5)
    u = torch.randn(2, 30, 1, generator=g, dtype=F64)
    data = IOData(u, torch.zeros(2, 30, 2, dtype=F64), Ts=0.1, intersample="foh")
    problem = _Problem(model, data, "simulation", "estimate", None, "rk4")
    z = problem.initial_z() + 0.1
    r, J = problem.residuals_and_jacobian(z)
    return r, J.dense(), problem.stats[0].extra


def test_compiled_kernel_of_a_module_with_substituted_parameters_equals_eager():
    """A zoo plant (``nn.Module``) whose parameter the grey-box model substitutes by
    ``functional_call``: residuals and Jacobian of the simulation error."""
    make = lambda c: GreyBoxModel(VanDerPol(), {"mu": Param(0.8)}, compile=c)  # noqa: E731
    r0, J0, info0 = _jacobian(make(False))
    r1, J1, info1 = _jacobian(make(True))
    assert not info0["compiled"] and info1["compiled"]
    torch.testing.assert_close(r1, r0, rtol=1e-12, atol=1e-13)
    torch.testing.assert_close(J1, J0, rtol=1e-12, atol=1e-13)


def test_multiple_shooting_compiles_with_parameters_broadcast_over_segments():
    """Multiple shooting simulates every segment from its own node with the parameters
    broadcast over the segments (a stride-0 view, which forward-mode duals refuse to
    compile): the kernel runs compiled and gives the eager residuals and Jacobian."""

    def damped_pendulum(t, x, u, p):
        acc = -p["a"] * torch.sin(x[..., 0]) - p["b"] * x[..., 1] + u[..., 0]
        return torch.stack([x[..., 1], acc], -1)

    def evaluate(compile):
        model = GreyBoxModel(
            damped_pendulum, {"a": Param(9.0), "b": Param(0.2)}, nx=2, output=[0], compile=compile
        )
        g = torch.Generator().manual_seed(7)
        u = torch.randn(2, 31, 1, generator=g, dtype=F64)
        data = IOData(u, torch.randn(2, 31, 1, generator=g, dtype=F64), Ts=0.1)
        problem = _Problem(model, data, "multiple_shooting", "estimate", 6, "rk4")
        r, J = problem.residuals_and_jacobian(problem.initial_z() + 0.1)
        return r, J.dense(), problem.stats[0].extra

    r0, J0, _ = evaluate(False)
    r1, J1, info = evaluate(True)
    assert info["compiled"] and info["compile_fallback"] is None
    torch.testing.assert_close(r1, r0, rtol=1e-12, atol=1e-13)
    torch.testing.assert_close(J1, J0, rtol=1e-12, atol=1e-13)


def _damped_pendulum(t, x, u, p):
    acc = -p["a"] * torch.sin(x[..., 0]) - p["b"] * x[..., 1] + u[..., 0]
    return torch.stack([x[..., 1], acc], -1)


def test_a_fresh_model_of_the_same_function_runs_the_compiled_kernel_without_compiling():
    """Grey-box models of one function share its compiled kernel (a study builds a model per
    chunk; each once compiled again, seconds per model); a model with its parameters in
    another order still gives the eager numbers."""

    def evaluate(names, compile):
        values = {"a": 9.0, "b": 0.2}
        params = {n: Param(values[n]) for n in names}
        model = GreyBoxModel(_damped_pendulum, params, nx=2, output=[0], compile=compile)
        u = torch.randn(2, 31, 1, generator=torch.Generator().manual_seed(7), dtype=F64)
        data = IOData(u, torch.zeros(2, 31, 1, dtype=F64), Ts=0.1)
        problem = _Problem(model, data, "multiple_shooting", "estimate", 6, "rk4")
        r, J = problem.residuals_and_jacobian(problem.initial_z() + 0.1)
        return r, J.dense(), problem.stats[0].extra

    first = evaluate(("a", "b"), True)
    if not first[2]["compiled"]:
        pytest.skip(f"compilation unavailable: {first[2]['compile_fallback']}")
    again = evaluate(("a", "b"), True)
    assert again[2]["compiled"] and again[2]["compile_s"] == 0.0
    for got, want in zip(again[:2], first[:2], strict=True):
        torch.testing.assert_close(got, want, rtol=0, atol=0)
    swapped, eager = evaluate(("b", "a"), True), evaluate(("b", "a"), False)
    assert swapped[2]["compiled"]
    for got, want in zip(swapped[:2], eager[:2], strict=True):
        torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-13)


def test_a_model_with_autograd_inside_runs_eagerly_and_says_why():
    """A Lagrangian plant forms its equations of motion by autograd: the kernel cannot be
    compiled; the run falls back to the eager recursion with the same numbers."""
    make = lambda c: GreyBoxModel(SpringMassDamper(), {"K": Param(3.0)}, compile=c)  # noqa: E731
    r0, J0, _ = _jacobian(make(False))
    r1, J1, info = _jacobian(make(True))
    assert not info["compiled"] and info["compile_fallback"]
    torch.testing.assert_close(r1, r0, rtol=0, atol=0)
    torch.testing.assert_close(J1, J0, rtol=0, atol=0)


def test_a_compiled_kernel_that_differs_from_the_eager_kernel_is_not_used():
    """The first call of the compiled interval kernel is checked against the same kernel run
    eagerly: a model whose compiled form computes other numbers (a stand-in for a compiler
    fault) runs eagerly, with the eager numbers, and ``compile_fallback`` says why."""
    x0, t, p, u = _collocation_case()

    def miscompiled(t, x, u, p):
        y = pendulum(t, x, u, p)
        return 2 * y if torch.compiler.is_compiling() else y

    kw = dict(u=u, input_sensitivities=False)
    eager = sensitivities(miscompiled, x0, t, p, compile=False, **kw)
    fast = sensitivities(miscompiled, x0, t, p, compile=True, **kw)
    assert not fast.stats.extra["compiled"]
    assert "differs from the eager chunk" in fast.stats.extra["compile_fallback"]
    torch.testing.assert_close(fast.x, eager.x, rtol=0, atol=0)
    torch.testing.assert_close(fast.B, eager.B, rtol=0, atol=0)


def test_auto_compiles_once_the_eager_time_reaches_its_threshold(monkeypatch):
    """Rent-or-buy: ``compile="auto"`` runs a model eagerly, counting the eager time over all
    calls, and compiles it as soon as that time, with the current run's predicted by its
    first intervals, reaches :data:`AUTO_COMPILE_EAGER_SECONDS`, whatever the number of
    steps. A fake clock advances only in eager model calls, so every eager run takes the same
    time W: with the threshold at 3.5 W, three runs are eager, the fourth compiles after its
    first interval (3 W spent + W predicted), the fifth is compiled; same numbers. A run
    without derivatives uses the same compiled kernel (one compile), and a new batch shape,
    which would compile a kernel of its own, starts its own account: eager."""
    module = importlib.import_module("integrators._fast.compiled")
    driver = importlib.import_module("integrators.sensitivities")  # not the function
    clock = [0]
    monkeypatch.setattr(driver, "time", types.SimpleNamespace(perf_counter=lambda: clock[0]))
    x0, t, p, u = _collocation_case()

    def model(t, x, u, p):  # a model object of its own: a fresh count
        if not torch.compiler.is_compiling():
            clock[0] += 1
        return pendulum(t, x, u, p)

    kw = dict(u=u, substeps=2, input_sensitivities=False)  # 40 steps a run
    eager = sensitivities(model, x0, t, p, compile=False, **kw)
    W = clock[0]
    monkeypatch.setattr(module, "AUTO_COMPILE_EAGER_SECONDS", 3.5 * W)
    runs = [sensitivities(model, x0, t, p, compile="auto", **kw) for _ in range(5)]
    assert [r.stats.extra["compiled"] for r in runs] == [False, False, False, True, True]
    assert all(r.stats.extra["compile_fallback"] is None for r in runs)
    for r in runs:
        torch.testing.assert_close(r.x, eager.x, rtol=1e-13, atol=1e-14)
        torch.testing.assert_close(r.B, eager.B, rtol=1e-11, atol=1e-13)
    states_only = sensitivities(model, x0, t, p, compile="auto", derivatives=False, **kw)
    assert states_only.stats.extra["compiled"] and states_only.B is None
    torch.testing.assert_close(states_only.x, eager.x, rtol=1e-13, atol=1e-14)
    ((_, entry),) = module._CACHE[model].items()
    assert len(entry.compiled) == 1
    clock_before = clock[0]
    wider = sensitivities(model, x0.expand(2, *x0.shape), t, p, compile="auto", **kw)
    assert not wider.stats.extra["compiled"] and clock[0] > clock_before
    assert len(entry.compiled) == 1
    torch.testing.assert_close(wider.x, eager.x.expand_as(wider.x), rtol=0, atol=0)


@pytest.mark.parametrize("compile_mode", ["auto", False])
def test_a_fit_compiles_at_once_when_its_first_simulation_is_slow(monkeypatch, compile_mode):
    """A Levenberg-Marquardt run evaluates its residuals many times: when the first (eager)
    simulation times the runs to come times _FIT_EVALUATIONS reaches the eager-time
    threshold, the fit compiles from the start (only for compile="auto"); below it, the
    model's setting stays. The simulation is made to take exactly one second."""
    module = importlib.import_module("integrators._fast.compiled")
    fit_module = importlib.import_module("sysid.continuous.fit")
    clock = iter(range(1000))
    fake_time = types.SimpleNamespace(perf_counter=lambda: float(next(clock)))
    monkeypatch.setattr(fit_module, "time", fake_time)
    model = GreyBoxModel(VanDerPol(), {"mu": Param(0.8)}, compile=compile_mode)
    u = torch.randn(2, 30, 1, generator=torch.Generator().manual_seed(1), dtype=F64)
    data = IOData(u, torch.zeros(2, 30, 2, dtype=F64), Ts=0.1)

    def decided(threshold, runs):
        monkeypatch.setattr(module, "AUTO_COMPILE_EAGER_SECONDS", threshold)
        problem = _Problem(model, data, "simulation", "zero", None, "rk4")
        _check_start(problem, problem.initial_z(), runs)
        return problem.compile

    wanted = True if compile_mode == "auto" else None
    assert decided(_FIT_EVALUATIONS, 1) is wanted
    assert decided(_FIT_EVALUATIONS + 1, 1) is None
    assert decided(3 * _FIT_EVALUATIONS, 3) is wanted  # e.g. the penalty stages
    assert decided(3 * _FIT_EVALUATIONS + 1, 3) is None
