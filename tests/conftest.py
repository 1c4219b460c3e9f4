"""Shared fixtures. Global torch state (default dtype) is restored after every test, and
dynamo's compile caches are reset before every test module."""

import contextlib
import functools
import math
import os

import numpy as np
import pytest
import torch
from scipy.integrate import solve_ivp

if os.environ.get("PYTEST_XDIST_WORKER"):
    # one torch thread per pytest-xdist worker: the workers already share the cores
    torch.set_num_threads(1)


@pytest.fixture(autouse=True, scope="module")
def fresh_dynamo():
    """Reset dynamo before each test module, so the graphs compiled by one module (the
    correctness matrix compiles every zoo plant) do not count against dynamo's process-wide
    limits (``accumulated_recompile_limit``) in the modules after it."""
    torch._dynamo.reset()
    yield


@pytest.fixture(autouse=True)
def eager_unless_asked(monkeypatch):
    """The solvers compile only when a test asks (``compile=True`` or a lowered threshold):
    ``compile="auto"`` would otherwise compile every model a test module simulates or fits
    long enough, for every batch shape, at seconds each. The compiled chunks and kernels are
    checked against the eager ones in tests/test_correctness_matrix.py,
    tests/test_explicit.py and tests/test_compiled_sensitivities.py."""
    import importlib

    module = importlib.import_module("integrators._fast.compiled")
    monkeypatch.setattr(module, "AUTO_COMPILE_EAGER_SECONDS", math.inf)


@pytest.fixture
def float64_default():
    """Run a test with float64 as torch's default dtype, restoring the previous default."""
    previous = torch.get_default_dtype()
    torch.set_default_dtype(torch.float64)
    yield
    torch.set_default_dtype(previous)


def _central_difference(loss, tensor: torch.Tensor, h: float = 1e-6) -> torch.Tensor:
    """d loss() / d tensor by central differences, shape of ``tensor``: each entry is moved by
    +-h in place (under no_grad) and restored, so it works for parameters and for leaf inputs
    that ``loss`` reads from its closure."""
    grad = torch.zeros_like(tensor)
    with torch.no_grad():
        flat, out = tensor.view(-1), grad.view(-1)
        for i in range(flat.numel()):
            flat[i] += h
            up = loss()
            flat[i] -= 2 * h
            down = loss()
            flat[i] += h
            out[i] = (up - down) / (2 * h)
    return grad


@pytest.fixture
def central_difference():
    """The function ``central_difference(loss, tensor, h=1e-6)`` (finite-difference truth)."""
    return _central_difference


def _central_jacobian(fun, tensor: torch.Tensor, h: float = 1e-6) -> torch.Tensor:
    """d fun() / d tensor by central differences for batched points: ``tensor`` (*batch, n),
    ``fun() -> (*batch, m)`` with members that do not interact; column j moves every
    member's entry j by +-h (1 + max |entry j|) in place (under no_grad) and is restored.
    Returns (*batch, m, n)."""
    columns = []
    with torch.no_grad():
        for j in range(tensor.shape[-1]):
            step = h * (1 + float(tensor[..., j].abs().max()))
            tensor[..., j] += step
            up = fun()
            tensor[..., j] -= 2 * step
            down = fun()
            tensor[..., j] += step
            columns.append((up - down) / (2 * step))
    return torch.stack(columns, -1)


@pytest.fixture
def central_jacobian():
    """The function ``central_jacobian(fun, tensor, h=1e-6)`` (finite-difference truth for
    the Jacobian of batched points)."""
    return _central_jacobian


def _stiff_vdp_reference(eps: float, t_end: float, y0=(2.0, 0.0)):
    """y(t_end) of y1' = y2, y2' = ((1 - y1^2) y2 - y1) / eps by scipy Radau at rtol = atol =
    1e-12 (the independent reference of the stiff Van der Pol tests): numpy array (2,).
    Computed once per session and argument set (eps = 1e-6 takes seconds)."""
    return _stiff_vdp_reference_cached(float(eps), float(t_end), tuple(map(float, y0))).copy()


@functools.cache
def _stiff_vdp_reference_cached(eps: float, t_end: float, y0: tuple):
    ref = solve_ivp(
        lambda t, y: [y[1], ((1 - y[0] ** 2) * y[1] - y[0]) / eps],
        (0.0, t_end),
        list(y0),
        method="Radau",
        rtol=1e-12,
        atol=1e-12,
    )
    return ref.y[:, -1]


@pytest.fixture
def stiff_vdp_reference():
    """The function ``stiff_vdp_reference(eps, t_end, y0=(2, 0))`` (scipy Radau at 1e-12)."""
    return _stiff_vdp_reference


def _accepted_grid(start, h, n_steps: int, t_end: float) -> torch.Tensor:
    """The (n_steps + 1,) time grid of an adaptive run's accepted steps (step starts ``start``,
    sizes ``h``, numpy), checked to be contiguous from 0 and to end at ``t_end``."""
    assert len(start) == n_steps and start[0] == 0.0
    np.testing.assert_array_equal(start[1:], start[:-1] + h[:-1])
    assert start[-1] + h[-1] == pytest.approx(t_end, abs=1e-14)
    return torch.tensor(np.append(start, t_end))


def _same_values_and_gradients(x_a, x_b, loss, params, x_rtol=1e-12, g_rtol=1e-10):
    """Assert that two end states (e.g. an adaptive run and the same method at fixed steps on
    its accepted step grid) agree to ``x_rtol`` and that ``loss(x)``'s gradients w.r.t.
    ``params`` agree to ``g_rtol`` (relative to the largest entry). Returns the gradients of
    ``loss(x_b)``."""
    g_a = torch.autograd.grad(loss(x_a), params)
    g_b = torch.autograd.grad(loss(x_b), params)
    x_a, x_b = x_a.detach(), x_b.detach()
    assert float((x_a - x_b).abs().max() / x_b.abs().max()) < x_rtol
    for a, b in zip(g_a, g_b, strict=True):
        assert float((a - b).abs().max() / b.abs().max()) < g_rtol
    return g_b


@pytest.fixture
def accepted_grid():
    """``accepted_grid(start, h, n_steps, t_end)``: the checked time grid of accepted steps."""
    return _accepted_grid


@pytest.fixture
def same_values_and_gradients():
    """``same_values_and_gradients(x_a, x_b, loss, params)``: values and gradients agree;
    returns the gradients of ``loss(x_b)``."""
    return _same_values_and_gradients


@contextlib.contextmanager
def recorded_figures():
    """Within the block, every matplotlib figure saved is recorded in the yielded dict, by
    file name (e.g. ``"regions.png"``), for checks on its axes, lines and legends
    (``experiments._common.figure_defects``); usable by module-scoped fixtures."""
    from matplotlib.figure import Figure

    figures = {}
    savefig = Figure.savefig

    def recording(self, fname, *args, **kwargs):
        figures[os.path.basename(str(fname))] = self
        return savefig(self, fname, *args, **kwargs)

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(Figure, "savefig", recording)
        yield figures


@pytest.fixture
def saved_figures():
    """Every matplotlib figure saved during the test (see :func:`recorded_figures`)."""
    with recorded_figures() as figures:
        yield figures


def _reference_slope_mismatches(ax) -> list[str]:
    """Curves of ``ax`` labelled ``"... (p = k)"`` without a dotted line of their colour and
    log-log slope k (``experiments._common.reference_slope``)."""
    import re

    from matplotlib.colors import same_color

    guides = [line for line in ax.lines if line.get_linestyle() == ":" and len(line.get_xdata())]
    missing = []
    for line in ax.lines:
        match = re.search(r"\(p = (\d+)\)", line.get_label())
        if not match:
            continue
        order = int(match.group(1))
        slopes = []
        for guide in guides:
            if same_color(guide.get_color(), line.get_color()):
                (x0, x1), (y0, y1) = guide.get_xdata(), guide.get_ydata()
                slopes.append(math.log(y1 / y0) / math.log(x1 / x0))
        if not any(abs(s - order) < 1e-9 for s in slopes):
            missing.append(f"{line.get_label()}: guide slopes {slopes}")
    return missing


@pytest.fixture
def reference_slope_mismatches():
    return _reference_slope_mismatches
