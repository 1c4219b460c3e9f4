"""Work-precision diagrams of the explicit Runge-Kutta methods (notes Fig. 6.12-6.13, eq. 6.38).

Error at the final time against the number of right-hand-side evaluations and against wall
time, for every explicit catalogued tableau run with fixed steps over a range of dt, and for
adaptive Dormand-Prince 5(4) (``odeint(method="dopri5")``) over a range of tolerances. Two
problems:

* ``linear``: x' = -x, x(0) = 1 on [0, 5] (eq. 6.40), exact exp(-5);
* ``vanderpol``: eq. (6.43) (mu = 1) from [0, 2] on [0, 10]; reference from scipy's DOP853 with
  rtol = atol = 1e-13 (independent of our solvers).

With N fixed steps of an s-stage method the cost is n = N s evaluations and the error is
c dt^o, so log(error) falls with slope -o against log(n) (eq. 6.37); the table reports the
fitted slope (over the 4 most expensive points above round-off) and, per method, the
evaluations needed to reach 1e-6 and 1e-10 (interpolated in log-log). ``n_f_evals`` is the
solver's own count (the fixed-step solver skips stages that b does not use, e.g. the 7th
stage of Dormand-Prince). Wall times are the best of ``--repeats`` runs on this machine, in
eager mode (``compile=False``; the compiled path is benchmarked elsewhere), and are for
comparison between rows only.

``--quick`` runs the linear problem only, with one timing repeat.

Run: ``python -m experiments.work_precision_explicit [--quick] [--out DIR] [--repeats N]``.
"""

from __future__ import annotations

import argparse
import math
import time

from experiments._common import (
    experiment_parser,
    finish,
    output_dir,
    parse_early,
    progress,
    save_figure,
    write_table,
)

NAME = "work_precision_explicit"


def build_parser() -> argparse.ArgumentParser:
    """The command line (``--help`` lists it); built without importing torch."""
    parser = experiment_parser(NAME, "Work-precision of the explicit RK methods (Fig. 6.13).")
    parser.add_argument("--repeats", type=int, default=3, help="timing repeats (best kept)")
    return parser


parse_early(__name__, build_parser)

import numpy as np
import torch
from scipy.integrate import solve_ivp

from experiments._common import plt
from experiments.convergence_explicit import explicit_methods, fixed_step_tableau
from integrators import odeint
from sysid.zoo import LinearTestEquation, VanDerPol

ROUND_OFF_FLOOR = 1e-12
POINTS_IN_FIT = 4
TARGETS = (1e-6, 1e-10)


def problems(include_vanderpol: bool = True) -> dict[str, tuple]:
    """name -> (plant, x0 (nx,), t_end, reference x(t_end) (nx,) numpy)."""
    cases = {
        "linear": (
            LinearTestEquation(lam=-1.0),
            torch.ones(1, dtype=torch.float64),
            5.0,
            np.array([math.exp(-5.0)]),
        )
    }
    if include_vanderpol:
        vdp = VanDerPol(mu=1.0)
        x0 = torch.tensor([0.0, 2.0], dtype=torch.float64)

        def vdp_numpy(t, x):
            with torch.no_grad():
                return vdp(t, torch.from_numpy(x)).numpy()

        ref = solve_ivp(vdp_numpy, (0.0, 10.0), x0.numpy(), method="DOP853", rtol=1e-13, atol=1e-13)
        cases["vanderpol"] = (vdp, x0, 10.0, ref.y[:, -1])
    return cases


def timed_run(plant, x0, grid, repeats: int, **options) -> tuple[np.ndarray, int, float]:
    """Run ``odeint`` ``repeats`` times: (final state (nx,), f-evaluations, best wall time).

    A run that fails (explicit Euler is unstable on Van der Pol for the largest steps) gives
    an infinite final state, hence an infinite error that the fits and plots leave out.
    """
    best = math.inf
    for _ in range(repeats):
        start = time.perf_counter()
        with torch.no_grad():
            sol = odeint(plant, x0, grid, **options)
        best = min(best, time.perf_counter() - start)
    x_end = sol.x[-1].numpy() if sol.success else np.full(sol.x.shape[-1], np.inf)
    return x_end, int(sol.stats.n_f_evals), best


def fitted_slope(n_evals, errors) -> float:
    """Slope of log(error) vs log(n_evals) over the POINTS_IN_FIT most expensive runs whose
    error is above ROUND_OFF_FLOOR (nan if fewer than two)."""
    pairs = sorted(
        ((n, e) for n, e in zip(n_evals, errors, strict=True) if ROUND_OFF_FLOOR < e < math.inf),
        reverse=True,
    )[:POINTS_IN_FIT]
    if len(pairs) < 2:
        return float("nan")
    n, e = np.array(pairs).T
    return float(np.polyfit(np.log(n), np.log(e), 1)[0])


def evals_for(target: float, n_evals, errors) -> float:
    """f-evaluations needed for error = target, by log-log interpolation (nan if not bracketed)."""
    finite = np.isfinite(errors)
    n_evals, errors = np.asarray(n_evals, float)[finite], np.asarray(errors)[finite]
    order = np.argsort(n_evals)
    n, e = np.log(n_evals[order]), np.log(errors[order])
    for i in range(len(n) - 1):
        lo, hi = e[i], e[i + 1]
        if (lo - math.log(target)) * (hi - math.log(target)) <= 0 and lo != hi:
            w = (math.log(target) - lo) / (hi - lo)
            return float(math.exp(n[i] + w * (n[i + 1] - n[i])))
    return float("nan")


def main(argv=None) -> dict[str, list[dict]]:
    args = build_parser().parse_args(argv)
    out = output_dir(args, NAME)
    repeats = 1 if args.quick else max(1, args.repeats)
    steps = [round(8 * 2 ** (k / 2)) for k in range(11 if args.quick else 19)]
    tolerances = [10.0**-k for k in range(3, 9 if args.quick else 14)]

    points, summary = [], []
    cases = problems(include_vanderpol=not args.quick)
    for problem, (plant, x0, t_end, exact) in cases.items():
        runs = {name: fixed_step_tableau(name) for name in explicit_methods()}
        runs["dopri5 adaptive"] = "dopri5"
        for label, method in progress(runs.items(), f"{problem}: methods", total=len(runs)):
            evals, errors = [], []
            adaptive = method == "dopri5"
            for setting in tolerances if adaptive else steps:
                if adaptive:
                    grid = torch.tensor([0.0, t_end], dtype=torch.float64)
                    opts = dict(method=method, rtol=setting, atol=setting)
                else:
                    grid = torch.linspace(0.0, t_end, setting + 1, dtype=torch.float64)
                    opts = dict(method=method, compile=False)
                x_end, n_f, wall = timed_run(plant, x0, grid, repeats, **opts)
                error = float(np.abs(x_end - exact).max())
                evals.append(n_f)
                errors.append(error)
                points.append(
                    {
                        "problem": problem,
                        "method": label,
                        "setting": setting,
                        "setting_kind": "tol" if adaptive else "n_steps",
                        "n_f_evals": n_f,
                        "error": error,
                        "wall_s": wall,
                    }
                )
                if error < 0.1 * ROUND_OFF_FLOOR:
                    break  # more work only measures round-off
            row = {
                "problem": problem,
                "method": label,
                "order": 5 if adaptive else method.order,
                "stages": 7 if adaptive else method.stages,
                "slope_error_vs_evals": float("nan") if adaptive else fitted_slope(evals, errors),
            }
            for target in TARGETS:
                row[f"evals_for_{target:.0e}"] = evals_for(target, evals, errors)
            summary.append(row)
    markdown = write_table(summary, out / "summary")
    write_table(points, out / "points")

    problem_names = list(cases)
    fig, axes = plt.subplots(2, len(problem_names), figsize=(13, 9), squeeze=False)
    for col, problem in enumerate(problem_names):
        for label in dict.fromkeys(p["method"] for p in points):
            sel = [
                p
                for p in points
                if p["problem"] == problem and p["method"] == label and p["error"] < 1.0
            ]  # errors >= 1 are unstable runs (Euler on Van der Pol at the largest steps)
            err = np.maximum([p["error"] for p in sel], 1e-17)
            style = "s--" if label == "dopri5 adaptive" else "o-"
            name = label if label == "dopri5 adaptive" else f"{label} (fixed dt)"
            axes[0, col].loglog([p["n_f_evals"] for p in sel], err, style, ms=3, label=name)
            axes[1, col].loglog([p["wall_s"] for p in sel], err, style, ms=3, label=name)
        axes[0, col].set_title(f"{problem}: error vs f-evaluations (Fig. 6.13)")
        axes[0, col].set_xlabel("f evaluations")
        axes[1, col].set_title(f"{problem}: error vs wall time")
        axes[1, col].set_xlabel("wall time [s]")
        for ax in axes[:, col]:
            ax.set_ylabel("error at t_end")
            ax.legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, out / "work_precision.png")
    finish(out, markdown)
    return {"summary": summary, "points": points}


if __name__ == "__main__":
    main()
