"""Benchmark of the estimators (issue 4), all in one process, ratios printed as a table.

1. 10 000 FIR (nb = 20) least-squares fits of N = 1000 samples: ``sysid.fir_lls`` (one batched
   call, normal equations from FFT correlations) and ``sysid.lls`` on the explicit regressors
   (one batched call, Cholesky) vs a Python loop of ``numpy.linalg.lstsq`` (goal >= 10x).
   Agreement: largest parameter difference to numpy.
2. One full OE (nb = nf = 4) fit on N = 10 000 samples: ``sysid.fit`` (automatic ARX/IV start,
   batched Levenberg-Marquardt with forward-mode Jacobians) vs ``scipy.optimize.least_squares``
   on the same model (simulation errors by ``scipy.signal.lfilter``, finite-difference
   Jacobian) from the same starting point: time, parameter error reached, final cost.
3. The OE simulation-error gradient through the IIR filter (imported from
   ``experiments/bench_filter.py``): ours vs a scipy-lfilter autograd function and a Python
   loop.

Run: ``python -m experiments.bench_sysid [--quick] [--out DIR]``.
"""

from __future__ import annotations

import time

import numpy as np
import scipy.optimize
import scipy.signal
import torch

from experiments._common import experiment_parser, output_dir, write_table
from sysid import OE, IOData, fir_lls, fit, lls
from sysid.montecarlo import fir_regressor

NAME = "bench_sysid"


_CPU: dict[float, float] = {}


def _timed(fn):
    """Wall-clock seconds and result; the process CPU time of the call is kept in ``_CPU``
    (on a shared machine CPU time is the fairer measure: all methods run single-threaded)."""
    start, cpu = time.perf_counter(), time.process_time()
    result = fn()
    wall = time.perf_counter() - start
    _CPU[wall] = time.process_time() - cpu
    return wall, result


def bench_fir(n_sets: int, N: int, nb: int = 20, seed: int = 0) -> list[dict]:
    g = torch.Generator().manual_seed(seed)
    u = torch.randn(n_sets, N, generator=g, dtype=torch.float64)
    b = 0.8 ** torch.arange(nb, dtype=torch.float64)
    y = fir_regressor(u, nb) @ b + 0.1 * torch.randn(n_sets, N, generator=g, dtype=torch.float64)
    fir_lls(u[:2], y[:2], nb)  # warm-up (FFT plans, LAPACK)
    lls(fir_regressor(u[:2], nb), y[:2], method="cholesky")
    t_fft, res_fft = _timed(lambda: fir_lls(u, y, nb))
    t_dense, res_dense = _timed(lambda: lls(fir_regressor(u, nb), y, method="cholesky"))
    un, yn = u.numpy(), y.numpy()

    def numpy_loop():
        out = np.empty((n_sets, nb))
        for i in range(n_sets):  # the baseline: one lstsq per data set
            padded = np.concatenate([np.zeros(nb - 1), un[i]])
            U = np.lib.stride_tricks.sliding_window_view(padded, nb)[:, ::-1]
            out[i] = np.linalg.lstsq(U, yn[i], rcond=None)[0]
        return out

    t_np, theta_np = _timed(numpy_loop)
    scale = np.abs(theta_np).max()
    rows = []
    for method, t, th in [
        ("numpy lstsq loop", t_np, theta_np),
        ("sysid.fir_lls (batched)", t_fft, res_fft.theta.numpy()),
        ("sysid.lls dense cholesky (batched)", t_dense, res_dense.theta.numpy()),
    ]:
        rows.append(
            {
                "task": f"{n_sets} FIR fits, N={N}, nb={nb}",
                "method": method,
                "seconds": t,
                "speedup_vs_baseline": t_np / t,
                "max_param_diff_vs_numpy": float(np.abs(th - theta_np).max() / scale),
            }
        )
    return rows


def oe_problem(N: int, seed: int = 0):
    """The nb = nf = 4 OE system of bench_filter (poles 0.9, 0.7, 0.5 +- 0.4j) + white noise."""
    g = torch.Generator().manual_seed(seed)
    u = torch.randn(N, generator=g, dtype=torch.float64)
    f_true = np.poly([0.9, 0.7, 0.5 + 0.4j, 0.5 - 0.4j]).real
    b_true = np.array([0.5, 0.3, -0.2, 0.1])
    y = scipy.signal.lfilter(np.r_[0.0, b_true], f_true, u.numpy())
    y = y + 0.1 * torch.randn(N, generator=g, dtype=torch.float64).numpy()
    return u.numpy(), y, np.r_[b_true, f_true[1:]]


def bench_oe(N: int) -> list[dict]:
    u, y, truth = oe_problem(N)
    data = IOData(torch.tensor(u), torch.tensor(y))
    fit(OE(4, 4, 1), IOData(data.u[:300], data.y[:300]))  # warm-up (lazy initialisations)
    t_ours, res = _timed(lambda: fit(OE(4, 4, 1), data))
    start = res.info["initial_theta"].numpy()

    def residual(th):
        return y - scipy.signal.lfilter(np.r_[0.0, th[:4]], np.r_[1.0, th[4:]], u)

    t_sp, sp = _timed(lambda: scipy.optimize.least_squares(residual, start, xtol=1e-10))
    ours = res.theta.detach().numpy()
    cost_ours = 0.5 * float(np.sum(residual(ours) ** 2))
    rows = []
    for method, t, th, cost, nit in [
        ("scipy least_squares (trf, 2-point)", t_sp, sp.x, float(sp.cost), int(sp.nfev)),
        ("sysid.fit gauss_newton", t_ours, ours, cost_ours, int(res.iterations)),
    ]:
        rows.append(
            {
                "task": f"OE(4,4) fit, N={N}",
                "method": method,
                "seconds": t,
                "speedup_vs_baseline": t_sp / t,
                "param_error_vs_truth": float(np.abs(th - truth).max()),
                "final_cost": cost,
                "iterations_or_nfev": nit,
            }
        )
    return rows


def bench_filter_gradient(N: int) -> list[dict]:
    try:
        from experiments.bench_filter import make_problem, oe_gradient
    except ImportError:  # the filter benchmark is optional here
        return []
    u, y, theta = make_problem(N)
    data = IOData(u, y)
    rows, ref = [], None
    for method in ("python_loop", "scipy_autograd", "ours"):
        oe_gradient(method, u[:100], y[:100], theta)  # warm-up
        t, (loss, grad) = _timed(
            lambda m=method: oe_gradient(m, u, y, theta, data if m == "ours" else None)
        )
        ref = grad if ref is None else ref
        rows.append(
            {
                "task": f"OE(4,4) loss gradient, N={N}",
                "method": method,
                "seconds": t,
                "grad_rel_diff": float((grad - ref).norm() / ref.norm()),
            }
        )
    t_loop = rows[0]["seconds"]
    for r in rows:
        r["speedup_vs_baseline"] = t_loop / r["seconds"]
    return rows


def main(argv=None):
    parser = experiment_parser(NAME, __doc__.splitlines()[0])
    parser.add_argument("--fir-sets", type=int, default=10_000)
    args = parser.parse_args(argv)
    out = output_dir(args, NAME)
    torch.set_num_threads(1)  # same footing as the single-threaded numpy/scipy baselines
    if args.quick:
        rows = bench_fir(300, 400) + bench_oe(2000) + bench_filter_gradient(2000)
    else:
        rows = bench_fir(args.fir_sets, 1000) + bench_oe(10_000) + bench_filter_gradient(100_000)
    for row in rows:
        row["cpu_seconds"] = _CPU.get(row["seconds"], float("nan"))
    for task in {r["task"] for r in rows}:
        group = [r for r in rows if r["task"] == task]
        base = group[0]["cpu_seconds"]  # the baseline is listed first in each task
        for r in group:
            r["cpu_speedup_vs_baseline"] = base / r["cpu_seconds"]
    markdown = write_table(rows, out / NAME)
    (out / "README.md").write_text(f"# {NAME}\n\n{__doc__}\n\n{markdown}")
    print(markdown)
    return rows


if __name__ == "__main__":
    main()
