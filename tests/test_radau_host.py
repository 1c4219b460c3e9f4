"""Host (numpy) loop of adaptive Radau IIA (integrators/_radau_host.py) against the torch
driver (integrators/radau.py), closed forms, scipy's Radau and finite differences.

The host loop is the same algorithm, so on every problem here it takes the same steps,
rejections, Newton iterations, Jacobians and factorisations as the torch driver; only the
rounding of tiny products differs (numpy vs torch kernels, summation order), which keeps the
results within ~1e-12 relative at the same steps.
"""

import numpy as np
import pytest
import torch
from hypothesis import example, given, settings
from hypothesis import strategies as st
from scipy.integrate import solve_ivp
from scipy.linalg import expm

from integrators import (
    InputValidationError,
    SemiExplicitDAE,
    Status,
    daeint,
    odeint,
    radau_iia,
    solve_implicit_ode,
)
from integrators._irk_core import InputSignal, IRKCore
from integrators._irk_system import StageSystem
from integrators._radau_host import HOST_MAX_NUMEL, _factorize, _filter_weights
from integrators.inputs import bind_rhs
from integrators.radau import embedded_weights

pytestmark = pytest.mark.usefixtures("float64_default")

COUNTERS = ("n_steps", "n_rejected", "n_newton_iters")


def vdp(eps):
    """Stiff Van der Pol y1' = y2, eps y2' = (1 - y1^2) y2 - y1 (eps a float or (B, 1))."""

    def rhs(t, y):
        y1, y2 = y[..., 0:1], y[..., 1:2]
        return torch.cat([y2, ((1 - y1**2) * y2 - y1) / eps], -1)

    return rhs


def both_paths(f, x0, t, **opts):
    """The same simulation (no gradient recording: in grad mode the torch driver adds the
    implicit-function-theorem evaluations of steps it then rejects to ``n_f_evals``, the host
    loop's replay only those of accepted steps) by the host loop and by the torch driver."""
    with torch.no_grad():
        host = solve_implicit_ode(f, x0, t, "radau_iia", host_loop=True, **opts)
        dev = solve_implicit_ode(f, x0, t, "radau_iia", host_loop=False, **opts)
    assert host.stats.extra["host_loop"] and not dev.stats.extra["host_loop"]
    return host, dev


def assert_same_run(host, dev, rtol=1e-10):
    """Same step sequence and counters, same statuses, results agreeing to ``rtol`` (and below
    the smallest normal number, where the two drivers' subnormal roundings may differ)."""
    for name in COUNTERS:
        assert getattr(host.stats, name).tolist() == getattr(dev.stats, name).tolist(), name
    for name in ("n_f_evals", "n_jac_evals", "n_factorizations"):
        assert getattr(host.stats, name) == getattr(dev.stats, name), name
    assert host.status.tolist() == dev.status.tolist()
    atol = rtol * float(dev.x.abs().max()) + torch.finfo(dev.x.dtype).tiny
    torch.testing.assert_close(host.x, dev.x, rtol=rtol, atol=atol)


def test_factorisation_and_error_filter_block_against_direct_inverses():
    """The host factorisation: ``-J^{-1}`` for ``J = I + h A (x) G`` (eq. 7.16), its image
    under ``A (x) I`` and the error filter's block ``(gamma / h I + G)^{-1}`` read off
    ``J^{-1}`` (gamma the real eigenvalue of A^{-1}) equal the direct inverses."""
    tab, n, B = radau_iia(3), 3, 4
    system = StageSystem("ode", n, 0, (lambda t, x: x,), False)
    core = IRKCore(tab, system, InputSignal(None), torch.float64, "cpu")
    rng = np.random.default_rng(0)
    G, h = rng.normal(size=(B, n, n)) * 10, rng.uniform(0.01, 1.0, B)
    A = np.array(tab.A)
    stacked, real_inv, singular = _factorize(A, _filter_weights(core, np.float64), G, h)
    J = np.eye(3 * n) + h[:, None, None] * np.stack([np.kron(A, g) for g in G])
    np.testing.assert_allclose(-stacked[:, : 3 * n], np.linalg.inv(J), rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(
        stacked[:, 3 * n :], np.kron(A, np.eye(n)) @ stacked[:, : 3 * n], rtol=1e-12, atol=1e-14
    )
    gamma, _ = embedded_weights(tab)
    direct = np.linalg.inv(G + np.eye(n) * (gamma / h)[:, None, None])
    np.testing.assert_allclose(real_inv, direct, rtol=1e-9, atol=1e-12)
    assert not singular.any()


def test_stiff_van_der_pol_same_steps_as_torch_driver_and_accurate(stiff_vdp_reference):
    """eps = 1e-3, t in [0, 1], rtol = atol = 1e-6: identical step sequences and counters,
    results equal to 1e-10 relative and, against scipy's Radau at 1e-12, each component of
    y(1) within rtol relative (measured 9.4e-8 = 0.094 rtol)."""
    eps, t = 1e-3, torch.tensor([0.0, 0.5, 1.0])
    host, dev = both_paths(vdp(eps), torch.tensor([[2.0, 0.0]]), t, rtol=1e-6, atol=1e-6)
    assert host.success and int(host.stats.n_steps[0]) > 50
    assert_same_run(host, dev)
    ref = stiff_vdp_reference(eps, 1.0)
    assert (np.abs(host.x[0, -1].numpy() - ref) / np.abs(ref)).max() < 1e-6


def test_stiff_linear_system_against_matrix_exponential():
    """x' = M x with eigenvalues -1 and -1e4 (stiffness ratio 1e4): closed form expm(M t) x0;
    dense output ``sol.at`` between the steps too."""
    M = torch.tensor([[-1.0, 1.0], [0.0, -1e4]])
    x0 = torch.tensor([[1.0, 2.0], [-0.5, 1.0]])
    t = torch.linspace(0.0, 2.0, 5)
    host, dev = both_paths(lambda t, x: x @ M.T, x0, t, rtol=1e-8, atol=1e-10)
    assert_same_run(host, dev)
    tq = torch.tensor([0.013, 0.37, 1.21, 1.9])
    exact = np.stack([x0.numpy() @ expm(M.numpy() * float(s)).T for s in tq], 1)
    assert np.abs(host.at(tq).numpy() - exact).max() < 1e-7
    torch.testing.assert_close(host.at(tq), dev.at(tq), rtol=1e-10, atol=1e-13)
    torch.testing.assert_close(host.at(t), host.x, rtol=1e-12, atol=1e-14)


def robertson(t, y):
    y1, y2, y3 = y[..., 0], y[..., 1], y[..., 2]
    return torch.stack(
        [-0.04 * y1 + 1e4 * y2 * y3, 0.04 * y1 - 1e4 * y2 * y3 - 3e7 * y2**2, 3e7 * y2**2], -1
    )


def test_robertson_kinetics_same_as_torch_driver_and_scipy():
    """Robertson's stiff kinetics (n = 3, s n = 9) to t = 40 at rtol = 1e-6, atol = 1e-10
    against scipy's BDF at 1e-12: each component of y(40) within 0.05 rtol relative (measured
    4.4e-9 = 0.0044 rtol; the tolerance 1e-9 is tested in test_implicit.py)."""
    t = torch.tensor([0.0, 0.4, 40.0])
    y0 = torch.tensor([[1.0, 0.0, 0.0]])
    host, dev = both_paths(robertson, y0, t, rtol=1e-6, atol=1e-10)
    assert_same_run(host, dev)
    ref = solve_ivp(
        lambda t, y: robertson(t, torch.as_tensor(y)).numpy(),
        (0.0, 40.0),
        [1.0, 0.0, 0.0],
        method="BDF",
        rtol=1e-12,
        atol=1e-16,
    ).y[:, -1]
    assert (np.abs(host.x[0, -1].numpy() - ref) / np.abs(ref)).max() < 0.05 * 1e-6
    # mass conservation y1 + y2 + y3 = 1 (a linear invariant every RK method keeps)
    assert float((host.x.sum(-1) - 1).abs().max()) < 1e-12


def test_batch_members_of_very_different_stiffness_equal_their_solo_runs():
    """Per-sample steps: in a batch with eps = 1e-1, 1e-3, 1e-5 each member takes exactly the
    steps it takes alone (bit for bit the same host arithmetic per member)."""
    eps = [1e-1, 1e-3, 1e-5]
    t = torch.tensor([0.0, 0.3])
    x0 = torch.tensor([2.0, 0.0])
    opts = dict(rtol=1e-6, atol=1e-6, host_loop=True)
    batch = solve_implicit_ode(
        vdp(torch.tensor(eps)[:, None]), x0.expand(3, 2), t, "radau_iia", **opts
    )
    steps = batch.stats.n_steps.tolist()
    assert steps[0] < steps[1] < steps[2]
    for i, e in enumerate(eps):
        alone = solve_implicit_ode(vdp(torch.tensor([[e]])), x0[None], t, "radau_iia", **opts)
        for name in COUNTERS:
            assert getattr(alone.stats, name)[0] == getattr(batch.stats, name)[i], (name, i)
        torch.testing.assert_close(alone.x[0], batch.x[i], rtol=1e-13, atol=1e-13)


def test_multi_dimensional_batch_and_unbatched_state():
    """Batch shape (2, 2) and an unbatched state (n,) give the numbers of a flat batch."""
    eps = torch.tensor([1e-1, 1e-2, 1e-3, 1e-4])[:, None]
    x0 = torch.tensor([[2.0, 0.0], [1.5, 0.1], [2.0, -0.2], [1.0, 0.0]])
    t = torch.tensor([0.0, 0.2, 0.4])
    opts = dict(rtol=1e-6, atol=1e-8, host_loop=True)
    flat = solve_implicit_ode(vdp(eps), x0, t, "radau_iia", **opts)
    grid = solve_implicit_ode(vdp(eps.reshape(2, 2, 1)), x0.reshape(2, 2, 2), t, **opts)
    assert grid.x.shape == (2, 2, 3, 2) and grid.status.shape == (2, 2)
    torch.testing.assert_close(grid.x.reshape(4, 3, 2), flat.x, rtol=1e-13, atol=1e-13)
    assert grid.stats.n_steps.reshape(4).tolist() == flat.stats.n_steps.tolist()
    alone = solve_implicit_ode(vdp(1e-3), x0[2], t, **opts)
    assert alone.x.shape == (3, 2) and alone.status.shape == ()
    torch.testing.assert_close(alone.x, flat.x[2], rtol=1e-13, atol=1e-13)


def test_float32_host_loop_matches_torch_driver_and_reference(stiff_vdp_reference):
    """float32 end to end: dtype kept, same accuracy as the torch driver against scipy."""
    eps, t = 1e-2, torch.tensor([0.0, 1.0], dtype=torch.float32)
    x0 = torch.tensor([[2.0, 0.0]], dtype=torch.float32)
    host, dev = both_paths(vdp(eps), x0, t, rtol=1e-4, atol=1e-4)
    assert host.x.dtype == torch.float32 and host.success
    # float32 rounding differs between numpy and torch kernels: a step or two may differ
    assert abs(int(host.stats.n_steps[0]) - int(dev.stats.n_steps[0])) <= 2
    ref = stiff_vdp_reference(eps, 1.0)
    for sol in (host, dev):
        assert np.abs(sol.x[0, -1].double().numpy() - ref).max() < 2e-3


def test_blow_up_and_max_steps_statuses_and_messages_as_torch_driver():
    """x' = x^2 escapes to infinity at t = 1 from x0 = 1 (the other member, x0 = -1, decays
    to -1 / (1 + t)); max_steps stops a long stiff run. Statuses and messages as the torch
    driver's."""
    x0 = torch.tensor([[1.0], [-1.0]])
    host, dev = both_paths(lambda t, x: x**2, x0, torch.tensor([0.0, 2.0]))
    assert host.status[0] in (Status.NON_FINITE, Status.STEP_TOO_SMALL)
    assert host.status[1] == Status.SUCCESS
    assert host.status.tolist() == dev.status.tolist()
    assert host.messages == dev.messages
    assert any("sample (0,)" in m and "t = 1" in m for m in host.messages)
    torch.testing.assert_close(host.x[1, -1], torch.tensor([-1 / 3]), rtol=1e-5, atol=1e-6)
    few, few_dev = both_paths(
        vdp(1e-6), torch.tensor([[2.0, 0.0]]), torch.tensor([0.0, 2.0]), max_steps=5
    )
    assert few.status[0] == Status.MAX_STEPS and few.messages == few_dev.messages
    assert int(few.stats.n_steps[0]) + int(few.stats.n_rejected[0]) == 5


class Decay(torch.nn.Module):
    """x' = -k x (x1) and a nonlinear damped oscillator (x2, x3) with parameters k."""

    def __init__(self):
        super().__init__()
        self.k = torch.nn.Parameter(torch.tensor([3.0, 2.0, 0.5]))

    def forward(self, t, x):
        k = self.k
        x1, x2, x3 = x[..., 0], x[..., 1], x[..., 2]
        return torch.stack([-k[0] * x1, x3, -k[1] * x2 - k[2] * x3 * (1 + x2**2)], -1)


def test_gradients_match_closed_form_finite_differences_and_torch_driver(central_difference):
    """d loss / d (x0, k) by the implicit function theorem on the replayed steps: equal to the
    torch driver's, to central differences, and for x1 = x0 e^{-k0 T} to the closed form."""
    model = Decay()
    x0 = torch.tensor([[1.0, 0.5, -0.2]], requires_grad=True)
    t = torch.tensor([0.0, 0.7, 1.5])
    opts = dict(rtol=1e-10, atol=1e-10)

    def loss(host_loop):
        sol = solve_implicit_ode(model, x0, t, "radau_iia", host_loop=host_loop, **opts)
        assert sol.stats.extra["host_loop"] == host_loop
        return sol.x[..., -1, :].pow(2).sum() + sol.at(torch.tensor([1.1])).sum()

    g_host = torch.autograd.grad(loss(True), (x0, model.k))
    g_dev = torch.autograd.grad(loss(False), (x0, model.k))
    for a, b in zip(g_host, g_dev, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-12)
    fd_x = central_difference(lambda: loss(True), x0)
    fd_k = central_difference(lambda: loss(True), model.k)
    # adaptive steps move with the perturbation: FD agrees to about the tolerance
    assert float((g_host[0] - fd_x).abs().max() / fd_x.abs().max()) < 1e-5
    assert float((g_host[1] - fd_k).abs().max() / fd_k.abs().max()) < 1e-5
    # closed form of the x1 part: d/dk0 [x1(T)^2 + x1(1.1)] with x1 = x0 e^{-k0 t}
    k0, a = 3.0, 1.0
    exact = -2 * 1.5 * a**2 * np.exp(-2 * k0 * 1.5) - 1.1 * a * np.exp(-k0 * 1.1)
    assert abs(float(g_host[1][0]) - exact) < 1e-7 * abs(exact)


def test_grad_mode_does_not_change_the_numbers():
    """With the IFT graph (replay) or without it, the outputs are bit for bit the same."""
    mu = torch.tensor(1.5, requires_grad=True)

    def osc(t, x):
        return torch.stack([mu * (1 - x[..., 1] ** 2) * x[..., 0] - x[..., 1], x[..., 0]], -1)

    x0 = torch.tensor([[0.5, 1.0], [1.0, -0.5]])
    t = torch.linspace(0.0, 2.0, 6)
    with_grad = solve_implicit_ode(osc, x0, t, rtol=1e-7, atol=1e-9, host_loop=True)
    with torch.no_grad():
        without = solve_implicit_ode(osc, x0, t, rtol=1e-7, atol=1e-9, host_loop=True)
    assert with_grad.x.requires_grad and not without.x.requires_grad
    torch.testing.assert_close(with_grad.x.detach(), without.x, rtol=0, atol=0)


def _rotation_first_axis_only(t, x):
    """x' = w [x2, -x1], w = 1 + |x|^2, written with x[:, i]: wrong when stages are stacked
    on a leading axis, so it is evaluated stage by stage."""
    w = 1 + x.square().sum(-1, keepdim=True)
    return w * torch.stack([x[:, 1], -x[:, 0]], -1)


def test_stage_by_stage_models_and_exact_rotation():
    """A model that cannot take stacked stages runs stage by stage on the host too; |x| is
    conserved, so the exact solution is a rotation by the angle w(x0) t."""
    x0 = torch.tensor([[1.0, 0.0], [0.3, -0.4]])
    t = torch.tensor([0.0, 1.0])
    host, dev = both_paths(_rotation_first_axis_only, x0, t, rtol=1e-9, atol=1e-11)
    assert not host.stats.extra["stacked_stages"]
    assert_same_run(host, dev)
    w = 1 + x0.square().sum(-1)
    c, s = torch.cos(w), torch.sin(w)
    exact = torch.stack([c * x0[:, 0] + s * x0[:, 1], -s * x0[:, 0] + c * x0[:, 1]], -1)
    assert float((host.x[:, -1] - exact).abs().max()) < 1e-7


# x' = -50 (x - u): elementwise (its stages are evaluated in one stacked call), and written
# for a (batch, 1) state only (the einsum refuses the stacked (s, batch, 1) stages, so the
# stages are evaluated one by one)
INPUT_MODELS = {
    "stacked": lambda t, x, u: -50 * (x - u),
    "stage by stage": lambda t, x, u: -50 * torch.einsum("bi->bi", x - u),
}


@pytest.mark.parametrize("evaluation", list(INPUT_MODELS))
def test_sampled_input_held_per_interval_against_exact_discretisation(evaluation):
    """x' = -50 (x - u) with a zero-order-hold input (eq. 8.34): exact x_{k+1} = u_k +
    (x_k - u_k) e^{-50 dt}. Both drivers evaluate the stages at the same stage times, with the
    inputs there, in one stacked call or stage by stage as the model allows. Near the input
    jumps the step control rejects many steps and a rounding-level difference in the error
    estimate (a difference of nearly equal numbers, where ulps of the stages become ~1e-10
    relative) can flip one accept/reject decision, after which the two step sequences differ
    a little: both meet the tolerance."""
    t = torch.linspace(0.0, 1.0, 5)
    u = torch.sin(3 * t)[:, None]
    rhs = bind_rhs(INPUT_MODELS[evaluation], u, t)
    x0 = torch.tensor([[0.5], [1.0]])
    host, dev = both_paths(rhs, x0, t, rtol=1e-7, atol=1e-9)
    stacked = evaluation == "stacked"
    assert host.stats.extra["stacked_stages"] == dev.stats.extra["stacked_stages"] == stacked
    assert host.success and dev.success
    x, exact = x0[:, 0].clone(), [x0[:, 0].clone()]
    for k in range(4):
        x = u[k] + (x - u[k]) * np.exp(-50 * float(t[k + 1] - t[k]))
        exact.append(x)
    exact = torch.stack(exact, -1)
    assert float((host.x[..., 0] - exact).abs().max()) < 1e-6
    assert float((host.x - dev.x).abs().max()) < 1e-6
    steps_host, steps_dev = host.stats.n_steps.double(), dev.stats.n_steps.double()
    assert float(((steps_host - steps_dev).abs() / steps_dev).max()) < 0.05


@pytest.mark.parametrize("host_loop", [True, False])
@pytest.mark.parametrize("x0_shape", [(2,), (3, 2)])
def test_float32_steps_land_on_the_input_sample_times(host_loop, x0_shape):
    """A float32 step cut to an input sample time ended one rounding short of it (t_k + (t_s -
    t_k) != t_s in float32), left a sliver below the smallest step, and the run stopped with
    STEP_TOO_SMALL at the first sample time; a step cut to a stop now ends on it. Truth: the
    exact zero-order-hold discretisation of x'' = -4 x - 0.5 x' + u (float64 matrix
    exponential), to float32's accuracy at rtol 1e-5."""
    t = 0.05 * torch.arange(21, dtype=torch.float64)
    u = torch.sin(7 * t)[:, None]
    x0 = torch.tensor([1.0, 0.0], dtype=torch.float32).expand(*x0_shape).clone()

    def f(t, x, u):
        return torch.stack([x[..., 1], -4 * x[..., 0] - 0.5 * x[..., 1] + u[..., 0]], -1)

    sol = odeint(f, x0, t, u=u, method="radau_iia", rtol=1e-5, atol=1e-7, host_loop=host_loop)
    assert sol.success, sol.messages
    assert sol.x.dtype == torch.float32
    M = torch.zeros(3, 3, dtype=torch.float64)
    M[0, 1], M[1, 0], M[1, 1], M[1, 2] = 1.0, -4.0, -0.5, 1.0
    step = torch.linalg.matrix_exp(0.05 * M)
    x, exact = x0[..., :].double().reshape(-1, 2)[0], []
    for k in range(21):
        exact.append(x)
        x = (step @ torch.cat([x, u[k]]))[:2]
    exact = torch.stack(exact)
    assert float((sol.x.double() - exact).abs().max()) < 1e-4


@settings(max_examples=5, deadline=None)
@given(lam=st.floats(-1e6, -1e-2), x0=st.floats(-3.0, 3.0))
@example(lam=-3.0, x0=5e-324)  # a subnormal state: the drivers may round it differently
def test_linear_test_equation_any_stiffness_same_as_torch_driver(lam, x0):
    """x' = lam x (eq. 6.40) for any stiffness: same steps as the torch driver, exact to tol."""
    t = torch.tensor([0.0, 0.3, 1.0])
    host, dev = both_paths(lambda t, x: lam * x, torch.tensor([[x0]]), t, rtol=1e-8, atol=1e-10)
    assert_same_run(host, dev, rtol=1e-9)
    exact = x0 * np.exp(lam * t.numpy())
    assert np.abs(host.x[0, :, 0].numpy() - exact).max() < 1e-7 * (1 + abs(x0))


def test_dispatch_auto_option_and_errors():
    """ "auto" takes the host loop for small CPU explicit ODEs only; odeint passes the option;
    host_loop=True where impossible and unknown values are errors."""
    t = torch.tensor([0.0, 0.1])
    small = torch.tensor([[2.0, 0.0]])
    big = small.expand(HOST_MAX_NUMEL // 2 + 1, 2)
    assert solve_implicit_ode(vdp(1e-2), small, t).stats.extra["host_loop"]
    assert not solve_implicit_ode(vdp(1e-2), big, t).stats.extra["host_loop"]
    assert not solve_implicit_ode(vdp(1e-2), small, t, adaptive=False).stats.extra["host_loop"]
    with pytest.raises(InputValidationError, match="not fixed steps"):
        solve_implicit_ode(vdp(1e-2), small, t, adaptive=False, host_loop=True)
    via = odeint(vdp(1e-2), small, t, method="radau_iia", host_loop=False)
    assert not via.stats.extra["host_loop"]
    dae = SemiExplicitDAE(lambda t, x, z: -z, lambda t, x, z: z - x)
    sol = daeint(dae, small[:, :1], small[:, :1], t)
    assert not sol.stats.extra["host_loop"]
    with pytest.raises(InputValidationError, match="DAEs use the torch driver"):
        daeint(dae, small[:, :1], small[:, :1], t, host_loop=True)
    with pytest.raises(InputValidationError, match="s n = 27 > 24"):
        solve_implicit_ode(lambda t, x: -x, torch.ones(1, 9), t, host_loop=True)
    with pytest.raises(InputValidationError, match="host_loop must be"):
        solve_implicit_ode(vdp(1e-2), small, t, host_loop="yes")


@pytest.mark.parametrize("host_loop", [True, False])
def test_wrong_model_output_shape_is_named_on_both_drivers(host_loop):
    """A model returning the wrong number of states, or one derivative for the whole batch,
    fails before the first step with both shapes in the message."""
    x0 = torch.tensor([[1.0, 2.0], [0.0, -1.0]])
    t = torch.tensor([0.0, 0.5])
    with pytest.raises(InputValidationError, match=r"returned shape \(2, 3\) for x0 of shape"):
        solve_implicit_ode(lambda t, x: torch.cat([x, x[..., :1]], -1), x0, t, host_loop=host_loop)
    rate = torch.tensor([1.0, -2.0])
    with pytest.raises(InputValidationError, match=r"returned shape \(2,\) for x0 of shape"):
        solve_implicit_ode(lambda t, x: rate, x0, t, host_loop=host_loop)


# ------------------------------------------------------------- one-trajectory kernel


def _single_and_batched(f, x0, t, **opts):
    """One float64 trajectory (the one-trajectory kernel, Python-scalar step control) and the
    same state twice (the numpy kernel, host arrays)."""
    one = solve_implicit_ode(f, x0, t, "radau_iia", host_loop=True, **opts)
    two = solve_implicit_ode(f, x0.expand(2, -1), t, "radau_iia", host_loop=True, **opts)
    assert one.stats.extra["driver"] == "host, one trajectory"
    assert two.stats.extra["driver"] == "host"
    return one, two


@pytest.mark.parametrize(
    "case",
    ["stiff_vdp", "robertson", "stiff_linear", "blow_up", "max_steps"],
)
def test_one_trajectory_kernel_takes_the_batched_kernels_steps(case):
    """The adaptive loop with the one-trajectory kernel (Python-scalar step control) takes the
    steps it takes with the batched numpy kernel: the same steps, rejections, Newton
    iterations, Jacobians, factorisations, statuses and results (to rounding of the Newton
    norm's summation order); into a blow-up, the same status and message within one step."""
    M = torch.tensor([[-1.0, 1.0], [0.0, -1e4]])
    f, x0, t, opts = {
        "stiff_vdp": (vdp(1e-4), [2.0, 0.0], [0.0, 0.3, 1.0], dict(rtol=1e-7, atol=1e-7)),
        "robertson": (robertson, [1.0, 0.0, 0.0], [0.0, 4.0, 40.0], dict(rtol=1e-6, atol=1e-10)),
        "stiff_linear": (lambda t, x: x @ M.T, [1.0, 2.0], [0.0, 2.0], dict(rtol=1e-8, atol=1e-10)),
        "blow_up": (lambda t, x: x**2, [1.0], [0.0, 2.0], dict(rtol=1e-6, atol=1e-9)),
        "max_steps": (vdp(1e-4), [2.0, 0.0], [0.0, 1.0], dict(rtol=1e-7, atol=1e-7, max_steps=15)),
    }[case]
    one, two = _single_and_batched(f, torch.tensor([x0]), torch.tensor(t), **opts)
    if case == "blow_up":
        # the error estimate cancels digits (|h K| ~ 1e6 |err|), so the scalar and the array
        # arithmetic give step sizes 1e-11 apart after some steps; where h shrinks towards the
        # time resolution at t = 1, that can decide one step more or less (hardware dependent)
        for name in COUNTERS:
            got, ref = getattr(two.stats, name), getattr(one.stats, name).expand(2)
            assert int((got - ref).abs().max()) <= {"n_steps": 1}.get(name, 2), name
    else:
        for name in COUNTERS:
            assert getattr(two.stats, name).tolist() == 2 * getattr(one.stats, name).tolist(), name
        assert one.stats.n_jac_evals == two.stats.n_jac_evals
        assert one.stats.n_factorizations == two.stats.n_factorizations
    assert two.status.tolist() == 2 * one.status.tolist()
    finite = torch.isfinite(one.x)
    # (near the blow-up the values reach 1e13, where the rounding of the norms shows at 1e-12)
    torch.testing.assert_close(one.x[finite], two.x[0][finite[0]], rtol=1e-11, atol=1e-14)
    if case == "blow_up":  # x = 1 / (1 - t) escapes at t = 1: stopped there with a message
        assert one.status[0] in (Status.NON_FINITE, Status.STEP_TOO_SMALL)
        dev = solve_implicit_ode(f, torch.tensor([x0]), torch.tensor(t), host_loop=False, **opts)
        assert one.messages == dev.messages and "t = 1" in one.messages[0]
    if case == "max_steps":
        assert one.status[0] == Status.MAX_STEPS and one.stats.n_steps[0] < 15
        assert one.messages[0].startswith("sample (0,): MAX_STEPS at t = ")
        assert two.messages[0] == one.messages[0]


def test_one_trajectory_kernel_unbatched_state_and_dispatch():
    """An unbatched float64 state (n,) takes the one-trajectory kernel with the batched
    kernel's numbers; float32 and batches keep the numpy kernel; host_loop=False the torch
    one."""
    t = torch.tensor([0.0, 0.2, 0.4])
    opts = dict(rtol=1e-6, atol=1e-8)
    alone = solve_implicit_ode(vdp(1e-3), torch.tensor([2.0, 0.0]), t, **opts)
    assert alone.stats.extra["driver"] == "host, one trajectory" and alone.x.shape == (3, 2)
    assert alone.status.shape == () and alone.stats.n_steps.shape == ()
    pair = solve_implicit_ode(vdp(1e-3), torch.tensor([[2.0, 0.0], [2.0, 0.0]]), t, **opts)
    torch.testing.assert_close(alone.x, pair.x[1], rtol=1e-12, atol=1e-14)
    assert int(alone.stats.n_steps) == int(pair.stats.n_steps[1])
    single32 = torch.tensor([[2.0, 0.0]], dtype=torch.float32)
    assert solve_implicit_ode(vdp(1e-3), single32, t.float()).stats.extra["driver"] == "host"
    torch_run = solve_implicit_ode(vdp(1e-3), torch.tensor([2.0, 0.0]), t, host_loop=False)
    assert torch_run.stats.extra["driver"] == "torch"


@settings(max_examples=300, deadline=None)
@given(
    h=st.floats(1e-12, 10.0),
    err=st.one_of(st.floats(0.0, 1e6), st.just(float("inf"))),
    err_old=st.floats(1e-2, 1e3),
    h_old=st.one_of(st.just(0.0), st.floats(1e-12, 10.0)),
    first=st.booleans(),
    iters=st.integers(1, 7),
    theta=st.floats(0.0, 0.99),
)
def test_scalar_step_size_rule_equals_the_array_rule(h, err, err_old, h_old, first, iters, theta):
    """``GustafssonController.radau_step_sizes`` on Python floats (the one-trajectory kernel's
    representation) returns what it returns on host arrays (the batched kernels'), to the last
    bit or two (numpy's vectorised ``power`` and the C library's ``pow`` may round
    differently), and the same decisions."""
    from integrators.controllers import GustafssonController

    rule = GustafssonController()

    finite = bool(np.isfinite(err))
    scalar = rule.radau_step_sizes(h, err, finite, err_old, h_old, first, iters, theta, 7, 0.25)
    assert all(type(v) in (float, bool) for v in scalar)  # the scalar representation
    arrays = rule.radau_step_sizes(
        *(np.array([v]) for v in (h, err, finite, err_old, h_old, first, iters, theta)), 7, 0.25
    )
    for got, want in zip(scalar[:3], arrays[:3], strict=True):
        assert got == pytest.approx(want[0], rel=1e-15, abs=0.0, nan_ok=True)
    assert scalar[3] == bool(arrays[3][0])
