"""sysid.linearize: Jacobians along trajectories and at steady states (eq. 1.33-1.42), and the
exact ZOH discretisation (eq. 1.55) against scipy and python-control."""

import math

import control
import numpy as np
import pytest
import scipy.signal
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from integrators.errors import ConvergenceError, InputValidationError, SingularMatrixError
from sysid.linearize import linearize, simulate_lti_zoh, steady_state, zoh_discretize
from sysid.zoo import NonlinearExample
from sysid.zoo.scenarios import scenarios

DT = torch.float64


def test_linearisation_along_a_trajectory_matches_eq_1_39():
    plant = NonlinearExample()
    x = torch.randn(3, 40, 2, dtype=DT, generator=torch.Generator().manual_seed(0))
    u = torch.randn(3, 40, 1, dtype=DT, generator=torch.Generator().manual_seed(1))
    a, b, c, d = linearize(plant, x, u, h=lambda xx, uu: plant.output(xx, uu))
    ref = plant.closed_form_linearization(x)
    for got, want in zip((a, b, c, d), ref, strict=True):
        torch.testing.assert_close(got, want.expand_as(got), rtol=1e-12, atol=1e-12)


@settings(max_examples=10, deadline=None)
@given(st.floats(-1.5, 1.5))
def test_steady_state_by_newton_and_eq_1_42(u_bar):
    """Eq. (1.40)-(1.42): x_bar = [0, u_bar]; A = [[1 - u_bar^2, -1], [1, 0]] (eq. 1.42 prints
    A[0, 0] = 1: a typo, right only for u_bar = 0), B = [1, 0]^T, C = [1, 3 u_bar^2], D = 0."""
    plant = NonlinearExample()
    u = torch.tensor([[u_bar]], dtype=DT)
    x_bar = steady_state(plant, torch.tensor([[0.3, 0.2]], dtype=DT), u)
    torch.testing.assert_close(x_bar, torch.tensor([[0.0, u_bar]], dtype=DT), atol=1e-9, rtol=0)
    a, b, c, d = linearize(plant, x_bar, u, h=lambda xx, uu: plant.output(xx, uu))
    a_ref = torch.tensor([[[1 - u_bar**2, -1.0], [1.0, 0.0]]], dtype=DT)
    torch.testing.assert_close(a, a_ref, atol=1e-8, rtol=0)
    torch.testing.assert_close(b, torch.tensor([[[1.0], [0.0]]], dtype=DT))
    torch.testing.assert_close(
        c, torch.tensor([[[1.0, 3 * u_bar**2]]], dtype=DT), atol=1e-8, rtol=0
    )
    assert float(d.abs().max()) == 0.0


def test_steady_state_reports_non_convergence():
    with pytest.raises(ConvergenceError, match="batch indices"):
        steady_state(lambda t, x: x**2 + 1.0, torch.tensor([[0.5]], dtype=DT), max_iter=5)


def test_steady_state_is_differentiable_by_the_implicit_function_theorem():
    """Eq. (1.41): x_bar = [0, u_bar], so dx_bar/du_bar = [0, 1]; a spring-mass-damper
    (eq. 1.26) rests at y = u / K, so dy/dK = -u / K^2 and dy/du = 1 / K."""
    u = torch.tensor([[0.4], [-0.9]], dtype=DT, requires_grad=True)
    x_bar = steady_state(NonlinearExample(), torch.tensor([[0.3, 0.2]] * 2, dtype=DT), u)
    (grad,) = torch.autograd.grad(x_bar[:, 1].sum(), u)
    torch.testing.assert_close(grad, torch.ones_like(u), rtol=0, atol=1e-12)
    (grad,) = torch.autograd.grad(x_bar[:, 0].sum(), u)
    torch.testing.assert_close(grad, torch.zeros_like(u), rtol=0, atol=1e-12)

    from sysid.zoo import SpringMassDamper

    plant = SpringMassDamper(K=4.0)
    u = torch.tensor([[2.0]], dtype=DT, requires_grad=True)
    x_bar = steady_state(plant, torch.tensor([[1.0, 0.5]], dtype=DT), u)
    torch.testing.assert_close(x_bar, torch.tensor([[0.5, 0.0]], dtype=DT), rtol=0, atol=1e-12)
    x_bar[0, 0].backward()
    assert plant.K.grad.item() == pytest.approx(-2.0 / 16.0, rel=1e-10)
    assert u.grad.item() == pytest.approx(1 / 4.0, rel=1e-10)


def test_steady_state_gradients_reach_tensors_that_f_reads_from_its_closure():
    """x' = -k x^3 + u at rest: x = (u / k)^(1/3), dx/dk = -x / (3 k) with k a tensor in the
    closure of a plain function (no gradient reached it: the equilibrium was detached), and
    dx/da for a bound method of a zoo plant (eq. 5.38a at rest: x1 = u / (a - 1))."""
    k = torch.tensor(2.0, dtype=DT, requires_grad=True)
    u = torch.tensor([[1.0]], dtype=DT)
    x = steady_state(lambda t, x, u: -k * x**3 + u, torch.tensor([[0.5]], dtype=DT), u)
    (g,) = torch.autograd.grad(x.sum(), k)
    assert g.item() == pytest.approx(-(0.5 ** (1 / 3)) / 6.0, rel=1e-10)

    from sysid.zoo.dae import SingularlyPerturbedLinear

    plant = SingularlyPerturbedLinear(a=2.0)
    x = steady_state(plant.reduced, torch.tensor([[0.3]], dtype=DT), u)
    torch.testing.assert_close(x, torch.tensor([[1.0]], dtype=DT), rtol=0, atol=1e-12)
    (g,) = torch.autograd.grad(x.sum(), plant.a)
    assert g.item() == pytest.approx(-1.0, rel=1e-10)  # d/da u / (a - 1) = -u / (a - 1)^2


def test_steady_state_names_the_sample_with_a_singular_jacobian():
    with pytest.raises(SingularMatrixError, match=r"df/dx is singular at batch indices \[\[1\]\]"):
        steady_state(lambda t, x: x**2 - 1.0, torch.tensor([[2.0], [0.0]], dtype=DT))


def test_linearize_is_differentiable_with_respect_to_parameters():
    from sysid.zoo import VanDerPol

    plant = VanDerPol(mu=1.5)
    x = torch.tensor([[0.4, -0.7]], dtype=DT)
    a = linearize(plant, x)[0]
    a[0, 0, 0].backward()  # d/dmu of mu (1 - x2^2) = 1 - x2^2
    assert plant.mu.grad.item() == pytest.approx(1 - 0.7**2)


def _random_lti(seed, n=3, m=2):
    rng = np.random.default_rng(seed)
    return rng.normal(size=(n, n)), rng.normal(size=(n, m))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_zoh_discretisation_matches_scipy_and_python_control(seed):
    a, b = _random_lti(seed)
    dt = 0.1 + 0.2 * seed
    ad, bd = zoh_discretize(torch.tensor(a), torch.tensor(b), dt)
    ad_s, bd_s, *_ = scipy.signal.cont2discrete((a, b, np.eye(3), np.zeros((3, 2))), dt, "zoh")
    np.testing.assert_allclose(ad.numpy(), ad_s, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(bd.numpy(), bd_s, rtol=1e-12, atol=1e-12)
    sys_d = control.c2d(control.ss(a, b, np.eye(3), np.zeros((3, 2))), dt, method="zoh")
    np.testing.assert_allclose(ad.numpy(), sys_d.A, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(bd.numpy(), sys_d.B, rtol=1e-10, atol=1e-12)


def test_zoh_discretisation_is_batched_over_systems_and_steps():
    a = torch.stack([torch.tensor(_random_lti(s)[0]) for s in range(4)])
    b = torch.stack([torch.tensor(_random_lti(s)[1]) for s in range(4)])
    dt = torch.tensor([0.1, 0.2, 0.3, 0.4], dtype=DT)
    ad, bd = zoh_discretize(a, b, dt)
    for i in range(4):
        ref = zoh_discretize(a[i], b[i], float(dt[i]))
        torch.testing.assert_close(ad[i], ref[0])
        torch.testing.assert_close(bd[i], ref[1])


@pytest.mark.parametrize("dt", [0.0, -0.1, math.nan, math.inf, [0.1, -0.1]])
def test_zoh_refuses_a_step_that_is_not_finite_and_positive(dt):
    """dt = 0 gave Ad = I, dt < 0 the backward map and dt = NaN NaN matrices, silently."""
    a, b = (torch.tensor(x) for x in _random_lti(0))
    with pytest.raises(InputValidationError, match="dt must be finite and > 0"):
        zoh_discretize(a, b, torch.tensor(dt, dtype=DT))
    with pytest.raises(InputValidationError, match="dt must be finite and > 0"):
        simulate_lti_zoh(a, b, torch.zeros(3, dtype=DT), torch.zeros(5, 2, dtype=DT), dt)


@pytest.mark.parametrize("name", ["A", "B"])
@pytest.mark.parametrize("value", [math.nan, math.inf])
def test_zoh_refuses_a_non_finite_system(name, value):
    """A NaN or inf coefficient gave NaN matrices; the entry is named. A finite system with
    a positive step still matches scipy's cont2discrete."""
    a, b = (torch.tensor(x) for x in _random_lti(1))
    bad = (a, b)[name == "B"].clone()
    bad[1, 0] = value
    args = (bad, b) if name == "A" else (a, bad)
    with pytest.raises(InputValidationError, match=rf"{name} has a non-finite entry .* \(1, 0\)"):
        zoh_discretize(*args, 0.1)
    ad, _ = zoh_discretize(a, b, 1e-3)
    ad_s, *_ = scipy.signal.cont2discrete(
        (a.numpy(), b.numpy(), np.eye(3), np.zeros((3, 2))), 1e-3, "zoh"
    )
    np.testing.assert_allclose(ad.numpy(), ad_s, rtol=1e-12, atol=1e-14)


def test_zoh_simulation_matches_scipy_dlsim_and_lsim():
    a, b = _random_lti(3, n=2, m=1)
    a = a - 2 * np.eye(2)  # stable
    c, d = np.array([[1.0, -0.5]]), np.array([[0.2]])
    dt, steps = 0.05, 60
    u = np.sin(np.arange(steps) * 0.3)[:, None]
    x0 = np.array([0.5, -1.0])
    x, y = simulate_lti_zoh(
        torch.tensor(a),
        torch.tensor(b),
        torch.tensor(x0),
        torch.tensor(u),
        dt,
        torch.tensor(c),
        torch.tensor(d),
    )
    sys_d = scipy.signal.cont2discrete((a, b, c, d), dt, "zoh")
    _, y_ref, x_ref = scipy.signal.dlsim(sys_d[:4] + (dt,), u, x0=x0)
    np.testing.assert_allclose(y.numpy(), y_ref, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(x[:-1].numpy(), x_ref, rtol=1e-10, atol=1e-12)
    # the continuous-time simulator with a held input agrees at the samples (eq. 1.55)
    t = np.arange(steps + 1) * dt
    u_fine = np.repeat(u[:, 0], 1)
    _, _, x_cont = scipy.signal.lsim(
        (a, b, c, d), np.append(u_fine, u_fine[-1]), t, X0=x0, interp=False
    )
    np.testing.assert_allclose(x.numpy(), x_cont, rtol=1e-8, atol=1e-10)


def _dlsim_ref(a, b, c, d, x0, u, dt):
    sys_d = scipy.signal.cont2discrete((a, b, c, d), dt, "zoh")
    _, y_ref, x_ref = scipy.signal.dlsim(sys_d[:4] + (dt,), u, x0=x0)
    return np.atleast_2d(y_ref.T).T, x_ref


def test_zoh_simulation_broadcasts_an_unbatched_x0_and_u_over_batched_systems():
    a = np.stack([_random_lti(s, n=2, m=1)[0] - 3 * np.eye(2) for s in range(3)])
    b = np.stack([_random_lti(s, n=2, m=1)[1] for s in range(3)])
    c = np.stack([[[1.0, -0.5]], [[0.3, 2.0]], [[0.0, 1.0]]])
    d = np.array([[0.2]])
    dts = np.array([0.05, 0.1, 0.2])
    u = np.cos(np.arange(20) * 0.4)[:, None]
    x0 = np.array([0.5, -1.0])
    tt = torch.tensor
    # batched A, B, C and dt; x0 (n,), u (T, m) and D (p, m) shared by every system
    x, y = simulate_lti_zoh(tt(a), tt(b), tt(x0), tt(u), tt(dts), tt(c), tt(d))
    assert x.shape == (3, 21, 2) and y.shape == (3, 20, 1)
    for i in range(3):
        y_ref, x_ref = _dlsim_ref(a[i], b[i], c[i], d, x0, u, dts[i])
        np.testing.assert_allclose(x[i, :-1].numpy(), x_ref, rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(y[i].numpy(), y_ref, rtol=1e-10, atol=1e-12)
    # one system and a batch of steps dt
    x = simulate_lti_zoh(tt(a[0]), tt(b[0]), tt(x0), tt(u), tt(dts))
    for i in range(3):
        _, x_ref = _dlsim_ref(a[0], b[0], c[0], d, x0, u, dts[i])
        np.testing.assert_allclose(x[i, :-1].numpy(), x_ref, rtol=1e-10, atol=1e-12)


def test_zoh_simulation_names_wrong_output_matrices_and_batches():
    a, b = -torch.eye(2, dtype=DT), torch.ones(2, 1, dtype=DT)
    x0, u = torch.zeros(2, dtype=DT), torch.ones(5, 1, dtype=DT)
    with pytest.raises(InputValidationError, match=r"C must be \(\*batch, p, n\) with n = 2"):
        simulate_lti_zoh(a, b, x0, u, 0.1, c=torch.ones(1, 3, dtype=DT))
    with pytest.raises(InputValidationError, match=r"D must be \(\*batch, p, m\)"):
        simulate_lti_zoh(a, b, x0, u, 0.1, c=torch.ones(1, 2, dtype=DT), d=torch.ones(1, 2))
    with pytest.raises(InputValidationError, match="do not broadcast"):
        simulate_lti_zoh(a.expand(3, 2, 2), b, torch.zeros(2, 2, dtype=DT), u, 0.1)


def test_linearize_broadcasts_x_and_u_to_a_common_batch():
    def f(t, x, u):
        return torch.stack([x[..., 1] * u[..., 0], -torch.sin(x[..., 0]) + u[..., 0] ** 2], -1)

    def h(x, u):
        return (x[..., :1] * u) ** 2

    x = torch.tensor([0.3, -0.7], dtype=DT)
    u = torch.tensor([[1.0], [2.0], [-0.5]], dtype=DT)
    a, b, c, d = linearize(f, x, u, h)
    assert a.shape == (3, 2, 2) and b.shape == (3, 2, 1)
    assert c.shape == (3, 1, 2) and d.shape == (3, 1, 1)
    for i, ui in enumerate(u[:, 0].tolist()):
        a_ref = torch.tensor([[0.0, ui], [-np.cos(0.3), 0.0]], dtype=DT)
        b_ref = torch.tensor([[-0.7], [2 * ui]], dtype=DT)
        torch.testing.assert_close(a[i], a_ref)
        torch.testing.assert_close(b[i], b_ref)
        torch.testing.assert_close(c[i], torch.tensor([[2 * 0.3 * ui**2, 0.0]], dtype=DT))
        torch.testing.assert_close(d[i], torch.tensor([[2 * 0.3**2 * ui]], dtype=DT))
    # a batch of states against one input
    a2, b2, _, _ = linearize(f, torch.stack([x, 2 * x]), u[1])
    torch.testing.assert_close(a2[0], a[1])
    torch.testing.assert_close(b2[1], torch.tensor([[-1.4], [4.0]], dtype=DT))


def test_plant_linearize_with_several_input_levels_and_mismatched_batches():
    from sysid.zoo.mechanical import SpringMassDamper

    plant = SpringMassDamper(m=1.5, xi=0.6, K=5.0)
    a, b = plant.linearize(torch.zeros(1, dtype=DT), torch.tensor([[1.0], [2.0]], dtype=DT))
    a_ref = torch.tensor([[0.0, 1.0], [-5.0 / 1.5, -0.6 / 1.5]], dtype=DT)
    torch.testing.assert_close(a, a_ref.expand(2, 2, 2))
    torch.testing.assert_close(b, torch.tensor([[0.0], [1 / 1.5]], dtype=DT).expand(2, 2, 1))
    with pytest.raises(InputValidationError, match=r"x \(2,\) and u \(3,\) do not broadcast"):
        linearize(plant, torch.zeros(2, 2, dtype=DT), torch.zeros(3, 1, dtype=DT))


@pytest.mark.parametrize("scenario", scenarios(), ids=lambda sc: sc.name)
def test_linearize_every_zoo_plant_matches_central_differences(scenario, central_jacobian):
    """A = df/dx and B = df/du (eq. 1.35) of every zoo plant (the Lagrangian ones call autograd
    inside f) at three points near its scenario's start equal central differences of f."""
    plant = scenario.build().to(DT)
    x0 = torch.tensor(scenario.x0, dtype=DT)
    x = torch.stack([x0, 0.95 * x0 + 0.01, 1.05 * x0 - 0.02])
    t = torch.tensor(0.3, dtype=DT)
    u = None if scenario.u is None else scenario.u(t).reshape(1, -1).repeat(3, 1)
    a, b, _, _ = linearize(plant, x, u, t=t)

    def f():
        return plant(t, x) if u is None else plant(t, x, u)

    a_ref = central_jacobian(f, x)
    scale = 1 + float(a_ref.abs().max())
    torch.testing.assert_close(a, a_ref, rtol=0, atol=1e-8 * scale)
    if u is None:
        assert b.shape == (3, x0.numel(), 0)
    else:
        torch.testing.assert_close(b, central_jacobian(f, u), rtol=0, atol=1e-8 * scale)
