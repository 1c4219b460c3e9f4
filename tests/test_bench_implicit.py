"""The implicit benchmark runs in --quick mode and reports errors that are checked here.

Section 3 (IFT vs unrolled Newton): gradients must agree with each other and with finite
differences, and the memory saved for backward must stay constant with the number of Newton
iterations for the implicit-function-theorem gradient (notes eq. 3.40) but grow linearly
for autograd through the iterations.
"""

import csv

import pytest
import torch
from conftest import recorded_figures

from experiments._common import figure_defects
from experiments._graph_memory import GraphMemory
from experiments.bench_implicit import main, unrolled_newton

#: the figures the module's quick run saved, by file name
FIGURES: dict = {}

UNROLLED = "unrolled autograd through Newton"


@pytest.fixture(scope="module")
def quick(tmp_path_factory):
    out = tmp_path_factory.mktemp("bench_implicit")
    with recorded_figures() as figures:
        result = main(["--quick", "--out", str(out)])
    FIGURES.update(figures)
    return out, result


def test_bench_implicit_quick_reports_consistent_errors(quick):
    out, rows = quick
    assert (out / "bench_implicit.png").exists()
    assert (out / "bench_implicit_ift_memory.png").exists()
    with open(out / "bench_implicit.csv") as fh:
        table = list(csv.DictReader(fh))
    assert len(table) == len(rows) == 10
    for row in rows:
        assert row["ours_s"] > 0 and row["peer_s"] > 0
        if row["peer"] == UNROLLED:
            continue
        if row["rtol"] is not None:
            # adaptive Radau IIA meets the tolerance about as well as scipy's Radau
            assert row["ours_error"] < 20 * row["rtol"]
            assert row["ours_error"] < 10 * row["peer_error"] + row["rtol"]
        else:
            # at dt = 0.05, order 4 (Gauss s=2) and 5 (Radau s=3) beat Adams-Moulton
            assert row["ours_error"] < row["peer_error"]
            assert row["ours_error"] < 1e-6


def test_ift_gradients_agree_with_unrolled_and_finite_differences(quick):
    _, rows = quick
    ift = [r for r in rows if r["peer"] == UNROLLED]
    assert len(ift) == 4
    for row in ift:
        # both converge Newton tightly in float64, so the two gradients are the same numbers
        assert row["grad_rel_diff"] < 1e-8, row
        # central differences (step 1e-5 / 1e-6) agree to their own accuracy
        assert row["ours_fd_error"] < 1e-6, row
        assert row["peer_fd_error"] < 1e-6, row
        # same method and step: the same trajectory / root
        if row["ours_steps"] is not None:  # IRK rows: error vs scipy DOP853
            assert row["ours_error"] < 1e-6
            assert abs(row["ours_error"] - row["peer_error"]) < 1e-10
        else:  # Newton rows: residual ||phi||_inf at the returned root
            assert row["ours_error"] <= 1e-12 and row["peer_error"] <= 1e-12
        # the IFT graph is smaller than the unrolled one
        assert row["ours_saved_MB"] < row["peer_saved_MB"]
        assert row["memory_ratio"] > 2


def test_unrolled_memory_grows_with_iterations_ift_memory_does_not(quick):
    _, rows = quick
    newton_rows = [r for r in rows if r["peer"] == UNROLLED and r["ours_steps"] is None]
    few, many = sorted(newton_rows, key=lambda r: r["ours_newton_iters"])
    assert many["ours_newton_iters"] >= 2 * few["ours_newton_iters"]
    assert few["peer_newton_iters"] == few["ours_newton_iters"]
    assert many["peer_newton_iters"] == many["ours_newton_iters"]
    # IFT: x*, the parameters and the loss's own input, whatever the iteration count
    assert many["ours_saved_MB"] == few["ours_saved_MB"]
    # unrolled: linear in the iterations (a fixed part for the loss and the parameters)
    iteration_ratio = many["peer_newton_iters"] / few["peer_newton_iters"]
    memory_ratio = many["peer_saved_MB"] / few["peer_saved_MB"]
    assert 0.8 * iteration_ratio < memory_ratio < 1.05 * iteration_ratio


class _Scale(torch.autograd.Function):
    """y = a x with ``a`` kept on the context as an attribute (not ``save_for_backward``)."""

    @staticmethod
    def forward(ctx, x, a):
        ctx.a = a
        return a * x

    @staticmethod
    def backward(ctx, grad):
        return ctx.a * grad, None


def test_graph_memory_counts_saved_storages_and_context_attributes():
    x = torch.randn(100, dtype=torch.float64, requires_grad=True)
    with GraphMemory() as meter:
        y = torch.exp(x)  # saves its output: 800 bytes
        temporary = torch.sin(x).sum()  # saves x, but the graph is dropped below
        del temporary
        z = (y * 2.0).sum()  # multiplication by a Python scalar saves nothing
        assert meter.saved_bytes(z) == 800
        w = _Scale.apply(y, torch.ones(50, dtype=torch.float64)[:1].expand(100)).sum()
        assert meter.saved_bytes(w) == 800 + 400  # the whole storage behind the expanded view
        v = (y * x).sum()  # saves y (counted once) and x
        assert meter.saved_bytes(v) == 1600  # context attributes only from v's own graph
    # the counted graph still differentiates correctly (pack/unpack keep the values)
    (g,) = torch.autograd.grad(v, x)
    torch.testing.assert_close(g, torch.exp(x) * (1 + x))


def test_unrolled_newton_matches_closed_form():
    # exp(x) = b  ->  x = log b, dx/db = 1 / b (eq. 3.40 in one dimension)
    b = torch.tensor([[0.5], [2.0], [7.0]], dtype=torch.float64, requires_grad=True)
    x0 = torch.full((3, 1), 3.0, dtype=torch.float64, requires_grad=True)
    x, iterations = unrolled_newton(lambda x, b: torch.exp(x) - b, x0, b, tol=1e-14)
    assert iterations > 3
    torch.testing.assert_close(x, torch.log(b), atol=1e-14, rtol=0)
    (g,) = torch.autograd.grad(x.sum(), b)
    torch.testing.assert_close(g, 1 / b.detach(), atol=1e-12, rtol=0)


def test_quick_run_figures_are_readable(quick):
    """Every figure of the quick run has labelled axes, finite lines and a legend without
    duplicates (``experiments._common.figure_defects``)."""
    assert FIGURES, "the quick run saved no figure"
    for name, figure in FIGURES.items():
        assert figure_defects(figure) == [], name
