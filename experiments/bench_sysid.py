"""Benchmark of the estimators (issue 4), all in one process, ratios printed as a table.

1. 10 000 FIR (nb = 20) least-squares fits of N = 1000 samples: ``sysid.fir_lls`` (one batched
   call, normal equations from block-Gram correlations, batched Cholesky) and ``sysid.lls`` on
   the explicit regressors (one batched call, Cholesky) vs a Python loop of
   ``numpy.linalg.lstsq`` (goal >= 10x). Agreement: largest parameter difference and largest
   relative difference of the residual variance sigma^2 to numpy.
2. One full OE (nb = nf = 4) fit on N = 10 000 samples: ``sysid.fit`` (automatic ARX/IV start,
   batched Levenberg-Marquardt; the OE Jacobian by filtering ``u/F`` and ``(B/F u)/F``) vs
   ``scipy.optimize.least_squares`` on the same model (simulation errors by
   ``scipy.signal.lfilter``, finite-difference Jacobian) started from our automatic initial
   estimate: time, parameter error reached, final cost. A second row times ``sysid.fit`` from
   that same start (``init=``), i.e. without the ARX/IV initialisation, like scipy.
3. The OE simulation-error gradient through the IIR filter (imported from
   ``experiments/bench_filter.py``): ours (default CPU dispatch: scipy's lfilter for the two
   filtering passes inside our autograd node) and ours with the pure-torch block method
   (``sysid.filters.cpu_backend("torch")``, the path used on CUDA and for higher derivatives)
   vs a scipy-lfilter autograd function and a Python loop.
4. Batched prediction-error fits of 128 data sets (N = 1000) of a Box-Jenkins and an OE model
   at a low signal-to-noise ratio (noise standard deviation 3), where the data sets need from
   4-5 to 45-72 iterations: ``sysid.fit`` on the whole batch, whose Levenberg-Marquardt
   iteration evaluates only the data sets still iterating (``minimize(compact=True)``), vs the
   same batch with that compaction off (every iteration evaluates all data sets until the
   slowest converges; the baseline) and vs four batches of 32. Agreement: largest parameter
   difference to the baseline and whether the iteration counts are equal.

Timings: best of ``--repeats`` runs (the Python loops run once), wall clock and process CPU
time, torch on one thread. Run with ``OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1
MKL_NUM_THREADS=1`` so that numpy/scipy also use one thread: the CPU time of a multithreaded
BLAS includes its spinning threads and would flatter our ratios.

Run: ``python -m experiments.bench_sysid [--quick] [--out DIR] [--repeats R]``.
"""

from __future__ import annotations

import argparse
import functools
import time
from unittest import mock

from experiments._common import (
    experiment_parser,
    finish,
    output_dir,
    parse_early,
    progress,
    write_table,
)

NAME = "bench_sysid"


def build_parser() -> argparse.ArgumentParser:
    """The command line (``--help`` lists it); built without importing torch."""
    parser = experiment_parser(NAME, __doc__.splitlines()[0])
    parser.add_argument(
        "--fir-sets",
        type=int,
        default=10_000,
        help="FIR data sets in the batched least-squares case",
    )
    parser.add_argument("--repeats", type=int, default=3, help="best of this many runs")
    return parser


parse_early(__name__, build_parser)

import numpy as np
import scipy.optimize
import scipy.signal
import torch

import sysid.estimation.prediction_error as prediction_error
from integrators.newton import minimize
from sysid import BJ, OE, IOData, fir_lls, fit, lls
from sysid.filters import cpu_backend
from sysid.montecarlo import fir_regressor, input_signal, simulate_data

REPEATS = 3


def _timed(fn, repeats: int | None = None):
    """Best-of-``repeats`` wall-clock and process-CPU seconds of ``fn()``, and its result.

    On a shared machine the minimum is the robust estimate and CPU time (all threads of this
    process) is less sensitive than wall time to other processes competing for the cores.
    """
    walls, cpus = [], []
    for _ in range(repeats or REPEATS):
        start, cpu = time.perf_counter(), time.process_time()
        result = fn()
        walls.append(time.perf_counter() - start)
        cpus.append(time.process_time() - cpu)
    return min(walls), min(cpus), result


def bench_fir(n_sets: int, N: int, nb: int = 20, seed: int = 0) -> list[dict]:
    g = torch.Generator().manual_seed(seed)
    u = torch.randn(n_sets, N, generator=g, dtype=torch.float64)
    b = 0.8 ** torch.arange(nb, dtype=torch.float64)
    y = fir_regressor(u, nb) @ b + 0.1 * torch.randn(n_sets, N, generator=g, dtype=torch.float64)
    fir_lls(u[:2], y[:2], nb)  # warm-up (FFT plans, LAPACK)
    lls(fir_regressor(u[:2], nb), y[:2], method="cholesky")
    t_fir = _timed(lambda: fir_lls(u, y, nb))
    t_dense = _timed(lambda: lls(fir_regressor(u, nb), y, method="cholesky"), 1)
    un, yn = u.numpy(), y.numpy()

    def numpy_loop():
        out, rss = np.empty((n_sets, nb)), np.empty(n_sets)
        for i in range(n_sets):  # the baseline: one lstsq per data set
            padded = np.concatenate([np.zeros(nb - 1), un[i]])
            U = np.lib.stride_tricks.sliding_window_view(padded, nb)[:, ::-1]
            theta_i, rss_i = np.linalg.lstsq(U, yn[i], rcond=None)[:2]
            out[i], rss[i] = theta_i, rss_i[0]
        return out, rss / (N - nb)

    t_np = _timed(numpy_loop, 1)
    theta_np, sigma2_np = t_np[2]
    scale = np.abs(theta_np).max()
    rows = []
    for method, (wall, cpu, res) in [
        ("numpy lstsq loop", t_np),
        ("sysid.fir_lls (batched)", t_fir),
        ("sysid.lls dense cholesky (batched)", t_dense),
    ]:
        th, s2 = res if isinstance(res, tuple) else (res.theta.numpy(), res.sigma2.numpy())
        rows.append(
            {
                "task": f"{n_sets} FIR fits, N={N}, nb={nb}",
                "method": method,
                "seconds": wall,
                "cpu_seconds": cpu,
                "max_param_diff_vs_numpy": float(np.abs(th - theta_np).max() / scale),
                "max_sigma2_rel_diff_vs_numpy": float(np.abs(s2 / sigma2_np - 1).max()),
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
    t_ours, c_ours, res = _timed(lambda: fit(OE(4, 4, 1), data))
    start = res.info["initial_theta"].numpy()

    def residual(th):
        return y - scipy.signal.lfilter(np.r_[0.0, th[:4]], np.r_[1.0, th[4:]], u)

    t_sp, c_sp, sp = _timed(lambda: scipy.optimize.least_squares(residual, start, xtol=1e-10))
    t_same, c_same, same = _timed(lambda: fit(OE(4, 4, 1), data, init=res.info["initial_theta"]))

    def row(method, t, c, theta, cost, iterations):
        return {
            "task": f"OE(4,4) fit, N={N}",
            "method": method,
            "seconds": t,
            "cpu_seconds": c,
            "param_error_vs_truth": float(np.abs(theta - truth).max()),
            "final_cost": cost,
            "iterations_or_nfev": iterations,
        }

    rows = [
        row("scipy least_squares (trf, 2-point)", t_sp, c_sp, sp.x, float(sp.cost), int(sp.nfev))
    ]
    for method, t, c, fitted in [
        ("sysid.fit gauss_newton", t_ours, c_ours, res),
        ("sysid.fit gauss_newton, same start as scipy", t_same, c_same, same),
    ]:
        theta = fitted.theta.detach().numpy()
        cost = 0.5 * float(np.sum(residual(theta) ** 2))
        rows.append(row(method, t, c, theta, cost, int(fitted.iterations)))
    return rows


def _uncompacted():
    """Within the block, the prediction-error fits evaluate every data set in every iteration
    (``minimize(compact=False)``)."""
    return mock.patch.object(
        prediction_error, "minimize", functools.partial(_minimize_uncompacted, minimize)
    )


def _minimize_uncompacted(minimize_fn, *args, **kwargs):
    return minimize_fn(*args, **{**kwargs, "compact": False})


def _fit_batches(model, data, size: int):
    """``sysid.fit`` on consecutive batches of ``size`` data sets: (theta, iterations) of all."""
    fits = [fit(model, data[i : i + size]) for i in range(0, data.batch_shape[0], size)]
    return torch.cat([f.theta for f in fits]), torch.cat([f.iterations for f in fits])


def bench_batched_pem(n_sets: int, N: int, seed: int = 0) -> list[dict]:
    """BJ(nb=2, nc=1, nd=1, nf=2) and OE(nb=nf=2) fits of ``n_sets`` data sets (white input,
    the BJ noise model / white output noise of standard deviation 3): compacted batch vs
    uncompacted batch vs batches of ``n_sets // 4``."""
    cases = [
        ("BJ(2,1,1,2)", BJ(2, 1, 1, 2, 1), [0.5, 0.3, 0.4, -0.6, -1.2, 0.5], "model"),
        ("OE(2,2)", OE(2, 2, 1), [0.5, 0.3, -1.2, 0.5], "output"),
    ]
    rows = []
    for label, model, theta, noise in cases:
        g = torch.Generator().manual_seed(seed)
        u = input_signal("white", N, (n_sets,), generator=g)
        data = simulate_data(
            model, u, theta=torch.tensor(theta), noise_std=3.0, noise=noise, generator=g
        )
        fit(model, data[:2])  # warm-up (lazy initialisations)
        with _uncompacted():
            t_full = _timed(lambda m=model, d=data: _fit_batches(m, d, n_sets), 1)
        t_compact = _timed(lambda m=model, d=data: _fit_batches(m, d, n_sets), 1)
        size = n_sets // 4
        t_split = _timed(lambda m=model, d=data, k=size: _fit_batches(m, d, k), 1)
        base_theta, base_iterations = t_full[2]
        for method, (wall, cpu, (theta_hat, iterations)) in [
            ("one batch, uncompacted", t_full),
            ("one batch, compacted", t_compact),
            (f"4 batches of {size}, compacted", t_split),
        ]:
            rows.append(
                {
                    "task": f"{n_sets} {label} fits, N={N}",
                    "method": method,
                    "seconds": wall,
                    "cpu_seconds": cpu,
                    "max_param_diff_vs_uncompacted": float((theta_hat - base_theta).abs().max()),
                    "same_iterations": bool(torch.equal(iterations, base_iterations)),
                    "iterations": f"{int(iterations.min())}-{int(iterations.max())}",
                }
            )
    return rows


def bench_filter_gradient(N: int) -> list[dict]:
    try:
        from experiments.bench_filter import make_problem, oe_gradient, oe_model
    except ImportError:  # the filter benchmark is optional here
        return []
    u, y, theta = make_problem(N)
    data, model = IOData(u, y), oe_model(theta, u)  # built once, as in a fit
    rows, ref = [], None
    methods = [
        ("python_loop", "python_loop", "auto"),
        ("scipy_autograd", "scipy_autograd", "auto"),
        ("ours (CPU dispatch to scipy lfilter)", "ours", "auto"),
        ("ours, pure-torch block method", "ours", "torch"),
    ]
    for label, method, backend in methods:
        with cpu_backend(backend):
            oe_gradient(method, u[:100], y[:100], theta)  # warm-up
            ours = method == "ours"
            t, c, (loss, grad) = _timed(
                lambda m=method, o=ours: oe_gradient(
                    m, u, y, theta, data if o else None, model if o else None
                ),
                1 if method == "python_loop" else 5 * REPEATS,
            )
        ref = grad if ref is None else ref
        rows.append(
            {
                "task": f"OE(4,4) loss gradient, N={N}",
                "method": label,
                "seconds": t,
                "cpu_seconds": c,
                "grad_rel_diff": float((grad - ref).norm() / ref.norm()),
            }
        )
    scipy_cpu = rows[1]["cpu_seconds"]
    for r in rows:
        r["cpu_speedup_vs_scipy_autograd"] = scipy_cpu / r["cpu_seconds"]
    return rows


def main(argv=None):
    args = build_parser().parse_args(argv)
    out = output_dir(args, NAME)
    global REPEATS
    REPEATS = args.repeats
    previous_threads = torch.get_num_threads()
    torch.set_num_threads(1)  # same footing as the single-threaded numpy/scipy baselines
    try:
        if args.quick:
            stages = [
                (bench_fir, 300, 400),
                (bench_oe, 2000),
                (bench_filter_gradient, 2000),
                (bench_batched_pem, 16, 300),
            ]
        else:
            stages = [
                (bench_fir, args.fir_sets, 1000),
                (bench_oe, 10_000),
                (bench_filter_gradient, 100_000),
                (bench_batched_pem, 128, 1000),
            ]
        rows = []
        for bench, *sizes in progress(stages, "benchmarks"):
            rows += bench(*sizes)
    finally:
        torch.set_num_threads(previous_threads)
    for task in dict.fromkeys(r["task"] for r in rows):
        group = [r for r in rows if r["task"] == task]
        base = group[0]  # the baseline is listed first in each task
        for r in group:
            r["speedup_vs_baseline"] = base["seconds"] / r["seconds"]
            r["cpu_speedup_vs_baseline"] = base["cpu_seconds"] / r["cpu_seconds"]
    markdown = write_table(rows, out / NAME)
    (out / "README.md").write_text(f"# {NAME}\n\n{__doc__}\n\n{markdown}")
    finish(out, markdown)
    return rows


if __name__ == "__main__":
    main()
