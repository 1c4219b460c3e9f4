"""Benchmark of declared Monte-Carlo studies (:class:`sysid.studies.Study`), in one process.

1. Throughput: ARX(2, 2) equation-error data sets (N = 500, white input, sigma = 0.5),
   end to end (simulation, one batched ``sysid.fit(..., method="lls")`` per chunk, Parquet
   checkpoint) against the plain Python loop a user writes: per data set, build the
   regressor, ``numpy.linalg.lstsq`` and its standard errors, and statsmodels ``OLS(...).fit()``
   (parameters and ``bse``), on the first ``--loop-trials`` data sets of the same study (the
   same data), extrapolated per data set; the same loops end to end, as a user writes a
   study by hand: per data set, draw the input and the noise (``numpy.random.Generator``),
   simulate ``A y = B u + e`` by ``scipy.signal.lfilter`` and fit by ``lstsq`` or statsmodels;
   and the study's batched fit alone on one chunk of its ready data (the like-for-like peer of
   the loops on ready data). Reported: seconds per data set, the ratio to the study, and the
   largest difference between the loop's estimates and the study's (on the same data; the
   end-to-end loops draw their own).
2. Checkpointing: the same study run into a folder (Parquet per chunk, manifest) against
   the same chunks computed without writing anything; overhead in per cent.
3. Dask: a compute-bound study (OE(2, 2) Gauss-Newton fits) on a ``LocalCluster`` of 2
   one-thread workers against 1 worker (``sysid.studies.local_cluster``: workers started
   with ``sysid.studies.WORKER_ENVIRONMENT``; cluster start-up not timed).

Timings: wall clock, best of ``--repeats``, torch on one thread. Run with
``OMP_NUM_THREADS=1`` so numpy and statsmodels use one thread too.

Run: ``python -m experiments.bench_studies [--quick] [--out DIR]``.
"""

from __future__ import annotations

import argparse
import datetime
import platform
import tempfile
import time

from experiments._common import (
    experiment_parser,
    finish,
    note,
    output_dir,
    parse_early,
    write_table,
)

NAME = "bench_studies"


def build_parser() -> argparse.ArgumentParser:
    """The command line (``--help`` lists it); built without importing torch."""
    parser = experiment_parser(NAME, __doc__.splitlines()[0])
    parser.add_argument(
        "--trials",
        type=int,
        default=None,
        help="ARX data sets of the throughput study (default 100000, 2000 with --quick)",
    )
    parser.add_argument(
        "--loop-trials",
        type=int,
        default=None,
        help="data sets fitted by the Python loops (default 2000, 50 with --quick); the "
        "loops' time per data set does not depend on how many are fitted",
    )
    parser.add_argument(
        "--dask-trials",
        type=int,
        default=None,
        help="OE data sets of the Dask study (default 2000, 64 with --quick)",
    )
    parser.add_argument("--repeats", type=int, default=2, help="timed repetitions (best kept)")
    return parser


parse_early(__name__, build_parser)

import numpy as np
import scipy.signal
import torch

from sysid import ARX, OE, fit
from sysid.montecarlo import input_signal, simulate_data
from sysid.studies import Study, local_cluster

N = 500
THETA = [-1.2, 0.5, 0.5, 0.3]  # a1, a2, b1, b2 of A y = B u + e
SIGMA = 0.5


def simulate(point: dict, n: int, generator: torch.Generator):
    """``n`` ARX(2, 2) data sets with equation-error noise (white input, ``point["N"]``)."""
    u = input_signal("white", point["N"], (n,), generator=generator)
    theta = torch.tensor(THETA, dtype=torch.float64)
    return simulate_data(
        ARX(2, 2, 1), u, theta=theta, noise_std=SIGMA, noise="model", generator=generator
    )


def arx_study(trials: int, chunk: int) -> Study:
    truth = dict(zip(ARX(2, 2, 1).parameter_names(), THETA, strict=True))
    return Study(
        simulate,
        {"arx_ls": lambda data: fit(ARX(2, 2, 1), data, method="lls")},
        grid={"N": [N]},
        trials=trials,
        seed=5,
        chunk=chunk,
        block=chunk,
        truth=truth,
    )


def oe_study(trials: int, chunk: int) -> Study:
    return Study(
        simulate,
        {"oe_gn": lambda data: fit(OE(2, 2, 1), data)},
        grid={"N": [N]},
        trials=trials,
        seed=6,
        chunk=chunk,
        block=chunk,
    )


def regressor(u: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """ARX(2, 2, 1) regressor ``[-y_{t-1}, -y_{t-2}, u_{t-1}, u_{t-2}]`` for t >= 2 and the
    target ``y_t`` (one data set, numpy)."""
    phi = np.column_stack([-y[1:-1], -y[:-2], u[1:-1], u[:-2]])
    return phi, y[2:]


def numpy_fit(u, y):
    phi, target = regressor(u, y)
    theta, ssr, _, _ = np.linalg.lstsq(phi, target, rcond=None)
    sigma2 = ssr[0] / (len(target) - phi.shape[1])
    se = np.sqrt(sigma2 * np.diag(np.linalg.inv(phi.T @ phi)))
    return theta, se


def loop_study(trials: int, one_fit, seed: int = 0) -> np.ndarray:
    """The study end to end in a Python loop: per data set, a white input and Gaussian noise
    from ``numpy.random.Generator``, ``A y = B u + e`` by ``scipy.signal.lfilter``, then
    ``one_fit(u, y)`` (:func:`numpy_fit` or :func:`statsmodels_fit`); returns the (trials, 4)
    estimates."""
    rng = np.random.default_rng(seed)
    a = np.array([1.0, THETA[0], THETA[1]])  # A(q) = 1 + a1 q^-1 + a2 q^-2
    b = np.array([0.0, THETA[2], THETA[3]])  # B(q) = b1 q^-1 + b2 q^-2
    out = np.empty((trials, 4))
    for i in range(trials):
        u = rng.standard_normal(N)
        y = scipy.signal.lfilter(b, a, u) + scipy.signal.lfilter(
            [1.0], a, SIGMA * rng.standard_normal(N)
        )
        out[i] = one_fit(u, y)[0]
    return out


def statsmodels_fit(u, y):
    import statsmodels.api as sm

    phi, target = regressor(u, y)
    res = sm.OLS(target, phi).fit()
    return res.params, res.bse


def best(function, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        function()
        times.append(time.perf_counter() - start)
    return min(times)


def throughput(trials: int, loop_trials: int, repeats: int, scratch) -> tuple[list, list]:
    """Section 1 and 2: rows of the throughput table and of the checkpoint table."""
    chunk = min(5000, trials)
    study = arx_study(trials, chunk)

    def run_to_folder():  # a fresh folder each time (removed with scratch, not timed)
        study.run(tempfile.mkdtemp(dir=scratch), progress=False)

    def run_in_memory():
        # the same chunks as run(folder), nothing written: the cost of checkpointing is the rest
        return study.run(progress=False)

    note(f"study: {trials} ARX data sets, N = {N}, chunks of {chunk}")
    t_study = best(run_to_folder, repeats)
    t_memory = best(run_in_memory, repeats)
    done = study.run(tempfile.mkdtemp(dir=scratch), progress=False)
    everything = done.results["estimate"].to_numpy().reshape(trials, 4)
    estimates = everything[:loop_trials]
    data = study.data(0, 0)  # the study's own first data sets
    us = data.u[:loop_trials, :, 0].numpy()
    ys = data.y[:loop_trials, :, 0].numpy()

    def row(method, n, seconds, theta, difference=float("nan")):
        return {
            "method": method,
            "data_sets": n,
            "seconds_per_data_set": seconds / n,
            "speedup_vs_this": seconds / n / (t_study / trials),
            "max_abs_estimate_difference": difference,
            "max_abs_mean_estimate_error": float(np.abs(theta.mean(0) - THETA).max()),
        }

    rows = [row("Study, batched fit(method='lls'), checkpointed", trials, t_study, everything, 0.0)]
    for label, one in (
        ("Python loop, numpy lstsq", numpy_fit),
        ("Python loop, statsmodels OLS", statsmodels_fit),
    ):
        note(f"{label}: {loop_trials} data sets")
        seconds = best(lambda one=one: [one(u, y) for u, y in zip(us, ys, strict=True)], repeats)
        theta = np.array([one(u, y)[0] for u, y in zip(us, ys, strict=True)])
        rows.append(row(label, loop_trials, seconds, theta, float(np.abs(theta - estimates).max())))
    for label, one in (
        ("Python loop end to end: numpy draws, scipy lfilter, numpy lstsq", numpy_fit),
        ("Python loop end to end: numpy draws, scipy lfilter, statsmodels OLS", statsmodels_fit),
    ):
        note(f"{label}: {loop_trials} data sets")
        seconds = best(lambda one=one: loop_study(loop_trials, one), repeats)
        rows.append(row(label, loop_trials, seconds, loop_study(loop_trials, one)))
    label = "batched fit(method='lls') alone, one chunk of ready data"
    note(f"{label}: {data.u.shape[0]} data sets")
    seconds = best(lambda: fit(ARX(2, 2, 1), data, method="lls"), repeats)
    theta = fit(ARX(2, 2, 1), data, method="lls").theta.detach().numpy()
    difference = float(np.abs(theta - everything[: len(theta)]).max())
    rows.append(row(label, len(theta), seconds, theta, difference))
    checkpoint = [
        {
            "data_sets": trials,
            "chunks": study.n_chunks,
            "seconds_in_memory": t_memory,
            "seconds_run_to_folder": t_study,
            "checkpoint_overhead_pct": 100 * (t_study - t_memory) / t_memory,
        }
    ]
    return rows, checkpoint


def dask_scaling(trials: int, repeats: int, scratch) -> list:
    """Section 3: OE Gauss-Newton study on 1 and 2 local Dask workers."""
    from dask.distributed import Client

    chunk = max(1, trials // 16)
    study = oe_study(trials, chunk)
    rows = []
    for workers in (1, 2):
        note(f"dask: {trials} OE data sets on {workers} worker(s)")
        with local_cluster(workers) as cluster, Client(cluster) as client:
            client.run(torch.set_num_threads, 1)

            def run(client=client):
                study.run(tempfile.mkdtemp(dir=scratch), client=client, progress=False)

            seconds = best(run, repeats)
        rows.append(
            {
                "workers": workers,
                "data_sets": trials,
                "chunks": study.n_chunks,
                "seconds": seconds,
                "data_sets_per_second": trials / seconds,
            }
        )
    for row in rows:
        row["speedup_vs_1_worker"] = rows[0]["seconds"] / row["seconds"]
    return rows


def main(argv=None):
    args = build_parser().parse_args(argv)
    out = output_dir(args, NAME)
    trials = args.trials or (2000 if args.quick else 100_000)
    loop_trials = min(trials, args.loop_trials or (50 if args.quick else 2000))
    dask_trials = args.dask_trials or (64 if args.quick else 2000)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        with tempfile.TemporaryDirectory() as scratch:
            rows, checkpoint = throughput(trials, loop_trials, args.repeats, scratch)
            dask_rows = dask_scaling(dask_trials, args.repeats, scratch)
    finally:
        torch.set_num_threads(threads)
    header = (
        f"Measured {datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d %H:%M} UTC on "
        f"{platform.machine()} ({platform.processor() or 'cpu'}), torch {torch.__version__}, "
        "1 thread per process, float64.\n\n"
    )
    md_rows = write_table(rows, out / "throughput")
    md_checkpoint = write_table(checkpoint, out / "checkpoint")
    md_dask = write_table(dask_rows, out / "dask")
    report = (
        header
        + f"## ARX(2, 2) least squares, N = {N}: Study vs a Python loop per data set\n\n"
        + md_rows
        + "\n## Checkpointing: run to a folder vs the same chunks in memory\n\n"
        + md_checkpoint
        + "\n## Dask LocalCluster, OE(2, 2) Gauss-Newton (compute-bound)\n\n"
        + md_dask
    )
    (out / "README.md").write_text(f"# {NAME}\n\n{__doc__}\n\n{report}")
    finish(out, report)
    return rows, checkpoint, dask_rows


if __name__ == "__main__":
    main()
