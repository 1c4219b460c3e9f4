"""Benchmark of grey-box identification through the RK layers against scipy, in one process.

1. Crane (the course notes (Modelling and Simulation), eq. 2.55-2.70, with viscous friction
   ``d`` on the cart): cart position and rope angle measured with white noise under a
   random binary force of 0.5 N held 0.5 s, linear between samples (``intersample="foh"``;
   the rope swings up to 0.3-0.5 rad, the cart travels a few metres). The physical
   parameters (M, m, L, d) of every data set are estimated by

   * ours: one batched ``sysid.fit`` of a ``GreyBoxModel`` (RK4, exact forward
     sensitivities, Levenberg-Marquardt) over all data sets, by multiple shooting (segments
     of 10 samples with free node states, the default): over a 50 s record the pendulum
     swings about 28 times, and from a start 30 % off (even 3 % off) the simulation error
     (single shooting) has local minima that a full-record fit stops in, ours and scipy's
     alike;
   * scipy, the usual user code: ``scipy.optimize.least_squares`` (trust-region reflective,
     finite-difference Jacobian) on the simulation error from ``scipy.integrate.solve_ivp``
     (RK45 at rtol 1e-8, the force interpolated linearly by ``numpy.interp``), one data set
     after another.

   Both start from the same values (30 % off). Reported: wall time per data set, the RMS
   relative parameter error over the data sets, the fraction of fits that converged (ours:
   a stationary point; scipy: ``success``), and the ratio of times.
2. The simulation-error Jacobian of a 6-parameter Duffing oscillator
   (m y'' + d y' + k1 y + k3 y^3 = u + offset, with x0 estimated) over a long record:
   time of one residual + Jacobian evaluation (compile included) and the growth of the peak
   memory of a fresh process over its peak before the evaluation, at N and 2 N samples
   (memory linear in the record length).

Timings: wall clock, torch on one thread. Run with ``OMP_NUM_THREADS=1`` so numpy/scipy use
one thread too.

Run: ``python -m experiments.bench_greybox [--quick] [--out DIR]``.
"""

from __future__ import annotations

import argparse
import multiprocessing
import resource
import time
from concurrent.futures import ProcessPoolExecutor

from experiments._common import (
    experiment_parser,
    finish,
    note,
    output_dir,
    parse_early,
    progress,
    write_table,
)

NAME = "bench_greybox"


def build_parser() -> argparse.ArgumentParser:
    """The command line (``--help`` lists it); built without importing torch."""
    parser = experiment_parser(NAME, __doc__.splitlines()[0])
    parser.add_argument(
        "--sets", type=int, default=None, help="crane data sets (default 100, 2 with --quick)"
    )
    parser.add_argument(
        "--samples",
        type=int,
        default=None,
        help="samples per crane data set (default 1000, 100 with --quick)",
    )
    parser.add_argument(
        "--scipy-sets",
        type=int,
        default=None,
        help="data sets fitted by the scipy loop (default 10, 1 with --quick): its time per "
        "data set does not depend on how many are fitted",
    )
    parser.add_argument(
        "--jacobian-samples",
        type=int,
        default=None,
        help="Duffing record length N of the Jacobian case, also run at 2 N "
        "(default 43500, 1000 with --quick)",
    )
    return parser


parse_early(__name__, build_parser)

import numpy as np
import scipy.integrate
import scipy.optimize
import torch

from sysid import GreyBoxModel, IOData, Param, fit
from sysid.continuous.fit import _Problem
from sysid.montecarlo import input_signal

G = 9.81
CRANE_TRUE = {"M": 2.0, "m": 0.5, "L": 0.8, "d": 0.4}
CRANE_START = {"M": 2.6, "m": 0.35, "L": 1.04, "d": 0.28}
TS = 0.05
NOISE = (0.002, 0.002)  # m, rad
#: force amplitude (N) of the binary excitation, held 0.5 s: the rope swings up to about
#: 0.3-0.5 rad (a 5 N force would swing the load over the top, a chaotic motion no crane
#: makes, whose simulation error no fit can follow over 50 s)
FORCE = 0.5


def crane(t, x, u, p):
    """Crane in polar coordinates, state (x, theta, xdot, thetadot): eq. 2.70 with the cart
    force u - d xdot (W(q)^-1 applied to the generalised force (F, 0), eq. 2.60)."""
    s, c = torch.sin(x[..., 1]), torch.cos(x[..., 1])
    M, m, L = p["M"], p["m"], p["L"]
    force = u[..., 0] - p["d"] * x[..., 2]
    den = M + m - m * c**2
    xdd = (m * s * (L * x[..., 3] ** 2 + G * c) + force) / den
    thdd = -(s * ((M + m) * G + m * L * c * x[..., 3] ** 2) + c * force) / (L * den)
    return torch.stack([x[..., 2], x[..., 3], xdd, thdd], -1)


def crane_numpy(x, force, M, m, L, d):
    """The same right-hand side for scipy (one trajectory, floats)."""
    s, c = np.sin(x[1]), np.cos(x[1])
    f = force - d * x[2]
    den = M + m - m * c**2
    xdd = (m * s * (L * x[3] ** 2 + G * c) + f) / den
    thdd = -(s * ((M + m) * G + m * L * c * x[3] ** 2) + c * f) / (L * den)
    return np.array([x[2], x[3], xdd, thdd])


def crane_data(sets: int, N: int, seed: int = 0) -> IOData:
    g = torch.Generator().manual_seed(seed)
    u = FORCE * input_signal("prbs", N, (sets,), hold=10, generator=g)
    truth = GreyBoxModel(crane, dict(CRANE_TRUE), nx=4, output=[0, 1], substeps=4)
    y = truth.simulate(IOData(u, torch.zeros(sets, N, 2), Ts=TS, intersample="foh"))
    noise = torch.tensor(NOISE, dtype=y.dtype)
    y = y + noise * torch.randn(y.shape, generator=g, dtype=y.dtype)
    return IOData(u, y, Ts=TS, intersample="foh")


def ours(data: IOData):
    start = {k: Param(v, min=0.0) for k, v in CRANE_START.items()}
    model = GreyBoxModel(crane, start, nx=4, output=[0, 1], substeps=2)
    res = fit(model, data, criterion="multiple_shooting")
    return res.theta.numpy(), res


def scipy_fit(u: np.ndarray, y: np.ndarray) -> scipy.optimize.OptimizeResult:
    """least_squares over (M, m, L, d) of one data set, simulation by solve_ivp (its
    result: ``x`` the estimate, ``success`` whether a stopping criterion was met)."""
    N = u.shape[0]
    t = TS * np.arange(N)
    scale = np.array(NOISE)

    def residual(p):
        M, m, L, d = p
        sol = scipy.integrate.solve_ivp(
            lambda tt, x: crane_numpy(x, np.interp(tt, t, u[:, 0]), M, m, L, d),
            (0.0, t[-1]),
            np.zeros(4),
            t_eval=t,
            rtol=1e-8,
            atol=1e-10,
        )
        if not sol.success or sol.y.shape[1] != N:
            return np.full(2 * N, 1e6)
        return ((sol.y[:2].T - y) / scale).ravel()

    start = np.array([CRANE_START[k] for k in ("M", "m", "L", "d")])
    # a relative difference step well above solve_ivp's tolerance: the default (1e-8) would
    # differentiate the integrator's error control and stall at the start
    return scipy.optimize.least_squares(residual, start, bounds=(1e-6, np.inf), diff_step=1e-4)


def relative_error(est: np.ndarray) -> float:
    truth = np.array([CRANE_TRUE[k] for k in ("M", "m", "L", "d")])
    return float(np.sqrt(np.mean(((est - truth) / truth) ** 2)))


def crane_rows(sets: int, N: int, scipy_sets: int) -> list[dict]:
    data = crane_data(sets, N)
    rows = []
    note(f"crane: one batched fit of {sets} data sets of {N} samples")
    start = time.perf_counter()
    est, res = ours(data)
    batched = time.perf_counter() - start
    single_data = data[:1]
    start = time.perf_counter()
    est1, res1 = ours(single_data)
    single = time.perf_counter() - start
    note(f"crane: scipy least_squares + solve_ivp on {scipy_sets} data sets, one by one")
    u, y = data.u.numpy(), data.y.numpy()
    scipy_runs, start = [], time.perf_counter()
    for i in progress(range(scipy_sets), "scipy fits"):
        scipy_runs.append(scipy_fit(u[i], y[i]))
    scipy_time = (time.perf_counter() - start) / scipy_sets
    scipy_est = np.array([run.x for run in scipy_runs])
    ours_sub = est[:scipy_sets]
    rows.append(
        {
            "case": f"crane, {sets} data sets x {N} samples",
            "method": "ours, one batched fit",
            "seconds_per_data_set": batched / sets,
            "relative_parameter_error": relative_error(est),
            "error_on_scipy_sets": relative_error(ours_sub),
            "converged": float(res.converged.double().mean()),
            "speed_up_vs_scipy": scipy_time / (batched / sets),
        }
    )
    rows.append(
        {
            "case": f"crane, 1 data set x {N} samples",
            "method": "ours, one data set",
            "seconds_per_data_set": single,
            "relative_parameter_error": relative_error(est1),
            "error_on_scipy_sets": relative_error(est1),
            "converged": float(res1.converged.double().mean()),
            "speed_up_vs_scipy": scipy_time / single,
        }
    )
    rows.append(
        {
            "case": f"crane, {scipy_sets} data sets x {N} samples",
            "method": "scipy least_squares + solve_ivp, loop",
            "seconds_per_data_set": scipy_time,
            "relative_parameter_error": relative_error(scipy_est),
            "error_on_scipy_sets": relative_error(scipy_est),
            "converged": float(np.mean([run.success for run in scipy_runs])),
            "speed_up_vs_scipy": 1.0,
        }
    )
    return rows


def duffing(t, x, u, p):
    acc = (
        u[..., 0]
        + p["offset"]
        - p["d"] * x[..., 1]
        - p["k1"] * x[..., 0]
        - p["k3"] * x[..., 0] ** 3
    ) / p["m"]
    return torch.stack([x[..., 1], acc], -1)


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _jacobian_in_fresh_process(n: int) -> dict:
    """One residual + Jacobian evaluation of the 6-parameter Duffing simulation error over
    ``n`` samples, run in a fresh process (see :func:`jacobian_rows`): its time (compile
    included) and the growth of the process' peak resident memory over its peak before."""
    torch.set_num_threads(1)
    params = {"m": 1.0, "d": 0.3, "k1": 2.0, "k3": 0.5, "offset": 0.1, "extra": 0.0}

    def duffing6(t, x, u, p):  # a sixth parameter scaling the input
        return duffing(t, x, u * (1 + p["extra"][..., None]), p)

    model = GreyBoxModel(duffing6, {k: Param(v) for k, v in params.items()}, nx=2, output=[0])
    g = torch.Generator().manual_seed(n)
    u = input_signal("white", n, (), generator=g)
    data = IOData(u, torch.zeros(n, 1, dtype=u.dtype), Ts=0.01, intersample="foh")
    problem = _Problem(model, data, "simulation", "estimate", None, "rk4")
    z = problem.initial_z()
    before = peak_rss_mb()
    start = time.perf_counter()
    r, J = problem.residuals_and_jacobian(z)
    seconds = time.perf_counter() - start
    stored = sum(values.numel() * values.element_size() for values, _ in J.groups)
    return {
        "case": f"Duffing simulation-error Jacobian, N = {n}",
        "columns": J.shape[-1],
        "seconds": seconds,
        "peak_memory_growth_mb": peak_rss_mb() - before,
        "jacobian_mb": stored / 2**20,
    }


def jacobian_rows(N: int) -> list[dict]:
    """The Duffing case at N and 2 N samples, each in a fresh process, so that one record's
    peak memory does not hide the other's (a process' peak never falls)."""
    rows = []
    for n in (N, 2 * N):
        context = multiprocessing.get_context("spawn")
        with ProcessPoolExecutor(max_workers=1, mp_context=context) as pool:
            rows.append(pool.submit(_jacobian_in_fresh_process, n).result())
    return rows


def main(argv=None):
    args = build_parser().parse_args(argv)
    out = output_dir(args, NAME)
    torch.set_num_threads(1)
    sets = args.sets or (2 if args.quick else 100)
    N = args.samples or (100 if args.quick else 1000)
    scipy_sets = min(sets, args.scipy_sets or (1 if args.quick else 10))
    n_jac = args.jacobian_samples or (1000 if args.quick else 43500)
    note(f"Duffing: residual and Jacobian over {n_jac} and {2 * n_jac} samples")
    jac = jacobian_rows(n_jac)
    rows = crane_rows(sets, N, scipy_sets)
    markdown = write_table(rows, out / "crane") + "\n\n" + write_table(jac, out / "jacobian")
    (out / f"{NAME}.md").write_text(markdown + "\n")
    finish(out, markdown)
    return rows, jac


if __name__ == "__main__":
    main()
