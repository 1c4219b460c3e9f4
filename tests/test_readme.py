"""The README's Python code runs as printed and produces the numbers it claims.

Every fenced ``python`` block of ``README.md`` is executed in order in one fresh namespace
(as a user pasting the quick start into a file would). The quick start's estimates are
checked against the exact zero-order-hold discretisation of the continuous spring-mass-damper
m y'' + xi y' + K y = u (the course notes Modelling and Simulation, eq. 1.26-1.28 and 1.55),
computed here independently with scipy.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
import scipy.signal
import torch

README = Path(__file__).resolve().parents[1] / "README.md"
BLOCK = re.compile(r"^```python\n(.*?)^```$", re.DOTALL | re.MULTILINE)
SHOWN_OUTPUT = re.compile(r"^```python\n.*?^```$.*?^```text\n(.*?)^```$", re.DOTALL | re.MULTILINE)
NUMBER = re.compile(r"[-+]?\d+\.\d+")


def python_blocks(text: str) -> list[str]:
    """Source of every fenced ```python block, in order."""
    return BLOCK.findall(text)


def exact_oe_parameters(m: float, xi: float, K: float, Ts: float) -> dict[str, float]:
    """b1, b2, f1, f2 of y = (b1 q^-1 + b2 q^-2) / (1 + f1 q^-1 + f2 q^-2) u: the ZOH
    discretisation of x = (y, y'), x' = [[0, 1], [-K/m, -xi/m]] x + [0, 1/m]' u."""
    A = np.array([[0.0, 1.0], [-K / m, -xi / m]])
    B = np.array([[0.0], [1.0 / m]])
    C = np.array([[1.0, 0.0]])
    Ad, Bd, Cd, Dd, _ = scipy.signal.cont2discrete((A, B, C, np.zeros((1, 1))), Ts, method="zoh")
    num, den = scipy.signal.ss2tf(Ad, Bd, Cd, Dd)
    num = num[0] / den[0]
    den = den / den[0]
    assert abs(num[0]) < 1e-14  # strictly proper: one sample of delay (nk = 1)
    return {"b1": num[1], "b2": num[2], "f1": den[1], "f2": den[2]}


@pytest.fixture(scope="module")
def quick_start():
    """Namespace and printed output of the README's Python blocks run in sequence."""
    blocks = python_blocks(README.read_text())
    assert blocks, "README.md has no ```python block (the quick start)"
    namespace: dict = {"__name__": "__readme__"}
    printed: list[str] = []
    namespace["print"] = lambda *args, **kw: printed.append(" ".join(map(str, args)))
    with torch.random.fork_rng():
        for source in blocks:
            exec(compile(source, str(README), "exec"), namespace)
    return namespace, "\n".join(printed)


def test_quick_start_is_short():
    blocks = python_blocks(README.read_text())
    assert blocks
    assert len(blocks[0].strip().splitlines()) <= 25


def test_quick_start_estimates_match_the_exact_discretisation(quick_start):
    ns, _ = quick_start
    plant, Ts = ns["plant"], ns["Ts"]
    truth = exact_oe_parameters(*(float(p.detach()) for p in (plant.m, plant.xi, plant.K)), Ts)
    result = ns["result"]
    assert result.parameter_names == ["b1", "b2", "f1", "f2"]
    true_theta = torch.tensor([truth[name] for name in result.parameter_names])
    theta, se = ns["theta"].double(), ns["se"].double()
    assert theta.shape == se.shape == (4,)
    assert bool(result.converged) and bool(result.stable)
    # Standard errors of the right size: N = 1000 samples, noise std 0.02 give SEs of 1e-4..1e-3
    assert bool(((se > 1e-5) & (se < 1e-2)).all()), se
    normalised = (theta - true_theta) / se
    assert bool((normalised.abs() < 4).all()), normalised


def test_quick_start_validation(quick_start):
    ns, out = quick_start
    assert 80.0 < ns["fit"] <= 100.0
    white = ns["white"]
    assert white.independent is not None
    assert bool(white.passed)
    # The printed estimates: one line "name = value ± error" per parameter, then the fit
    lines = out.splitlines()
    for name, value, error in zip(ns["result"].parameter_names, ns["theta"], ns["se"], strict=True):
        line = next(line for line in lines if line.startswith(f"{name} = "))
        shown_value, shown_error = map(float, line.split("=")[1].split("±"))
        assert shown_value == pytest.approx(float(value), abs=1e-5)
        assert shown_error == pytest.approx(float(error), abs=1e-5)
    assert f"validation fit {ns['fit']:.1f} %" in out


def test_output_shown_in_the_readme_is_what_the_quick_start_prints(quick_start):
    """The ```text block after the quick start: same lines, numbers to their last digit."""
    _, out = quick_start
    match = SHOWN_OUTPUT.search(README.read_text())
    assert match, "README.md shows no output of the quick start (a ```text block after it)"
    shown, printed = match.group(1).strip().splitlines(), out.strip().splitlines()
    assert len(shown) == len(printed)
    for shown_line, printed_line in zip(shown, printed, strict=True):
        assert NUMBER.sub("#", shown_line) == NUMBER.sub("#", printed_line)
        for a, b in zip(NUMBER.findall(shown_line), NUMBER.findall(printed_line), strict=True):
            digits = len(a.split(".")[1])
            assert float(a) == pytest.approx(float(b), abs=1.01 * 10.0**-digits), printed_line


def test_monte_carlo_study_example(quick_start):
    """The study example: unbiased FIR least squares, std ~ N^(-1/2), 95 % coverage
    (400 trials: binomial spread 0.011)."""
    ns, _ = quick_start
    table, slopes = ns["table"], ns["slopes"]
    assert len(table) == 4 and (table["trials"] == 400).all()
    assert (table["bias"].abs() < 4 * table["bias_se"]).all()
    assert (table["coverage"] - 0.95).abs().max() < 0.05
    assert (slopes["std_slope"] + 0.5).abs().max() < 0.15


def test_identify_your_own_plant_recovers_the_pendulum(quick_start):
    """The grey-box example: every record's g/L and damping within 4 standard errors of the
    values that simulated it, each fit converged."""
    namespace, _ = quick_start
    estimate = namespace["estimate"]
    truth = torch.tensor([9.81, 0.3], dtype=torch.float64)
    assert estimate.parameter_names == ["g_over_L", "d"]
    assert bool(estimate.converged.all())
    assert bool(((estimate.theta - truth).abs() <= 4 * estimate.standard_errors).all())
