"""Long-rollout diagnostics (``sysid.rollout_diagnostics``) against closed forms."""

import math

import pytest
import torch

from integrators.errors import InputValidationError
from sysid import rollout_diagnostics

DT = torch.float64


def oscillator(w: float):
    """x1' = x2, x2' = -w^2 x1 (a harmonic oscillator of angular frequency w)."""

    def f(t, x):
        return torch.stack([x[..., 1], -(w**2) * x[..., 0]], -1)

    return f


def energy(x):
    return 0.5 * (x[..., 0] ** 2 + x[..., 1] ** 2)


def test_error_and_floor_of_a_detuned_oscillator_match_the_closed_form():
    """Truth w = 1 from (1, 0): (cos t, -sin t); model w = 1.1: (cos wt, -w sin wt). The floor
    of the rotation from x0 + delta (1, 1) stays delta sqrt(2)."""
    t = torch.linspace(0.0, 20.0, 201, dtype=DT)
    x0 = torch.tensor([1.0, 0.0], dtype=DT)
    w = 1.1
    d = rollout_diagnostics(oscillator(w), oscillator(1.0), x0, t, substeps=20)
    want = torch.sqrt(
        (torch.cos(w * t) - torch.cos(t)) ** 2 + (w * torch.sin(w * t) - torch.sin(t)) ** 2
    )
    torch.testing.assert_close(d.error, want, rtol=0, atol=1e-6)
    torch.testing.assert_close(d.floor, torch.full_like(t, 1e-4 * math.sqrt(2)), rtol=1e-7, atol=0)
    torch.testing.assert_close(d.x_true[:, 0], torch.cos(t), rtol=0, atol=1e-7)
    assert d.energy is None
    s = d.summary()
    assert set(s) == {"rms_error", "final_error", "rms_floor", "error_over_floor"}
    torch.testing.assert_close(s["rms_error"], want.square().mean().sqrt(), rtol=1e-6, atol=0)
    torch.testing.assert_close(s["error_over_floor"], s["rms_error"] / s["rms_floor"])


def test_energy_drift_of_explicit_euler_is_the_closed_form():
    """Explicit Euler on the oscillator multiplies |x|^2 by exactly 1 + h^2 per step, so the
    relative energy drift after k steps is (1 + h^2)^k - 1; the exact flow keeps E."""
    h = 0.05
    t = h * torch.arange(101, dtype=DT)
    x0 = torch.tensor([[1.0, 0.5], [0.0, 2.0]], dtype=DT)
    f = oscillator(1.0)
    d = rollout_diagnostics(f, f, x0, t, energy=energy, method="euler")
    want = (1 + h * h) ** torch.arange(101, dtype=DT) - 1
    torch.testing.assert_close(d.energy, want.expand(2, -1), rtol=1e-12, atol=1e-15)
    torch.testing.assert_close(d.summary()["energy_drift"], want[-1].expand(2))
    exact = rollout_diagnostics(f, f, x0, t, energy=energy, substeps=10)
    assert exact.summary()["energy_drift"].max() < 1e-9
    assert exact.summary()["rms_error"].max() < 1e-7  # rk4 at h and h/10 on the same flow


def test_a_forced_system_takes_its_input():
    """x' = -x + u, u = 1 held: x = 1 - (1 - x0) e^{-t}; model = truth."""
    t = torch.linspace(0.0, 3.0, 31, dtype=DT)
    u = torch.ones(31, 1, dtype=DT)

    def f(t, x, u):
        return -x + u

    d = rollout_diagnostics(f, f, torch.tensor([0.2], dtype=DT), t, u=u, substeps=5)
    torch.testing.assert_close(d.x_true[:, 0], 1 - 0.8 * torch.exp(-t), rtol=0, atol=1e-9)
    torch.testing.assert_close(d.floor, 1e-4 * torch.exp(-t), rtol=1e-6, atol=0)
    assert d.summary()["rms_error"] < 1e-7


def test_bad_input_is_refused_by_name():
    t = torch.linspace(0.0, 1.0, 5, dtype=DT)
    x0 = torch.tensor([1.0, 0.0], dtype=DT)
    f = oscillator(1.0)
    with pytest.raises(InputValidationError, match="perturbation"):
        rollout_diagnostics(f, f, x0, t, perturbation=0.0)
    with pytest.raises(InputValidationError, match="one value per state"):
        rollout_diagnostics(f, f, x0, t, energy=lambda x: x)
    with pytest.raises(InputValidationError, match="zero at x0"):
        rollout_diagnostics(f, f, torch.zeros(2, dtype=DT), t, energy=energy)
