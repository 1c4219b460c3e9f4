"""method="auto": stiffness estimate from the spectral radius of df/dx (notes §6.4, §7.1.1)."""

import pytest
import torch

from integrators import InputValidationError, odeint
from integrators.auto import choose_method
from sysid.zoo import StiffLinear

pytestmark = pytest.mark.usefixtures("float64_default")


def test_spectral_radius_is_the_largest_eigenvalue_modulus():
    plant = StiffLinear(eps=5e-4)
    x0 = torch.ones(3, 4)
    t = torch.linspace(0, 1, 11)
    name, info = choose_method(plant, x0, t)
    eig = torch.linalg.eigvals(plant.matrix().detach()).abs().max()
    assert info["spectral_radius"] == pytest.approx(float(eig), rel=1e-10)
    assert info["typical_step"] == pytest.approx(0.1)
    assert name == "radau_iia" and info["stiffness"] > info["threshold"]
    assert "stiff" in info["reason"]


@pytest.mark.parametrize("lam,expected", [(-1.0, "dopri5"), (-2.0e3, "radau_iia")])
def test_choice_follows_lambda_dt_against_explicit_stability(lam, expected):
    t = torch.linspace(0, 1, 101)  # dt = 0.01: |lambda dt| = 0.01 vs 20
    name, info = choose_method(lambda t, x: lam * x, torch.ones(2, 1), t)
    assert name == expected
    assert info["stiffness"] == pytest.approx(abs(lam) * 0.01)


def test_odeint_auto_records_choice_and_solves_stiff_problem():
    lam = -2.0e3
    t = torch.linspace(0, 1, 11)
    x0 = torch.tensor([[1.0], [2.0]])
    sol = odeint(lambda t, x: lam * (x - torch.cos(t)), x0, t, method="auto", rtol=1e-8, atol=1e-10)
    assert sol.stats.extra["auto"]["method"] == "radau_iia"
    # closed form of x' = lam (x - cos t)
    c = lam * lam / (lam * lam + 1)
    particular = c * (torch.cos(t) - torch.sin(t) / lam)
    exact = particular + (x0 - c) * torch.exp(lam * t)
    assert float((sol.x[..., 0] - exact).abs().max()) < 1e-6


@pytest.mark.parametrize("lam,expected", [(-1.0, "dopri5"), (-2.0e3, "radau_iia")])
def test_implicit_solver_options_are_accepted_whichever_method_is_picked(lam, expected):
    """A call with Radau's options (host_loop, max_iter) is valid or not regardless of the
    stiffness estimate: dopri5 leaves them unused and says so, Radau IIA uses them; a
    misspelt option is refused for both. Before, the same call raised when dopri5 was picked.
    The closed form of x' = lam x checks both runs."""
    t = torch.linspace(0, 1, 101)
    x0 = torch.ones(2, 1)
    sol = odeint(
        lambda t, x: lam * x,
        x0,
        t,
        method="auto",
        rtol=1e-9,
        atol=1e-12,
        host_loop=False,
        max_iter=10,
    )
    auto = sol.stats.extra["auto"]
    assert auto["method"] == expected
    assert auto["unused_options"] == (["host_loop", "max_iter"] if expected == "dopri5" else [])
    if expected == "radau_iia":
        assert sol.stats.extra["driver"] == "torch"  # host_loop=False was applied
    torch.testing.assert_close(
        sol.x[..., 0], torch.exp(lam * t).expand(2, -1), rtol=1e-6, atol=1e-9
    )
    with pytest.raises(InputValidationError, match="unknown option.*max_iters"):
        odeint(lambda t, x: lam * x, x0, t, method="auto", max_iters=10)
