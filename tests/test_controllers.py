"""Step-size controllers, error norm and initial step (notes §6.5), checked against the
formulas written out by hand."""

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from integrators import IController, InputValidationError, PIController, odeint
from integrators.controllers import GustafssonController, error_norm, initial_step

pytestmark = pytest.mark.usefixtures("float64_default")


def test_error_norm_is_hairers_weighted_rms():
    rng = np.random.default_rng(1)
    err, xo, xn = (rng.normal(size=(5, 3)) for _ in range(3))
    rtol, atol = 1e-3, 1e-6
    expected = np.sqrt(np.mean((err / (atol + rtol * np.maximum(abs(xo), abs(xn)))) ** 2, -1))
    got = error_norm(*(torch.tensor(a) for a in (err, xo, xn)), rtol, atol)
    np.testing.assert_allclose(got.numpy(), expected, rtol=1e-13)
    # per-component tolerances broadcast
    atol_vec = torch.tensor([1e-6, 1e-3, 1.0])
    got = error_norm(*(torch.tensor(a) for a in (err, xo, xn)), rtol, atol_vec)
    expected = np.sqrt(
        np.mean((err / (atol_vec.numpy() + rtol * np.maximum(abs(xo), abs(xn)))) ** 2, -1)
    )
    np.testing.assert_allclose(got.numpy(), expected, rtol=1e-13)


def test_i_controller_formula_bounds_and_rejection():
    ctrl = IController(safety=0.9, min_factor=0.2, max_factor=10.0)
    err = torch.tensor([0.5, 2.0, 1e-30, math.nan, math.inf, 1.0])
    dt = torch.full((6,), 0.1)
    accept, new = ctrl.propose(err, torch.ones(6), dt, order=4)
    assert accept.tolist() == [True, False, True, False, False, True]
    expected = [
        0.1 * 0.9 * 0.5**-0.2,
        0.1 * 0.9 * 2.0**-0.2,
        0.1 * 10.0,  # capped by max_factor
        0.1 * 0.2,  # non-finite trial: maximal shrink
        0.1 * 0.2,
        0.1 * 0.9,
    ]
    np.testing.assert_allclose(new.numpy(), expected, rtol=1e-14)
    # right after a rejection the step may not grow
    _, new = ctrl.propose(
        torch.tensor([1e-6]),
        torch.ones(1),
        torch.tensor([0.1]),
        4,
        after_reject=torch.tensor([True]),
    )
    assert float(new[0]) == pytest.approx(0.1)


def test_pi_controller_formula():
    ctrl = PIController(beta1=0.7, beta2=-0.4, safety=0.9)
    err = torch.tensor([0.3, 3.0])
    prev = torch.tensor([0.8, 0.8])
    accept, new = ctrl.propose(err, prev, torch.tensor([1.0, 1.0]), order=4)
    assert accept.tolist() == [True, False]
    # accepted: safety * err^(-beta1/k) * prev^(-beta2/k), k = 5; rejected: I formula
    assert float(new[0]) == pytest.approx(0.9 * 0.3 ** (-0.7 / 5) * 0.8 ** (0.4 / 5), rel=1e-14)
    assert float(new[1]) == pytest.approx(0.9 * 3.0 ** (-1 / 5), rel=1e-14)


@settings(max_examples=30, deadline=None)
@given(
    err=st.floats(1e-8, 1e3),
    prev=st.floats(1e-6, 1.0),
    dt=st.floats(1e-6, 1e2),
    order=st.integers(1, 8),
)
def test_pi_with_beta_1_0_is_the_i_controller(err, prev, dt, order):
    args = (torch.tensor([err]), torch.tensor([prev]), torch.tensor([dt]), order)
    a_i, h_i = IController().propose(*args)
    a_pi, h_pi = PIController(beta1=1.0, beta2=0.0).propose(*args)
    assert bool(a_i[0]) == bool(a_pi[0]) == (err <= 1.0)
    assert float(h_pi[0]) == pytest.approx(float(h_i[0]), rel=1e-12)
    assert 0.2 * dt * (1 - 1e-12) <= float(h_i[0]) <= 10.0 * dt * (1 + 1e-12)


def test_initial_step_on_linear_equation_by_hand():
    """x' = lam x: d0 = |x0|/sc, d1 = |lam| d0, h0 = 0.01/|lam|, d2 = lam^2 d0,
    h1 = (0.01 / max(d1, d2))^(1/5), h = min(100 h0, h1)."""
    lam = torch.tensor([[-2.0], [-50.0], [0.0]])
    x0 = torch.tensor([[1.0], [3.0], [1.0]])

    def rhs(t, x):
        return lam * x

    h = initial_step(rhs, torch.zeros(3), x0, rhs(None, x0), 4, 1e-6, 1e-9, span=10.0)
    for i in range(2):
        a, x = abs(float(lam[i, 0])), float(x0[i, 0])
        d0 = x / (1e-9 + 1e-6 * x)
        h0 = 0.01 * d0 / (a * d0)
        d2 = a * a * d0
        h1 = (0.01 / max(a * d0, d2)) ** 0.2
        assert float(h[i]) == pytest.approx(min(100 * h0, h1), rel=1e-12)
    # f(x0) = 0: the probe is h0 = 1e-6 and there is no curvature, so h1 = max(1e-6, 1e-3 h0)
    assert float(h[2]) == pytest.approx(1e-6)


def test_initial_step_batch_shapes_and_no_probe():
    """The rule works on any batch shape (a (2, 3) batch gives the flat batch's steps, a
    single trajectory a 0-d step), and without a probe (DAEs) it is ``min(h0, span)`` with
    ``h0 = 0.01 d0 / d1``. Radau IIA's first step is this rule with the order s = 3 of its
    error estimate: x' = -x from 1 at rtol 1e-6, atol 1e-9 gives d0 = d1 = 1 / (1e-9 + 1e-6),
    h0 = 0.01, d2 = d1 (f changes by h0 along the probe), so h = min(1, (0.01 / d1)^(1/4));
    the run equals the one started with that step as dt0, not one started 1 % off."""
    g = torch.Generator().manual_seed(3)
    lam = -torch.rand(2, 3, 1, generator=g) * 10
    x0 = torch.randn(2, 3, 2, generator=g)

    def linear(rate):
        return lambda t, x: rate * x

    f0 = lam * x0
    h = initial_step(linear(lam), torch.zeros(2, 3), x0, f0, 4, 1e-6, 1e-9, 10.0)
    flat = initial_step(
        linear(lam.reshape(6, 1)),
        torch.zeros(6),
        x0.reshape(6, 2),
        f0.reshape(6, 2),
        4,
        1e-6,
        1e-9,
        10.0,
    )
    torch.testing.assert_close(h.reshape(6), flat, rtol=0, atol=0)
    one = initial_step(linear(lam[0, 0]), torch.zeros(()), x0[0, 0], f0[0, 0], 4, 1e-6, 1e-9, 10)
    assert one.shape == () and float(one) == float(h[0, 0])
    h_dae = initial_step(None, torch.zeros(2, 3), x0, f0, 4, 1e-6, 1e-9, 10.0)
    scale = 1e-9 + 1e-6 * x0.abs()
    d0 = (x0 / scale).square().mean(-1).sqrt()
    d1 = (f0 / scale).square().mean(-1).sqrt()
    torch.testing.assert_close(h_dae, (0.01 * d0 / d1).clamp(max=10.0))
    # Radau IIA starts with the rule's step: the same run as with that step given as dt0
    one = torch.ones(1)
    rule = float(initial_step(lambda tt, x: -x, torch.zeros(()), one, -one, 3, 1e-6, 1e-9, 1.0))
    assert rule == pytest.approx(min(1.0, (0.01 * (1e-9 + 1e-6)) ** 0.25), rel=1e-14)
    t = torch.tensor([0.0, 1.0])
    for host_loop in (False, True):
        runs = [
            odeint(
                lambda tt, x: -x,
                torch.ones(1),
                t,
                method="radau_iia",
                rtol=1e-6,
                atol=1e-9,
                host_loop=host_loop,
                **extra,
            )
            for extra in ({}, {"dt0": rule}, {"dt0": 1.01 * rule})
        ]
        assert torch.equal(runs[0].x, runs[1].x)
        assert not torch.equal(runs[0].x, runs[2].x)


def test_controller_arguments_are_validated():
    with pytest.raises(InputValidationError):
        IController(safety=0.0)
    with pytest.raises(InputValidationError):
        IController(min_factor=2.0)
    with pytest.raises(InputValidationError):
        PIController(beta1=-1.0)
    # non-finite or non-numeric gains ran 100 000 rejected steps to NaN (beta nan) or gave a
    # raw TypeError ("0.7")
    for bad in (
        {"beta1": math.nan},
        {"beta2": math.nan},
        {"beta2": -math.inf},
        {"beta1": "0.7"},
        {"max_factor": math.inf},
    ):
        with pytest.raises(InputValidationError, match="must be a finite number"):
            PIController(**bad)


@pytest.mark.parametrize("bad", ["pi", 3.0, IController, GustafssonController()])
def test_an_embedded_pair_takes_i_or_pi_controller_objects_only(bad):
    """A string, a number, the class instead of an instance, or Radau's predictive rule given
    to dopri5 is refused by name (it failed with AttributeError inside the step loop)."""
    t = torch.linspace(0, 1, 3, dtype=torch.float64)
    x0 = torch.ones(1, dtype=torch.float64)
    with pytest.raises(InputValidationError, match="controller"):
        odeint(lambda t, x: -x, x0, t, method="dopri5", controller=bad)


def test_controller_reprs_name_the_class_of_a_subclass():
    """The repr is what ``stats.extra["controller"]`` reports: a subclass names itself."""

    class Cautious(PIController):
        pass

    class Gentle(GustafssonController):
        pass

    assert repr(PIController()).startswith("PIController(beta1=")
    assert repr(Cautious()).startswith("Cautious(beta1=")
    assert repr(Gentle()).startswith("Gentle(min_factor=")
    assert repr(IController()).startswith("IController(safety=")
