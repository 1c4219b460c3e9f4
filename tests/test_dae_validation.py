"""daeint's entry checks (widths, batch shapes, finiteness of the model at t0, degenerate
sizes) and the classification of failures (finite escape vs. loss of index 1)."""

import math
import re
import warnings

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from integrators import (
    HighIndexWarning,
    ImplicitDAE,
    ImplicitODE,
    InputValidationError,
    SemiExplicitDAE,
    Status,
    daeint,
)

pytestmark = pytest.mark.usefixtures("float64_default")

T = torch.linspace(0, 1, 3)


def _semi(f_width=None, g_width=None):
    """x' = -x (+ sum z), 0 = z - x; f or g padded/truncated to the given width."""

    def f(t, x, z):
        out = -x + z.sum(-1, keepdim=True)
        return out if f_width is None else out[..., :1].expand(*x.shape[:-1], f_width)

    def g(t, x, z):
        out = z - x[..., :1]
        return out if g_width is None else out[..., :1].expand(*z.shape[:-1], g_width)

    return SemiExplicitDAE(f, g)


@pytest.mark.parametrize(
    "call, words",
    [
        (
            lambda: daeint(_semi(g_width=2), torch.ones(2, 1), torch.ones(2, 1), T),
            ["g(t, x, z) returned width 2", "z0 has width 1", "one residual per algebraic"],
        ),
        (
            lambda: daeint(_semi(g_width=1), torch.ones(2, 1), torch.ones(2, 2), T),
            ["g(t, x, z) returned width 1", "z0 has width 2"],
        ),
        (
            lambda: daeint(_semi(f_width=3), torch.ones(2, 1), torch.ones(2, 1), T),
            ["f(t, x, z) returned width 3", "x0 has width 1"],
        ),
        (
            lambda: daeint(
                SemiExplicitDAE(
                    lambda t, x, z, u: -x + u, lambda t, x, z, u: torch.cat([z, z], -1)
                ),
                torch.ones(2, 1),
                torch.ones(2, 1),
                T,
                u=torch.ones(3, 1),
            ),
            ["g(t, x, z, u) returned width 2", "z0 has width 1"],
        ),
        (
            lambda: daeint(_semi(), torch.ones(2, 1), torch.ones(3, 1), T),
            ["z0 has batch shape (3,)", "x0 has (2,)"],
        ),
        (
            lambda: daeint(
                ImplicitODE(lambda t, xd, x: torch.cat([xd + x, x], -1)), torch.ones(2, 1), None, T
            ),
            ["F(t, xdot, x) returned width 2", "x0 has width 1"],
        ),
        (
            lambda: daeint(
                ImplicitDAE(lambda t, xd, x, z: xd + x), torch.ones(2, 1), torch.ones(2, 1), T
            ),
            ["F(t, xdot, x, z) returned width 1", "widths 1 + 1", "(2)"],
        ),
        (
            lambda: daeint(
                SemiExplicitDAE(lambda t, x, z: -x, lambda t, x, z: z - torch.sqrt(x - 2)),
                torch.tensor([[3.0], [1.0]]),
                torch.ones(2, 1),
                T,
            ),
            ["g(t, x, z) returned inf/nan", "sample (1,)"],
        ),
        (
            lambda: daeint(
                SemiExplicitDAE(lambda t, x, z: -x, lambda t, x, z: z),
                torch.ones(2, 1),
                torch.ones(2, 0),
                T,
            ),
            ["at least one algebraic state", "odeint"],
        ),
        (
            lambda: daeint(
                ImplicitDAE(lambda t, xd, x, z: xd + x), torch.ones(2, 1), torch.ones(2, 0), T
            ),
            ["at least one algebraic state", "ImplicitODE"],
        ),
        (
            lambda: daeint(
                SemiExplicitDAE(lambda t, x, z: x, lambda t, x, z: z - torch.cos(t)),
                torch.ones(2, 0),
                torch.zeros(2, 1),
                T,
            ),
            ["x0 has width 0", "adaptive=False"],
        ),
        (
            lambda: daeint(_semi(), torch.ones(2, 1), torch.ones(2, 1), T, u=torch.ones(3, 1)),
            ["calling the model as f(t, x, z, u) failed", "takes 3 positional", "receives u"],
        ),
        (
            lambda: daeint(
                ImplicitDAE(lambda t, xd, x, z: torch.cat([xd + x, z - x], -1)),
                torch.ones(2, 1),
                torch.ones(2, 1),
                T,
                u=torch.ones(3, 1),
            ),
            ["calling the model as F(t, xdot, x, z, u) failed", "receives u"],
        ),
        (
            lambda: daeint(
                SemiExplicitDAE(lambda t, x, z: -z, lambda t, x, z: z > x),
                torch.ones(2, 1),
                torch.ones(2, 1),
                T,
            ),
            ["g(t, x, z) returned a torch.bool tensor", "floating-point"],
        ),
        (
            lambda: daeint(
                SemiExplicitDAE(lambda t, x, z: -z, lambda t, x, z: (z - x).long()),
                torch.ones(2, 1),
                torch.ones(2, 1),
                T,
            ),
            ["g(t, x, z) returned a torch.int64 tensor", "floating-point"],
        ),
        (
            lambda: daeint(
                SemiExplicitDAE(lambda t, x, z: -z, lambda t, x, z: (z - x).detach()),
                torch.ones(2, 1),
                torch.ones(2, 1),
                T,
            ),
            ["g(t, x, z) returned a tensor without autograd graph", "numpy"],
        ),
        (
            lambda: daeint(
                ImplicitODE(lambda t, xd, x: torch.tensor((xd + x).detach().numpy())),
                torch.ones(2, 1),
                None,
                T,
            ),
            ["F(t, xdot, x) returned a tensor without autograd graph"],
        ),
    ],
)
def test_daeint_entry_checks_name_the_function_and_the_shapes(call, words):
    with pytest.raises(InputValidationError) as info:
        call()
    for w in words:
        assert w in str(info.value), str(info.value)


@settings(max_examples=15, deadline=None)
@given(n=st.integers(1, 3), m=st.integers(1, 3), extra=st.integers(-2, 2))
def test_wrong_residual_width_is_named_for_every_size(n, m, extra):
    """g returning m + extra residuals (extra != 0) is reported with both widths; extra = 0 runs."""
    w = max(m + extra, 1)

    def g(t, x, z):  # z - 1, truncated or padded with copies of its first entry to width w
        r = z - 1
        return r[..., :w] if w <= m else torch.cat([r, r[..., :1].expand(*r.shape[:-1], w - m)], -1)

    prob = SemiExplicitDAE(lambda t, x, z: -x, g)
    x0, z0 = torch.ones(2, n), torch.ones(2, m)
    if w == m:
        sol = daeint(prob, x0, z0, T, adaptive=False, substeps=8)
        torch.testing.assert_close(
            sol.x[:, -1], torch.full((2, n), math.exp(-1)), atol=1e-6, rtol=0
        )
        return
    with pytest.raises(InputValidationError, match=rf"returned width {w} .* z0 has width {m}"):
        daeint(prob, x0, z0, T, adaptive=False)


def test_purely_algebraic_problem_on_fixed_steps_solves_g():
    """nx = 0: 0 = z - cos t is solved at every step (z = cos t exactly)."""
    t = torch.linspace(0, 2, 9)
    prob = SemiExplicitDAE(lambda t, x, z: x, lambda t, x, z: z - torch.cos(t))
    sol = daeint(prob, torch.ones(2, 0), torch.zeros(2, 1), t, adaptive=False)
    assert sol.success
    torch.testing.assert_close(sol.z[..., 0], torch.cos(t).expand(2, -1), rtol=0, atol=1e-12)


def test_inconsistent_z0_report_names_the_corrected_samples():
    """0 = z - x with z0 = x0 for sample 0 and z0 = x0 + 0.5 for sample 1: only sample 1 is
    reported, with its correction 0.5."""
    prob = SemiExplicitDAE(lambda t, x, z: -x, lambda t, x, z: z - x)
    sol = daeint(prob, torch.ones(2, 1), torch.tensor([[1.0], [1.5]]), T)
    corr = sol.stats.extra["z0_correction"]
    assert float(corr[0]) == 0.0 and float(corr[1]) == pytest.approx(0.5, abs=1e-12)
    (msg,) = [m for m in sol.messages if "inconsistent" in m]
    assert "1 sample(s) [(1,)]" in msg and "0.5" in msg and "at sample (1,)" in msg, msg


def _stop_time(msg):
    return float(re.search(r"at t = ([0-9.e+-]+)", msg).group(1))


@pytest.mark.parametrize(
    "prob",
    [
        SemiExplicitDAE(lambda t, x, z: x**2, lambda t, x, z: z - x),
        SemiExplicitDAE(lambda t, x, z: x**2, lambda t, x, z: z - x**3),
        ImplicitDAE(lambda t, xd, x, z: torch.cat([xd - x**2, z - x], -1)),
    ],
    ids=["z=x", "z=x^3", "implicit"],
)
def test_finite_escape_is_non_finite_not_high_index(prob):
    """x' = x^2, x(0) = 1 (notes eq. 1.44) escapes at t = 1 (x = 1 / (1 - t)); dg/dz = 1 is
    regular throughout. Adaptive Radau IIA to t = 2 with the index re-checked at every step:
    NON_FINITE at t ~ 1, no HighIndexWarning and no index message (before: a HighIndexWarning
    for z = x^3 and the implicit form, whose dg/dx grows with x, and an "index > 1" hint in the
    STEP_TOO_SMALL message for z = x); x matches 1 / (1 - t) before the escape."""
    t = torch.linspace(0, 2, 21)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        sol = daeint(prob, torch.ones(1, 1), torch.ones(1, 1), t, index_check_every=1)
    assert not any(issubclass(w.category, HighIndexWarning) for w in caught)
    assert sol.status.tolist() == [Status.NON_FINITE]
    assert not any("index" in m for m in sol.messages), sol.messages
    (msg,) = sol.messages
    assert "sample (0,)" in msg and "escapes to infinity" in msg
    assert _stop_time(msg) == pytest.approx(1.0, abs=1e-6)
    before = t < 0.95
    torch.testing.assert_close(sol.x[0, before, 0], 1 / (1 - t[before]), rtol=1e-4, atol=0)
