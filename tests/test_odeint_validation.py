"""odeint (contract C4): every invalid input raises a clear error from the hierarchy, and the
method dispatch reaches the right solver (checked against closed forms)."""

import math

import numpy as np
import pytest
import torch

from integrators import InputValidationError, TableauError, gauss_legendre, odeint, tableau
from integrators.errors import RKIdentError

T = torch.linspace(0, 1, 5, dtype=torch.float64)
X0 = torch.ones(2, 1, dtype=torch.float64)


def decay(t, x):
    return -x


@pytest.mark.parametrize(
    "x0, match",
    [
        (torch.tensor(1.0, dtype=torch.float64), r"shape \(\*batch, nx\)"),
        (torch.zeros(3, 0, dtype=torch.float64), r"nx >= 1"),
        (torch.tensor([1.0 + 1j]), "real floating point"),
        (torch.tensor([[1.0], [float("nan")]], dtype=torch.float64), r"sample index \(1,\)"),
        ("abc", "not numeric"),
    ],
)
def test_bad_x0(x0, match):
    with pytest.raises(InputValidationError, match=match):
        odeint(decay, x0, T)


@pytest.mark.parametrize(
    "t, match",
    [
        (torch.zeros(2, 3), "1-D"),
        (torch.tensor([0.0]), "T >= 2"),
        (torch.tensor([0.0, 0.5, 0.5, 1.0]), r"strictly increasing, but t\[2\]"),
        (torch.tensor([0.0, 1.0, 0.5]), r"t\[2\] = 0.5 <= t\[1\] = 1.0"),
        (torch.tensor([0.0, float("inf")]), "non-finite"),
    ],
)
def test_bad_t(t, match):
    with pytest.raises(InputValidationError, match=match):
        odeint(decay, X0, t)


def test_non_finite_input_names_time_index():
    u = torch.zeros(5, 1, dtype=torch.float64)
    u[3] = float("nan")
    with pytest.raises(InputValidationError, match="time index 3"):
        odeint(lambda t, x, u: -x + u, X0, T, u=u)


def test_model_output_checks():
    with pytest.raises(InputValidationError, match=r"returned shape \(2, 2\)"):
        odeint(lambda t, x: torch.cat([x, x], dim=-1), X0, T)
    with pytest.raises(InputValidationError, match="must return a tensor"):
        odeint(lambda t, x: 1.0, X0, T)
    with pytest.raises(InputValidationError, match="dtype"):
        odeint(lambda t, x: -x.float(), X0, T)
    with pytest.raises(InputValidationError, match="non-finite at the initial time"):
        odeint(lambda t, x: x / 0.0, X0, T)
    with pytest.raises(InputValidationError, match=r"f\(t, x, u\)"):
        odeint(decay, X0, T, u=torch.zeros(5, 1, dtype=torch.float64))


@pytest.mark.parametrize(
    "kwargs, error, match",
    [
        (dict(method="rk5"), TableauError, "unknown method 'rk5'"),
        (dict(method=3), TableauError, "unknown method"),
        (dict(substeps=0), InputValidationError, "substeps"),
        (dict(substeps=1.5), InputValidationError, "substeps"),
        (dict(rtol=-1.0), InputValidationError, "rtol"),
        (dict(rtol=0.0, atol=0.0), InputValidationError, "both be zero"),
        (dict(max_steps=0), InputValidationError, "max_steps"),
        (dict(compile="yes"), InputValidationError, "compile"),
        (dict(method="rk4", adaptive=True), TableauError, "no embedded weights"),
        (dict(method="rk4", newton_tol=1e-3), InputValidationError, "unexpected keyword"),
        (dict(interpolation="spline", u=torch.zeros(5, 1)), InputValidationError, "interp"),
    ],
)
def test_bad_options(kwargs, error, match):
    f = decay if "u" not in kwargs else (lambda t, x, u: -x)
    with pytest.raises(error, match=match):
        odeint(f, X0, T, **kwargs)


def test_errors_belong_to_hierarchy_and_value_error():
    with pytest.raises(RKIdentError):
        odeint(decay, X0, torch.tensor([1.0, 0.0]))
    with pytest.raises(ValueError):
        odeint(decay, X0, torch.tensor([1.0, 0.0]))


def test_array_likes_become_float64_and_t_follows_x0():
    sol = odeint(decay, [[1.0], [2.0]], [0.0, 0.5, 1.0], substeps=10)
    assert sol.x.dtype == torch.float64 and sol.t.dtype == torch.float64
    np.testing.assert_allclose(
        sol.x[:, :, 0].numpy(), np.outer([1.0, 2.0], np.exp(-np.array([0, 0.5, 1.0]))), atol=1e-8
    )
    sol32 = odeint(decay, torch.ones(1, dtype=torch.float32), torch.tensor([0.0, 1.0]))
    assert sol32.t.dtype == torch.float32


def test_dispatch_dopri5_adaptive_and_fixed():
    """'dopri5' is adaptive by default; adaptive=False runs it at fixed step (6 f-evals/step)."""
    t = torch.linspace(0, 2, 5, dtype=torch.float64)
    x0 = torch.tensor([[1.0], [3.0]], dtype=torch.float64)
    exact = x0[:, None] * torch.exp(-t)[None, :, None]
    fixed = odeint(decay, x0, t, method="dopri5", adaptive=False, substeps=5)
    assert fixed.stats.n_f_evals == 4 * 5 * 6
    torch.testing.assert_close(fixed.x, exact, rtol=1e-8, atol=0)
    adaptive = odeint(decay, x0, t, method=tableau("dopri5"), rtol=1e-9, atol=1e-12)
    torch.testing.assert_close(adaptive.x, exact, rtol=1e-7, atol=0)
    assert adaptive.success


def test_dispatch_implicit_methods():
    """Implicit tableaus and collocation names reach the implicit solver (contract C3)."""
    pytest.importorskip("integrators.implicit")
    lam = -50.0
    t = torch.linspace(0, 0.2, 3, dtype=torch.float64)
    x0 = torch.ones(1, 1, dtype=torch.float64)
    sol = odeint(lambda t, x: lam * x, x0, t, method="implicit_euler", substeps=10, adaptive=False)
    h = 0.01  # implicit Euler: x_{k+1} = x_k / (1 - lam h)
    torch.testing.assert_close(sol.x[0, -1, 0], torch.tensor((1 / (1 - lam * h)) ** 20).double())
    sol = odeint(lambda t, x: lam * x, x0, t, method="gauss_legendre", stages=2, substeps=4)
    growth = gauss_legendre(2).stability_function(lam * 0.025).real  # one step: R(lam h)
    assert abs(float(sol.x[0, -1, 0]) - growth**8) < 1e-10
    assert sol.x[0, -1, 0] == pytest.approx(math.exp(lam * 0.2), abs=1e-3)


def test_dispatch_auto_records_the_choice():
    """method="auto" asks integrators.auto (contract C3) and records its choice."""
    pytest.importorskip("integrators.auto")
    t = torch.linspace(0, 1, 11, dtype=torch.float64)
    x0 = torch.ones(2, 1, dtype=torch.float64)
    sol = odeint(decay, x0, t, method="auto")
    assert sol.stats.extra["auto"]["method"] == "dopri5"
    torch.testing.assert_close(sol.x[:, :, 0], torch.exp(-t).expand(2, -1), rtol=1e-6, atol=0)
    # stiff relaxation to cos(t): x = cos t + O(1/lam) once the transient has decayed
    lam = 1e4
    sol = odeint(lambda t, x: -lam * (x - torch.cos(t)), x0, t, method="auto")
    assert sol.stats.extra["auto"]["method"] == "radau_iia"
    assert sol.success
    assert (sol.x[:, 1:, 0] - torch.cos(t[1:])).abs().max() < 1e-3
