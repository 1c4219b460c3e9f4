"""Fat-tailed noise: least squares vs maximum likelihood with the fair loss (eq. 4.71-4.75).

An ARX(2, 2) system with equation-error noise ``A y = B u + e`` where ``e`` is Gaussian,
Student-t (2 and 3 degrees of freedom), Laplace or contaminated Gaussian (10 % outliers ten
times wider). For every noise law the same batch of data sets is fitted by least squares
(the Gaussian MLE), by the fair-loss MLE (eq. 4.73, alpha = 1 / robust scale of the LS
residuals) and by least absolute deviations (the Laplace MLE). Reported: the mean squared
parameter error E||theta_hat - theta||^2 of each estimator and its ratio to least squares.

A declared study (:class:`sysid.studies.Study`, see :func:`declare`) over the noise laws, one
batched fit per estimator and chunk of data sets; its chunks are kept in ``study/`` (Parquet,
resumable; other options in the same folder are refused: use another ``--out``), its full
report in ``report/``.

Run: ``python -m experiments.sysid_fat_tails [--quick] [--out DIR]``.
"""

from __future__ import annotations

import argparse

from experiments._common import (
    experiment_parser,
    finish,
    output_dir,
    parse_early,
    save_figure,
    study_grid,
    write_table,
)

NAME = "sysid_fat_tails"


def build_parser() -> argparse.ArgumentParser:
    """The command line (``--help`` lists it); built without importing torch."""
    parser = experiment_parser(NAME, __doc__.splitlines()[0])
    parser.add_argument(
        "--trials",
        type=int,
        default=None,
        help="Monte-Carlo data sets per noise law (default 500, 100 with --quick)",
    )
    parser.add_argument(
        "--n", type=int, default=None, help="samples per data set (default 500, 200 with --quick)"
    )
    parser.add_argument("--sigma", type=float, default=0.2, help="noise scale")
    return parser


parse_early(__name__, build_parser)

import functools
import json

import numpy as np
import torch

from experiments._common import plt
from sysid import ARX, IOData, fit
from sysid.montecarlo import input_signal, simulate_data
from sysid.studies import Study

THETA = [-1.2, 0.5, 0.5, 0.3]
MODEL = ARX(2, 2, 1)
NOISES = {
    "gaussian": ("gaussian", {}),
    "student_t(df=3)": ("student_t", {"df": 3}),
    "student_t(df=2)": ("student_t", {"df": 2}),
    "laplace": ("laplace", {}),
    "contaminated": ("contaminated", {"contamination": 0.1, "outlier_scale": 10.0}),
}
GRID = {"noise": list(NOISES), "N": [500], "sigma": [0.2]}
TRIALS, SEED, CHUNK = 500, 3, 100
LOSSES = {"ls": "gaussian", "fair": "fair", "laplace": "laplace"}  # estimator -> MLE loss


def fit_mle(data: IOData, loss: str):
    """The ARX(2, 2) maximum-likelihood fit of ``data`` with ``loss`` (one batched call)."""
    return fit(MODEL, data, method="mle", loss=loss)


ESTIMATORS = {name: functools.partial(fit_mle, loss=loss) for name, loss in LOSSES.items()}


def simulate(point: dict, n: int, generator: torch.Generator) -> IOData:
    """``n`` ARX(2, 2) data sets ``A y = B u + e`` with white-noise input, ``e`` of the law
    ``point["noise"]`` (a key of :data:`NOISES`) and scale ``point["sigma"]``."""
    kind, options = NOISES[point["noise"]]
    u = input_signal("white", point["N"], (n,), generator=generator)
    theta = torch.tensor(THETA, dtype=torch.float64)
    return simulate_data(
        MODEL,
        u,
        theta=theta,
        noise_std=point["sigma"],
        noise="model",
        noise_kind=kind,
        generator=generator,
        **options,
    )


def declare(grid=None, trials=TRIALS, seed=SEED, chunk=CHUNK) -> Study:
    """The declared study: ``grid`` (factors ``noise`` (keys of :data:`NOISES`), ``N``,
    ``sigma``; default :data:`GRID`), ``trials`` per grid point, master ``seed``, ``chunk``
    trials per batched fit (and per ``simulate`` call)."""
    return Study(
        simulate,
        ESTIMATORS,
        grid=study_grid(grid, GRID, {"noise": NOISES}),
        trials=trials,
        seed=seed,
        chunk=chunk,
        block=chunk,
        truth=dict(zip(MODEL.parameter_names(), THETA, strict=True)),
        version=json.dumps({"study": "fat_tails", "theta": THETA}),
    )


def rows_of(done: Study) -> list[dict]:
    """One row per grid point: ``E||theta_hat - theta||^2`` (the sum of the parameters'
    squared RMSE) of each estimator and its ratio to least squares."""
    summary = done.summary()
    mse = (summary["rmse"] ** 2).groupby([summary[f] for f in (*done.factors, "estimator")]).sum()
    rows = []
    for point in done.points:
        key = tuple(point.values())
        m = {name: float(mse[(*key, name)]) for name in ESTIMATORS}
        rows.append(
            {
                "noise": point["noise"],
                "N": point["N"],
                "trials": done.trials,
                "mse_ls": m["ls"],
                "mse_fair": m["fair"],
                "mse_laplace": m["laplace"],
                "fair_over_ls": m["fair"] / m["ls"],
                "laplace_over_ls": m["laplace"] / m["ls"],
            }
        )
    return rows


def main(argv=None):
    args = build_parser().parse_args(argv)
    out = output_dir(args, NAME)
    trials = args.trials or (100 if args.quick else TRIALS)
    N = args.n or (200 if args.quick else GRID["N"][0])
    done = declare({**GRID, "N": [N], "sigma": [args.sigma]}, trials).run(out / "study")
    done.report(out / "report")
    rows = rows_of(done)
    markdown = write_table(rows, out / "fat_tails")
    fig, ax = plt.subplots(figsize=(9, 4))
    x = np.arange(len(rows))
    estimators = [
        ("mse_ls", "least squares", "o"),
        ("mse_fair", "fair MLE (4.73)", "s"),
        ("mse_laplace", "LAD", "^"),
    ]
    # points, not bars: a bar's length means nothing on a log axis
    for i, (key, label, marker) in enumerate(estimators):
        ax.semilogy(x + (i - 1) * 0.15, [r[key] for r in rows], marker, ms=7, label=label)
    ax.set_xticks(x, [r["noise"] for r in rows], fontsize=8)
    ax.grid(axis="y", which="major", color="0.9")
    ax.set_xlabel("noise law")
    ax.set_ylabel("mean squared parameter error")
    ax.legend()
    fig.tight_layout()
    save_figure(fig, out / "fat_tails.png")
    (out / "README.md").write_text(f"# {NAME}\n\n{__doc__}\n\n{markdown}")
    finish(out, markdown)
    return rows


if __name__ == "__main__":
    main()
