"""Fat-tailed noise: least squares vs maximum likelihood with the fair loss (eq. 4.71-4.75).

An ARX(2, 2) system with equation-error noise ``A y = B u + e`` where ``e`` is Gaussian,
Student-t (2 and 3 degrees of freedom), Laplace or contaminated Gaussian (10 % outliers ten
times wider). For every noise law the same batch of data sets is fitted by least squares
(the Gaussian MLE), by the fair-loss MLE (eq. 4.73, alpha = 1 / robust scale of the LS
residuals) and by least absolute deviations (the Laplace MLE). Reported: the mean squared
parameter error E||theta_hat - theta||^2 of each estimator and its ratio to least squares.

Run: ``python -m experiments.sysid_fat_tails [--quick] [--out DIR]``.
"""

from __future__ import annotations

import argparse

from experiments._common import (
    experiment_parser,
    finish,
    output_dir,
    parse_early,
    progress,
    save_figure,
    write_table,
)

NAME = "sysid_fat_tails"


def build_parser() -> argparse.ArgumentParser:
    """The command line (``--help`` lists it); built without importing torch."""
    parser = experiment_parser(NAME, __doc__.splitlines()[0])
    parser.add_argument(
        "--trials", type=int, default=500, help="Monte-Carlo data sets per noise law"
    )
    parser.add_argument("--n", type=int, default=500, help="samples per data set")
    parser.add_argument("--sigma", type=float, default=0.2, help="noise scale")
    return parser


parse_early(__name__, build_parser)

import numpy as np
import torch

from experiments._common import plt
from sysid import ARX, fit
from sysid.montecarlo import input_signal, simulate_data

THETA = [-1.2, 0.5, 0.5, 0.3]
NOISES = [
    ("gaussian", {}),
    ("student_t", {"df": 3}),
    ("student_t", {"df": 2}),
    ("laplace", {}),
    ("contaminated", {"contamination": 0.1, "outlier_scale": 10.0}),
]


def main(argv=None):
    args = build_parser().parse_args(argv)
    out = output_dir(args, NAME)
    trials = 40 if args.quick else args.trials
    N = 200 if args.quick else args.n
    theta = torch.tensor(THETA, dtype=torch.float64)
    model = ARX(2, 2, 1)
    g = torch.Generator().manual_seed(3)
    rows = []
    for kind, options in progress(NOISES, "noise laws"):
        u = input_signal("white", N, (trials,), generator=g)
        data = simulate_data(
            model,
            u,
            theta=theta,
            noise_std=args.sigma,
            noise="model",
            noise_kind=kind,
            generator=g,
            **options,
        )
        mse = {}
        for loss in ("gaussian", "fair", "laplace"):
            res = fit(model, data, method="mle", loss=loss)
            mse[loss] = ((res.theta - theta) ** 2).sum(-1).mean().item()
        label = kind + (f"(df={options['df']})" if "df" in options else "")
        rows.append(
            {
                "noise": label,
                "N": N,
                "trials": trials,
                "mse_ls": mse["gaussian"],
                "mse_fair": mse["fair"],
                "mse_laplace": mse["laplace"],
                "fair_over_ls": mse["fair"] / mse["gaussian"],
                "laplace_over_ls": mse["laplace"] / mse["gaussian"],
            }
        )
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
