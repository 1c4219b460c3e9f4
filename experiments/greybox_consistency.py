"""Consistency of the grey-box fit: bias, std and coverage of physical parameters vs N.

Plant: a damped, driven pendulum, theta'' = -a sin(theta) - c theta' + b u (a = g/L in 1/s^2,
c the viscous damping in 1/s, b the input gain in 1/s^2 per unit input; nonlinear, so no
black-box linear model is consistent for it), as a :class:`sysid.GreyBoxModel` with its three
parameters free and positive. Each data set: a random binary input held ``HOLD`` samples
(zero-order hold), the pendulum from rest simulated by the model's own ``simulate`` (RK4,
``Ts = TS``), white noise of std ``sigma`` rad on the measured angle.

Estimator: :func:`sysid.fit` of the grey-box model (Gauss-Newton on the simulation error,
Jacobians from the forward sensitivities of the RK4 recursion, the course notes (Modelling and
Simulation) eq. 8.17-8.18), one batched fit per chunk of data sets, from a start 25-30 % off.

A declared study (:class:`sysid.studies.Study`) over the grid ``N`` x ``sigma``: the
maximum-likelihood estimate is consistent with standard deviation falling like
``N^(-1/2)`` (std slope -1/2) and reported standard errors from the Gauss-Newton Hessian whose
95 % intervals cover the truth 95 % of the time. Finished chunks are kept in ``study/``
(Parquet; a rerun resumes, a rerun with other options in the same folder is refused: use
another ``--out``); ``report/`` holds the study's report (tables, bias/std vs N with the
``N^(-1/2)`` reference, coverage vs N, normalised-error histograms and QQ plots, covariance
ellipses of a and b). Also a declaration kind of ``python -m experiments.study``.

Run: ``python -m experiments.greybox_consistency [--quick] [--trials T] [--ns N ...] [--out
DIR]``.
"""

from __future__ import annotations

import argparse

from experiments._common import (
    experiment_parser,
    finish,
    output_dir,
    parse_early,
    study_grid,
    write_table,
)

NAME = "greybox_consistency"


def build_parser() -> argparse.ArgumentParser:
    """The command line (``--help`` lists it); built without importing torch."""
    parser = experiment_parser(NAME, __doc__.splitlines()[0])
    parser.add_argument(
        "--trials", type=int, default=None, help="data sets per N (default 400, 48 with --quick)"
    )
    parser.add_argument(
        "--ns",
        type=int,
        nargs="+",
        default=None,
        help="data lengths N (default 100 200 400 800; 40 160 with --quick)",
    )
    parser.add_argument("--sigma", type=float, default=0.02, help="angle noise std (rad)")
    parser.add_argument("--seed", type=int, default=None, help="master seed (default 5)")
    return parser


parse_early(__name__, build_parser)

import json

import torch

from sysid import GreyBoxModel, IOData, Param, fit
from sysid.montecarlo import input_signal
from sysid.studies import Study

TRUTH = {"a": 4.0, "c": 1.5, "b": 1.0}
START = {"a": 3.0, "c": 1.2, "b": 1.3}
TS, HOLD = 0.2, 2
GRID = {"N": [100, 200, 400, 800], "sigma": [0.02]}
TRIALS, SEED, CHUNK = 400, 5, 100
QUICK = {"N": [40, 160], "trials": 48}


def pendulum(t, x, u, p):
    """Right-hand side (*batch, 2) of the state (theta, theta') under input u (*batch, 1)."""
    theta, omega = x[..., 0], x[..., 1]
    return torch.stack(
        [omega, -p["a"] * torch.sin(theta) - p["c"] * omega + p["b"] * u[..., 0]], -1
    )


def model(values: dict) -> GreyBoxModel:
    """The pendulum measured by its angle, from rest; ``values`` name -> start (positive)."""
    params = {k: Param(v, min=0.0) for k, v in values.items()}
    return GreyBoxModel(pendulum, params, nx=2, output=[0], state_names=("theta", "omega"))


def simulate(point: dict, n: int, generator: torch.Generator) -> IOData:
    """``n`` data sets of ``point["N"]`` samples with angle noise std ``point["sigma"]``:
    u, y of shape (n, N, 1)."""
    u = input_signal("prbs", point["N"], (n,), hold=HOLD, generator=generator)
    y = model(TRUTH).simulate(IOData(u, u, Ts=TS))
    noise = torch.randn(y.shape, generator=generator, dtype=y.dtype)
    return IOData(u, y + point["sigma"] * noise, Ts=TS)


def declare(grid=None, trials=TRIALS, seed=SEED, chunk=CHUNK) -> Study:
    """The declared study: the grey-box fit on ``trials`` data sets per point of ``grid``
    (factors ``N`` and ``sigma``; default :data:`GRID`), master ``seed``, ``chunk`` data sets
    per batched fit and per ``simulate`` call."""
    return Study(
        simulate,
        {"greybox": lambda data: fit(model(START), data)},
        grid=study_grid(grid, GRID),
        trials=trials,
        seed=seed,
        chunk=chunk,
        block=chunk,
        truth=TRUTH,
        version=json.dumps({"study": NAME, "Ts": TS, "hold": HOLD, "start": START}),
    )


def main(argv=None):
    args = build_parser().parse_args(argv)
    out = output_dir(args, NAME)
    trials = args.trials or (QUICK["trials"] if args.quick else TRIALS)
    ns = args.ns or (QUICK["N"] if args.quick else GRID["N"])
    seed = SEED if args.seed is None else args.seed
    study = declare({"N": ns, "sigma": [args.sigma]}, trials, seed).run(out / "study")
    study.report(out / "report", ellipse=("a", "b"))
    summary = study.summary()
    slopes = study.consistency("N").set_index("parameter")
    rows = []
    for parameter, group in summary.groupby("parameter", sort=False):
        rows.append(
            {
                "parameter": parameter,
                "truth": TRUTH[parameter],
                "std_slope": float(slopes.loc[parameter, "std_slope"]),
                "rmse_slope": float(slopes.loc[parameter, "rmse_slope"]),
                "max_bias_over_bias_se": float((group["bias"].abs() / group["bias_se"]).max()),
                "min_coverage_95": float(group["coverage"].min()),
                "max_coverage_95": float(group["coverage"].max()),
                "se_over_std_mean": float(group["se_over_std"].mean()),
                "converged": float(group["converged"].min()),
            }
        )
    markdown = write_table(rows, out / "greybox_consistency")
    (out / "README.md").write_text(f"# {NAME}\n\n{__doc__}\n\n{markdown}")
    finish(out, markdown)
    return study, rows


if __name__ == "__main__":
    main()
