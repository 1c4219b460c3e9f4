"""Fixed-step explicit Runge-Kutta (notes eq. 6.26) checked against closed forms, observed
convergence orders, matrix exponentials, finite differences and per-sample runs."""

import importlib
import math
import re
import types

import numpy as np
import pytest
import scipy.linalg
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from integrators import ButcherTableau, ODELayer, Status, TableauError, odeint, tableau
from integrators.explicit import solve_explicit

EXPLICIT = ["euler", "midpoint", "heun", "ralston", "kutta3", "rk4", "rk38", "dopri5"]


def forced_decay(t, x):
    """x' = -x + sin(3t): time-dependent, so wrong nodes c_i would show up in the order."""
    return -x + torch.sin(3 * t)


def forced_decay_exact(t, x0):
    return (x0 + 0.3) * np.exp(-t) + (np.sin(3 * t) - 3 * np.cos(3 * t)) / 10


@pytest.mark.parametrize("name", EXPLICIT)
def test_observed_order_matches_tableau_order(name):
    tab = tableau(name)
    base = {1: 40, 2: 20, 3: 20, 4: 20, 5: 10}[tab.order]
    ns = [base, 2 * base, 4 * base, 8 * base]
    x0 = torch.tensor([[1.0], [-0.5]], dtype=torch.float64)
    errors = []
    for n in ns:
        t = torch.linspace(0.0, 3.0, n + 1, dtype=torch.float64)
        sol = odeint(forced_decay, x0, t, method=name, adaptive=False)
        exact = forced_decay_exact(t.numpy()[None, :, None], x0.numpy()[:, None, :])
        errors.append(np.abs(sol.x.numpy() - exact).max())
    slope = -np.polyfit(np.log(ns), np.log(errors), 1)[0]
    assert abs(slope - tab.order) <= 0.15, (name, slope, errors)
    assert sol.success


def _linear_rhs(A):
    def f(t, x):
        return x @ A.T

    return f


@settings(max_examples=12, deadline=None)
@given(
    n=st.integers(1, 4),
    batch=st.integers(1, 3),
    seed=st.integers(0, 2**31 - 1),
    name=st.sampled_from(["rk4", "rk38", "dopri5", "kutta3"]),
)
def test_random_stable_linear_systems_match_matrix_exponential(n, batch, seed, name):
    rng = np.random.default_rng(seed)
    M = rng.standard_normal((n, n))
    S = rng.standard_normal((n, n))
    A = -(M @ M.T) / n - 0.2 * np.eye(n) + (S - S.T)  # stable: symmetric part negative
    x0 = rng.standard_normal((batch, n))
    t = np.sort(rng.uniform(0.0, 2.0, 6))
    t = np.concatenate([[0.0], t + np.arange(1, 7) * 1e-3])  # strictly increasing, non-uniform
    sol = odeint(
        _linear_rhs(torch.tensor(A)),
        torch.tensor(x0),
        torch.tensor(t),
        method=name,
        adaptive=False,
        substeps=200,
    )
    exact = np.stack([x0 @ scipy.linalg.expm(A * tk).T for tk in t], axis=1)
    # Rigorous bound: e^{At} is a contraction (symmetric part of A negative), so the global
    # error is at most the sum of the local errors |e^z - R(z)| <= |z|^(p+1)/(p+1)! e^|z|,
    # z = h ||A||_2 (R is the degree-p Taylor polynomial, plus z^6/600 for dopri5, notes
    # eq. 6.41), times ||x0||; a factor 2 for safety.
    p = tableau(name).order
    z = np.diff(t) / 200 * np.linalg.norm(A, 2)
    local = z ** (p + 1) / math.factorial(p + 1) * np.exp(z)
    bound = 2 * 200 * local.sum() * np.linalg.norm(x0, axis=-1).max() + 1e-13
    assert np.abs(sol.x.numpy() - exact).max() <= bound


def test_substeps_equal_a_finer_grid():
    t = torch.tensor([0.0, 0.3, 0.35, 1.0, 1.7], dtype=torch.float64)  # non-uniform
    m = 4
    pieces = [t[k] + (t[k + 1] - t[k]) * torch.arange(m, dtype=t.dtype) / m for k in range(4)]
    fine = torch.cat(pieces + [t[-1:]])
    x0 = torch.tensor([[1.0, 0.0], [0.5, -1.0]], dtype=torch.float64)

    def f(t, x):
        return torch.stack([x[..., 1], -torch.sin(x[..., 0]) + 0.1 * t], dim=-1)

    coarse = odeint(f, x0, t, method="rk4", substeps=m)
    ref = odeint(f, x0, fine, method="rk4")
    torch.testing.assert_close(coarse.x, ref.x[:, ::m], rtol=0, atol=1e-14)
    assert coarse.stats.n_steps == 4 * m and coarse.stats.n_f_evals == 16 * m


def test_batched_equals_per_sample_and_broadcast_parameters():
    mu = torch.tensor([[0.5], [1.0], [3.0]], dtype=torch.float64)

    def vdp(t, x, mu=mu):
        first = mu[..., 0] * (1 - x[..., 1] ** 2) * x[..., 0] - x[..., 1]
        return torch.stack([first, x[..., 0].expand_as(first)], dim=-1)

    x0 = torch.tensor([[0.1, 1.0], [2.0, 0.0], [-1.0, 0.5]], dtype=torch.float64)
    t = torch.linspace(0, 5, 51, dtype=torch.float64)
    batched = odeint(vdp, x0, t, method="rk4", substeps=3)
    for i in range(3):
        single = odeint(lambda t, x, i=i: vdp(t, x, mu[i]), x0[i], t, method="rk4", substeps=3)
        torch.testing.assert_close(batched.x[i], single.x, rtol=0, atol=1e-13)
    # a (3, 1) parameter broadcasts an unbatched x0 to a batch of three
    broadcast = odeint(vdp, x0[0], t, method="rk4", substeps=3)
    assert broadcast.x.shape == (3, 51, 2)
    for i in range(3):
        single = odeint(lambda t, x, i=i: vdp(t, x, mu[i]), x0[0], t, method="rk4", substeps=3)
        torch.testing.assert_close(broadcast.x[i], single.x, rtol=0, atol=1e-13)


def test_finite_escape_time_is_reported_and_other_samples_continue():
    """x' = x^2 escapes at t = 1/x0 (notes eq. 1.44-1.45: x(t) = 1/(1 - t) for x0 = 1)."""
    x0 = torch.tensor([[1.0], [-1.0], [0.25]], dtype=torch.float64)
    t = torch.linspace(0.0, 2.0, 41, dtype=torch.float64)
    sol = odeint(lambda t, x: x**2, x0, t, method="rk4", substeps=4)
    assert sol.status.tolist() == [Status.NON_FINITE, Status.SUCCESS, Status.SUCCESS]
    assert not sol.success
    assert len(sol.messages) == 1 and "sample 0" in sol.messages[0]
    # the message names the interval where the state became non-finite, after t = 1
    times = [float(v.rstrip(";.,")) for v in re.findall(r"t = ([0-9.e+-]+)", sol.messages[0])]
    assert 1.0 <= times[0] < times[1] <= 2.0
    k = int(torch.nonzero(torch.isnan(sol.x[0, :, 0]))[0])
    assert torch.isnan(sol.x[0, k:]).all() and torch.isfinite(sol.x[0, :k]).all()
    assert abs(float(t[k]) - times[2]) < 1e-12
    # benign samples follow the closed form x0 / (1 - x0 t)
    exact = x0[1:] / (1 - x0[1:] * t)
    torch.testing.assert_close(sol.x[1:, :, 0], exact, rtol=1e-6, atol=0)
    # before the escape, sample 0 follows 1 / (1 - t)
    early = t < 0.8
    torch.testing.assert_close(sol.x[0, early, 0], 1 / (1 - t[early]), rtol=1e-4, atol=0)


def test_gradients_match_central_finite_differences(central_difference):
    """d(loss)/d(x0) and d(loss)/d(theta) of the discrete simulation, float64, rel. 1e-6."""
    theta = torch.tensor([0.7, 1.3], dtype=torch.float64, requires_grad=True)

    def f(t, x):
        return torch.stack(
            [x[..., 1], -theta[0] * torch.sin(x[..., 0]) - theta[1] * 0.1 * x[..., 1] + 0.2 * t],
            dim=-1,
        )

    t = torch.linspace(0, 3, 31, dtype=torch.float64)
    x0 = torch.tensor([[0.5, 0.0], [1.0, -0.3]], dtype=torch.float64, requires_grad=True)
    w = torch.linspace(-1, 1, 2 * 31 * 2, dtype=torch.float64).reshape(2, 31, 2)

    def loss():
        return (odeint(f, x0, t, method="rk4", substeps=2).x * w).sum()

    value = loss()
    g_x0, g_theta = torch.autograd.grad(value, (x0, theta))
    for param, grad in ((x0, g_x0), (theta, g_theta)):
        fd = central_difference(loss, param, 1e-6)
        torch.testing.assert_close(grad, fd, rtol=1e-6, atol=1e-9)


def test_gradient_with_respect_to_sampled_input():
    """x' = -x + u (ZOH): x_T = sum_k e^{-(T - t_{k+1})} (1 - e^{-h}) u_k, so dx_T/du_k is known."""
    t = torch.linspace(0, 1, 11, dtype=torch.float64)
    u = torch.randn(11, 1, dtype=torch.float64, generator=torch.Generator().manual_seed(3))
    u.requires_grad_(True)
    sol = odeint(lambda t, x, u: -x + u, torch.zeros(1, dtype=torch.float64), t, u=u, substeps=8)
    (grad,) = torch.autograd.grad(sol.x[-1, 0], u)
    h = 0.1
    expected = torch.exp(-(1.0 - t[1:])) * (1 - np.exp(-h))
    torch.testing.assert_close(grad[:-1, 0], expected, rtol=1e-6, atol=0)
    assert grad[-1, 0] == 0.0


def test_float32_works_and_is_accurate_to_single_precision():
    x0 = torch.tensor([[1.0], [-0.5]], dtype=torch.float32)
    t = torch.linspace(0, 3, 61, dtype=torch.float32)
    sol = odeint(forced_decay, x0, t, method="rk4")
    assert sol.x.dtype == torch.float32
    exact = forced_decay_exact(t.double().numpy()[None, :, None], x0.double().numpy()[:, None])
    assert np.abs(sol.x.double().numpy() - exact).max() < 1e-5


def test_f_evaluation_count_skips_unused_stages():
    """dopri5 at fixed step needs 6 of its 7 stages (b_7 = 0, the FSAL stage)."""
    calls = []

    def f(t, x):
        calls.append(1)
        return -x

    t = torch.linspace(0, 1, 6, dtype=torch.float64)
    x0 = torch.ones(1, dtype=torch.float64)
    sol = solve_explicit(f, x0, t, tableau("dopri5"), substeps=2)
    assert len(calls) == sol.stats.n_f_evals == 10 * 6
    # on x' = -x one step multiplies by the stability function R(-h) (here h = 0.1)
    growth = tableau("dopri5").stability_function(-0.1).real
    assert abs(float(sol.x[-1, 0]) - growth**10) <= 1e-14


def test_custom_tableau_with_zero_coefficients():
    """Any explicit tableau works: Ralston's third-order method (c = 0, 1/2, 3/4)."""
    tab = ButcherTableau(
        A=[[0, 0, 0], [0.5, 0, 0], [0, 0.75, 0]], b=[2 / 9, 1 / 3, 4 / 9], name="ralston3"
    )
    assert tab.order == 3
    x0 = torch.tensor([[1.0]], dtype=torch.float64)
    errors = []
    for n in (20, 40, 80):
        t = torch.linspace(0.0, 3.0, n + 1, dtype=torch.float64)
        sol = odeint(forced_decay, x0, t, method=tab)
        exact = forced_decay_exact(t.numpy(), 1.0)
        errors.append(np.abs(sol.x[0, :, 0].numpy() - exact).max())
    slope = -np.polyfit(np.log([20, 40, 80]), np.log(errors), 1)[0]
    assert abs(slope - 3) <= 0.15


def test_implicit_tableau_rejected_by_explicit_solver():
    with pytest.raises(TableauError, match="implicit"):
        solve_explicit(
            lambda t, x: -x,
            torch.ones(1, dtype=torch.float64),
            torch.linspace(0, 1, 3, dtype=torch.float64),
            tableau("implicit_euler"),
        )


def test_compiled_chunks_match_eager():
    """torch.compile of the chunked step gives the eager result (or falls back to eager)."""

    def f(t, x):
        return torch.stack([x[..., 1], -x[..., 0] + torch.cos(t)], dim=-1)

    x0 = torch.tensor([[1.0, 0.0], [0.0, 2.0]], dtype=torch.float64)
    t = torch.linspace(0, 2, 20, dtype=torch.float64)  # 19 intervals: 2 chunks of 8 + 3 eager
    with torch.no_grad():
        eager = odeint(f, x0, t, method="euler", compile=False)
        compiled = odeint(f, x0, t, method="euler", compile=True)
    assert eager.stats.extra["compiled"] is False
    torch.testing.assert_close(compiled.x, eager.x, rtol=1e-13, atol=1e-13)
    assert compiled.stats.extra["compile_s"] >= 0.0


def _counting(clock):
    """Van der Pol (component-wise) whose eager calls advance ``clock`` by one."""

    def f(t, x):
        if not torch.compiler.is_compiling():
            clock[0] += 1
        return torch.stack([x[..., 1], (1 - x[..., 0] ** 2) * x[..., 1] - x[..., 0]], dim=-1)

    return f


def test_auto_compiles_once_the_eager_time_reaches_its_threshold(monkeypatch):
    """Rent-or-buy, the rule of the sensitivities too: ``compile="auto"`` runs a model eagerly,
    counting its eager time over all calls, and compiles once that time, with the current
    run's predicted (from the eager time per step counted before, or from the run's first
    steps), reaches ``AUTO_COMPILE_EAGER_SECONDS``. A fake clock advances only in eager model
    calls, so every eager run of 10 intervals takes the same time W.

    Threshold 0.5 W: a first run compiles after its first interval (W predicted), and its
    outputs move to the component-major layout; with autograd it switches to interleaved
    compiled chunks, same gradients. Threshold 2.5 W: two runs are eager (W + W predicted at
    the second), the third compiles from its first step (2 W counted + W predicted)."""
    from integrators import explicit

    compiled = importlib.import_module("integrators._fast.compiled")
    monkeypatch.setattr(explicit, "CHUNK_STEPS", 2)  # small graphs: quick compiles
    clock = [0]
    monkeypatch.setattr(explicit, "time", types.SimpleNamespace(perf_counter=lambda: clock[0]))
    x0 = torch.tensor([[2.0, 0.0], [1.0, 1.0]], dtype=torch.float64)
    t = torch.linspace(0, 1, 11, dtype=torch.float64)
    reference = _counting(clock)
    with torch.no_grad():
        eager = odeint(reference, x0, t, method="midpoint", compile=False)
    W = clock[0]

    monkeypatch.setattr(compiled, "AUTO_COMPILE_EAGER_SECONDS", 0.5 * W)
    with torch.no_grad():
        switched = odeint(_counting(clock), x0, t, method="midpoint", compile="auto")
    if not switched.stats.extra["compiled"]:
        pytest.skip("torch.compile is unavailable here")
    assert switched.stats.extra["compiled_from_step"] == 1
    assert switched.stats.extra["layout"] == "component-major"
    torch.testing.assert_close(switched.x, eager.x, rtol=1e-13, atol=1e-13)

    p = torch.tensor(1.5, dtype=torch.float64, requires_grad=True)
    grad_eager = torch.autograd.grad(
        odeint(reference, x0 * p, t, method="midpoint", compile=False).x.square().sum(), p
    )
    sol = odeint(_counting(clock), x0 * p, t, method="midpoint", compile="auto")
    assert sol.stats.extra["compiled"] and sol.stats.extra["compiled_from_step"] == 1
    assert sol.stats.extra["layout"] == "interleaved"
    torch.testing.assert_close(torch.autograd.grad(sol.x.square().sum(), p), grad_eager)

    monkeypatch.setattr(compiled, "AUTO_COMPILE_EAGER_SECONDS", 2.5 * W)
    model = _counting(clock)
    with torch.no_grad():
        runs = [odeint(model, x0, t, method="midpoint", compile="auto") for _ in range(3)]
    assert [r.stats.extra["compiled_from_step"] for r in runs] == [None, None, 0]
    for r in runs:
        torch.testing.assert_close(r.x, eager.x, rtol=1e-13, atol=1e-13)


def test_big_states_take_fewer_steps_per_compiled_chunk(monkeypatch):
    """Chunk length follows the state size (cache budget ``CHUNK_STATE_BYTES``), at least one
    output interval; a model compiled at two chunk lengths keeps both and matches eager."""
    from integrators import explicit
    from integrators._fast import compiled as compiled_cache

    def chunk_len(batch, substeps=1, dtype=torch.float64):
        return explicit._outputs_per_chunk(torch.zeros(batch, 2, dtype=dtype), substeps)

    assert chunk_len(1) == chunk_len(1024) == explicit.CHUNK_STEPS == 8
    assert (chunk_len(16384), chunk_len(32768), chunk_len(65536)) == (4, 2, 1)
    assert chunk_len(65536, dtype=torch.float32) == 2
    assert chunk_len(1024, substeps=4) == 2 and chunk_len(65536, substeps=4) == 1

    def f(t, x):
        return torch.stack([x[..., 1], -torch.sin(x[..., 0])], dim=-1)

    x0 = torch.tensor([[1.0, 0.0], [0.5, 2.0], [-1.0, 0.3]], dtype=torch.float64)
    t = torch.linspace(0, 2, 12, dtype=torch.float64)
    with torch.no_grad():
        eager = odeint(f, x0, t, method="rk4", compile=False)
        long_chunks = odeint(f, x0[:2], t, method="rk4", compile=True)
        monkeypatch.setattr(explicit, "CHUNK_STATE_BYTES", 48)  # 3 x 2 float64: one step
        short_chunks = odeint(f, x0, t, method="rk4", compile=True)
    if short_chunks.stats.extra["compiled"]:  # (compilation may be unavailable)
        (entry,) = compiled_cache._CACHE[f].values()
        # keys: (outputs per chunk, component-major layout, state shape, ...); this model is
        # component-wise
        assert sorted(key[:3] for key in entry.compiled) == [(1, True, (3, 2)), (8, True, (2, 2))]
    torch.testing.assert_close(long_chunks.x, eager.x[:2], rtol=1e-13, atol=1e-13)
    torch.testing.assert_close(short_chunks.x, eager.x, rtol=1e-13, atol=1e-13)


def test_huge_page_output_buffer_gives_the_same_solution(monkeypatch):
    """With the huge-page threshold lowered, the no-grad output buffer comes from an anonymous
    mapping (``torch.frombuffer``): the solution equals the ordinary buffer's exactly, the
    failure search still works on it, and the tensor outlives every other reference."""
    import gc

    from integrators._fast import buffers as _buffers

    def f(t, x):
        return x**2

    x0 = torch.tensor([[1.0], [-1.0], [0.25]], dtype=torch.float64)
    t = torch.linspace(0.0, 2.0, 41, dtype=torch.float64)
    with torch.no_grad():
        plain = odeint(f, x0, t, method="rk4", substeps=4)
        monkeypatch.setattr(_buffers, "HUGE_PAGE_MIN_BYTES", 0)
        mapped = odeint(f, x0, t, method="rk4", substeps=4)
        benign = odeint(f, x0[1:], t, method="rk4", substeps=4)
    if hasattr(__import__("mmap"), "MADV_HUGEPAGE"):  # Linux: the mapped path really ran
        assert benign.x.untyped_storage().data_ptr() % 4096 == 0  # a fresh page mapping
    torch.testing.assert_close(mapped.x, plain.x, rtol=0, atol=0, equal_nan=True)
    torch.testing.assert_close(benign.x, plain.x[1:], rtol=0, atol=0)
    assert mapped.status.tolist() == plain.status.tolist() and mapped.messages == plain.messages
    view = benign.x[:, 5:, 0]
    expected = view.clone()
    del benign
    gc.collect()
    view.add_(1.0)  # the mapping is still alive and writable
    torch.testing.assert_close(view, expected + 1.0)


class Pendulum(torch.nn.Module):
    def __init__(self):
        super().__init__()
        self.g = torch.nn.Parameter(torch.tensor(9.0, dtype=torch.float64))

    def forward(self, t, x):
        return torch.stack([x[..., 1], -self.g * torch.sin(x[..., 0])], dim=-1)


def test_ode_layer_trains_module_parameters():
    """Fit the gravity constant of a pendulum from a trajectory simulated with g = 9.81."""
    t = torch.linspace(0, 2, 21, dtype=torch.float64)
    x0 = torch.tensor([[0.5, 0.0], [1.0, 0.0]], dtype=torch.float64)
    truth = Pendulum()
    with torch.no_grad():
        truth.g.fill_(9.81)
        target = odeint(truth, x0, t, substeps=4).x
    layer = ODELayer(Pendulum(), t=t, method="rk4", return_solution=False, substeps=4)
    assert [name for name, _ in layer.named_parameters()] == ["f.g"]
    opt = torch.optim.LBFGS(
        layer.parameters(),
        max_iter=50,
        tolerance_grad=1e-15,
        tolerance_change=1e-20,
        line_search_fn="strong_wolfe",
    )

    def closure():
        opt.zero_grad()
        loss = ((layer(x0) - target) ** 2).mean()
        loss.backward()
        return loss

    opt.step(closure)
    assert abs(layer.f.g.item() - 9.81) < 1e-8
    sol = ODELayer(truth, method="rk4", substeps=4)(x0, t=t)
    torch.testing.assert_close(sol.x, target)


def test_compile_failure_falls_back_to_eager(monkeypatch):
    """If torch.compile cannot build the chunk, the run continues eagerly with the same result."""
    from integrators import explicit

    def broken_compile(fn, **options):
        def call(*args):
            raise RuntimeError("no C++ compiler")

        return call

    monkeypatch.setattr(explicit.torch, "compile", broken_compile)

    def f(t, x):  # a fresh model, so no cached compiled chunk exists
        return -2.0 * x + t

    x0 = torch.tensor([[1.0], [0.0]], dtype=torch.float64)
    t = torch.linspace(0, 1, 21, dtype=torch.float64)
    sol = odeint(f, x0, t, method="rk4", substeps=2, compile=True)
    assert sol.stats.extra["compiled"] is False
    exact = (x0 + 0.25) * torch.exp(-2 * t) + 0.5 * t - 0.25  # x' = -2x + t
    torch.testing.assert_close(sol.x[..., 0], exact, rtol=0, atol=1e-7)


def _miscompiled(t, x):
    """A harmonic oscillator whose compiled form is wrong (twice the derivative): a stand-in
    for a compiler fault that changes the numbers without raising."""
    y = torch.stack([x[..., 1], -x[..., 0]], -1)
    return 2 * y if torch.compiler.is_compiling() else y


@pytest.mark.parametrize("grad", [False, True])
def test_a_compiled_chunk_that_differs_from_the_eager_chunk_is_not_used(grad):
    """The first call of every compiled chunk is checked against the eager chunk: a compiled
    model that computes other numbers is given up, the run continues eagerly with the eager
    numbers, and ``compile_fallback`` says why."""
    x0 = torch.tensor([[1.0, 0.0], [0.5, 0.5]], dtype=torch.float64, requires_grad=grad)
    t = torch.linspace(0, 1, 11, dtype=torch.float64)
    eager = odeint(_miscompiled, x0, t, method="rk4", compile=False)
    fast = odeint(_miscompiled, x0, t, method="rk4", compile=True)
    assert not fast.stats.extra["compiled"]
    assert "differs from the eager chunk" in fast.stats.extra["compile_fallback"]
    torch.testing.assert_close(fast.x, eager.x, rtol=0, atol=0)


def test_zoo_crane_with_second_derivatives_inside_f_runs_eagerly_when_compiled():
    """The Cartesian crane forms its constraint curvature by a second reverse pass inside
    ``f`` (eq. 2.165b), which the compiled graph loses (it would return zeros): the compiled
    run is refused by the check against the eager chunk, and equals the eager run."""
    from sysid.zoo import RigidCraneCartesian

    plant = RigidCraneCartesian(baumgarte=5.0).to(torch.float64)
    q, qdot = plant.project_consistent(
        torch.tensor([0.0, 0.5, 0.8], dtype=torch.float64), torch.full((3,), 0.3).double()
    )
    x0 = torch.cat([q, qdot]).detach().expand(3, 6)
    t = torch.linspace(0, 0.5, 11, dtype=torch.float64)
    with torch.no_grad():
        eager = odeint(plant, x0, t, method="rk4", substeps=5, compile=False)
        fast = odeint(plant, x0, t, method="rk4", substeps=5, compile=True)
    assert not fast.stats.extra["compiled"] and fast.stats.extra["compile_fallback"]
    torch.testing.assert_close(fast.x, eager.x, rtol=1e-12, atol=1e-12)


def _oscillator_with_input(t, x, u):
    """x1' = x2, x2' = -x1 - 0.2 x2 + u (component-wise: unbind ... stack)."""
    x1, x2 = x.unbind(-1)
    return torch.stack([x2, -x1 - 0.2 * x2 + u[..., 0]], dim=-1)


def _van_der_pol_sliced(t, x):
    x1, x2 = x[..., 0:1], x[..., 1:]
    return torch.cat([(1 - x2**2) * x1 - x2, x1], dim=-1)


def _lorenz(t, x):  # notes eq. 6.9 with beta = 3
    a, b, c = x.unbind(-1)
    return torch.stack([10 * (b - a), a * (28 - c) - b, a * b - 3 * c], dim=-1)


_U_SAMPLES = torch.sin(torch.linspace(0, 3, 11, dtype=torch.float64))[:, None]


@pytest.mark.parametrize(
    "case",
    ["sliced, batch (2, 3)", "lorenz, batch ()", "zoh input", "linear input", "callable input"],
)
def test_component_major_compiled_runs_match_eager(case):
    """Compiled runs without autograd of component-wise models keep the state component-major
    (stats.extra["layout"]) and give the eager, interleaved result: batch shapes (2, 3) and
    (), models built with slices and cat, and every kind of input."""
    gen = torch.Generator().manual_seed(7)
    t = torch.linspace(0, 1, 11, dtype=torch.float64)  # 10 intervals: one chunk of 8 + 2 eager
    kwargs = {}
    if case == "sliced, batch (2, 3)":
        f, x0 = _van_der_pol_sliced, torch.randn(2, 3, 2, dtype=torch.float64, generator=gen)
    elif case == "lorenz, batch ()":
        f, x0 = _lorenz, torch.tensor([1.0, 1.0, 20.0], dtype=torch.float64)
    else:
        f, x0 = _oscillator_with_input, torch.randn(4, 2, dtype=torch.float64, generator=gen)
        if case == "callable input":
            kwargs = {"u": lambda s: torch.cos(3 * s).reshape(1, 1).expand(4, 1)}
        else:
            kwargs = {"u": _U_SAMPLES, "interpolation": case.split()[0]}
    with torch.no_grad():
        eager = odeint(f, x0, t, method="midpoint", compile=False, **kwargs)
        compiled = odeint(f, x0, t, method="midpoint", compile=True, **kwargs)
        again = odeint(f, x0, t, method="midpoint", compile=True, **kwargs)
    assert eager.stats.extra["layout"] == "interleaved"
    if compiled.stats.extra["compiled"]:  # (compilation may be unavailable)
        assert compiled.stats.extra["layout"] == "component-major"
        assert compiled.stats.extra["compile_s"] > 0.0 and again.stats.extra["compile_s"] == 0.0
        torch.testing.assert_close(again.x, compiled.x, rtol=0, atol=0)
    assert compiled.x.shape == eager.x.shape == (*x0.shape[:-1], 11, x0.shape[-1])
    torch.testing.assert_close(compiled.x, eager.x, rtol=1e-13, atol=1e-12)


def test_component_major_blow_up_and_compile_failure(monkeypatch):
    """A component-major run reports a finite escape like the eager run (same status, same
    NaN outputs, same message), also when torch.compile fails and the run continues eagerly
    on the component-major buffer."""
    from integrators import explicit

    monkeypatch.setattr(explicit, "CHUNK_STEPS", 2)  # small graphs: quick compiles

    def escape(t, x):  # x1' = x1^2 escapes at t = 1/x1(0); x2' = -x2
        x1, x2 = x.unbind(-1)
        return torch.stack([x1 * x1, -x2], dim=-1)

    x0 = torch.tensor([[1.0, 1.0], [0.25, 2.0]], dtype=torch.float64)
    t = torch.linspace(0.0, 2.0, 21, dtype=torch.float64)
    with torch.no_grad():
        eager = odeint(escape, x0, t, method="heun", substeps=2, compile=False)
        compiled = odeint(escape, x0, t, method="heun", substeps=2, compile=True)
        monkeypatch.setattr(explicit.torch, "compile", lambda fn, **kw: _raise_on_call)
        explicit.clear_compile_cache()
        fallback = odeint(escape, x0, t, method="heun", substeps=2, compile=True)
    assert eager.status.tolist() == [Status.NON_FINITE, Status.SUCCESS]
    assert fallback.stats.extra == {**fallback.stats.extra, "compiled": False}
    assert fallback.stats.extra["layout"] == "component-major"
    for sol in (compiled, fallback):
        assert sol.status.tolist() == eager.status.tolist()
        assert sol.messages == eager.messages
        # (rounding differences grow like the solution near the escape: 1e88 at t = 1.2)
        torch.testing.assert_close(sol.x, eager.x, rtol=1e-10, atol=1e-13, equal_nan=True)


def _raise_on_call(*args):
    raise RuntimeError("no C++ compiler")


class _Damped(torch.nn.Module):
    """x' = -k x, k a parameter; ``rhs`` the same as a bound method of the module."""

    def __init__(self, k):
        super().__init__()
        self.k = torch.nn.Parameter(torch.tensor(k, dtype=torch.float64))

    def forward(self, t, x):
        return -self.k * x

    def rhs(self, t, x, u):
        return -self.k * x + u


@pytest.mark.parametrize("call", ["module", "bound method with a callable input", "sensitivities"])
def test_compiled_models_are_reused_while_alive_and_freed_after(call, monkeypatch):
    """A compiled model runs again without compiling (same numbers), and once the caller drops
    it the model and its cache entry are freed: the cache holds no reference to the model it is
    keyed by (it once kept every compiled model, its parameters and kernels, for the life of
    the process). x' = -k x (+ u) against its closed form."""
    import gc
    import weakref

    from integrators import explicit
    from integrators._fast import compiled as compiled_module
    from integrators.sensitivities import sensitivities

    monkeypatch.setattr(explicit, "CHUNK_STEPS", 2)  # small graphs: quick compiles
    t = torch.linspace(0.0, 1.0, 11, dtype=torch.float64)
    x0 = torch.tensor([[1.0], [2.0]], dtype=torch.float64)
    model = _Damped(0.7)
    u = 0.25  # constant input: x = u / k + (x0 - u / k) exp(-k t)
    if call == "module":
        f, kwargs, exact = model, {}, x0[:, None] * torch.exp(-0.7 * t)[:, None]
    else:
        f = model.rhs if call.startswith("bound") else model.forward
        kwargs = {"u": lambda s: torch.full((2, 1), u, dtype=torch.float64)}
        exact = u / 0.7 + (x0[:, None] - u / 0.7) * torch.exp(-0.7 * t)[:, None]

    def run(f, kwargs):
        if call == "sensitivities":
            sol = sensitivities(f, x0, t, method="rk4", substeps=4, compile=True)
            return sol.x, sol.stats.extra
        with torch.no_grad():
            sol = odeint(f, x0, t, method="rk4", substeps=4, compile=True, **kwargs)
        return sol.x, sol.stats.extra

    first, stats = run(f, kwargs)
    if not stats["compiled"]:
        pytest.skip(f"compilation unavailable: {stats['compile_fallback']}")
    again, again_stats = run(f, kwargs)
    assert again_stats["compiled"] and again_stats["compile_s"] == 0.0
    torch.testing.assert_close(again, first, rtol=0, atol=0)
    if call != "sensitivities":
        torch.testing.assert_close(first, exact, rtol=1e-7, atol=0)
    alive, entries = weakref.ref(model), len(compiled_module._CACHE)
    del model, f, kwargs, first, again
    gc.collect()
    assert alive() is None
    assert len(compiled_module._CACHE) == entries - 1


@pytest.mark.parametrize("grad", [False, True])
def test_compiled_linear_model_matches_matrix_exponential(grad, monkeypatch):
    """x' = A x through a matrix product, compiled: the interleaved layout (the model mixes
    components) and the eager result, against expm. Regression: inductor drops the
    coefficient of add(a, mm, alpha=c), which once made every compiled step of such a model
    wrong by O(1)."""
    from integrators import explicit

    monkeypatch.setattr(explicit, "CHUNK_STEPS", 1)  # small graphs: quick compiles
    A = torch.tensor([[-1.0, 2.0, 0.0], [-2.0, -1.0, 0.5], [0.0, -0.5, -0.3]], dtype=torch.float64)
    x0 = torch.randn(5, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(2))
    x0.requires_grad_(grad)
    t = torch.linspace(0, 2, 21, dtype=torch.float64)

    def linear(t, x):
        return x @ A.T

    with torch.set_grad_enabled(grad):
        sol = odeint(linear, x0, t, method="rk4", substeps=2, compile=True)
        eager = odeint(linear, x0, t, method="rk4", substeps=2, compile=False)
        sol_x, eager_x = sol.x.detach(), eager.x.detach()
    assert sol.stats.extra["layout"] == "interleaved"
    exact = torch.einsum("tij,bj->bti", torch.linalg.matrix_exp(A * t[:, None, None]), x0.detach())
    torch.testing.assert_close(sol_x, eager_x, rtol=1e-13, atol=1e-13)
    assert float((sol_x - exact).abs().max()) < 4e-6  # RK4 at h = 0.05: 2.2e-6


class _HalfCoupled(torch.nn.Module):
    """x' = -x + 0.5 W x written with ``add(..., alpha=0.5)`` on a matrix product: the form
    inductor compiles without its coefficient unless the chunk's graph pass rewrites it."""

    def __init__(self):
        super().__init__()
        self.W = torch.nn.Parameter(torch.zeros(2, 2, dtype=torch.float64))

    def forward(self, t, x):
        return torch.add(-x, x @ self.W.T, alpha=0.5)


def test_a_model_with_alpha_on_a_matrix_product_compiles_right_after_a_zero_first_call(
    monkeypatch,
):
    """A zero-initialised layer passed the first call's eager check (its product is zero), then
    trained weights ran through a graph without the alpha: x(1) = [0.0955, -0.4001] for
    expm(-I + W/2) x0 = [0.3535, -0.2102]. Every compiled chunk rewrites alpha into a product."""
    from integrators import explicit

    monkeypatch.setattr(explicit, "CHUNK_STEPS", 1)  # small graphs: quick compiles
    model = _HalfCoupled()
    x0 = torch.tensor([[1.0, 0.5]], dtype=torch.float64)
    t = torch.linspace(0, 1, 11, dtype=torch.float64)
    with torch.no_grad():
        odeint(model, x0, t, method="rk4", compile=True)  # compiled and checked with W = 0
        model.W.copy_(torch.tensor([[0.0, 2.0], [-2.0, 0.0]]))
        sol = odeint(model, x0, t, method="rk4", compile=True)
        eager = odeint(model, x0, t, method="rk4", compile=False)
    assert sol.stats.extra["compiled"]
    torch.testing.assert_close(sol.x, eager.x, rtol=1e-13, atol=1e-13)
    exact = torch.linalg.matrix_exp(-torch.eye(2, dtype=torch.float64) + 0.5 * model.W.detach())
    assert float((sol.x[0, -1] - exact @ x0[0]).abs().max()) < 1e-5  # RK4 at h = 0.1: 2e-6


def test_every_model_gets_its_own_compiled_chunk(monkeypatch):
    """Dynamo stops compiling a code object after ``recompile_limit`` graphs (8 by default,
    2 here) and then runs it eagerly without an error; each model's (and state shape's) chunk
    has its own code, so models and batch sizes past the limit are still compiled."""
    from torch._dynamo.utils import counters

    from integrators import explicit

    monkeypatch.setattr(explicit, "CHUNK_STEPS", 1)  # small graphs: quick compiles
    monkeypatch.setattr(torch._dynamo.config, "recompile_limit", 2)
    t = torch.linspace(0, 1, 3, dtype=torch.float64)
    x0 = torch.ones(2, 2, dtype=torch.float64)
    before = counters["stats"]["unique_graphs"]
    models = []
    for k in range(4):

        def f(t, x, k=k):
            return torch.stack([x[..., 1], -(1.0 + k) * x[..., 0]], dim=-1)

        models.append(f)  # keep every model alive (the compiled cache is weak)
        with torch.no_grad():
            sol = odeint(f, x0, t, method="euler", compile=True)
        if not sol.stats.extra["compiled"]:
            pytest.skip("torch.compile is unavailable here")
    assert counters["stats"]["unique_graphs"] - before >= 4
    before = counters["stats"]["unique_graphs"]
    for batch in (1, 3, 4):
        with torch.no_grad():
            x0 = torch.ones(batch, 2, dtype=torch.float64)
            odeint(models[0], x0, t, method="euler", compile=True)
    assert counters["stats"]["unique_graphs"] - before >= 3
