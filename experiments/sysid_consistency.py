"""Bias and variance vs N: ARX least squares vs OE Gauss-Newton (notes §4.6.2-4.6.4).

True system ``y = B/F u + v`` with ``B = 0.5 q^-1 + 0.3 q^-2``, ``F = 1 - 1.2 q^-1 + 0.5 q^-2``.
Two declared Monte-Carlo studies (:class:`sysid.studies.Study`, grid over the record length
N, each chunk of trials one batched fit per estimator):

* ``arx_ls / equation``: equation-error noise ``F y = B u + e`` (the ARX noise model,
  eq. 4.117-4.120): least squares (eq. 4.111-4.112) is consistent (no bias);
* ``arx_ls / output``: white output noise ``y = B/F u + e``: the equation error ``F e`` is
  coloured and correlated with the regressors, so least squares is biased and the bias does
  NOT shrink with N;
* ``oe_gn / output``: the OE model fitted by Gauss-Newton on the simulation error on the same
  output-noise data: consistent, standard deviation falling like 1/sqrt(N);
* ``arx_iv / output``: instrumental variables on the same data (consistent, less efficient).

Each study keeps its finished chunks in ``study_<noise>/`` (Parquet, written atomically), so
a rerun resumes where the last one stopped; a rerun with other options (N values, trials,
sigma) in the same folder is refused: use another ``--out``. The figure shows |bias| and std
of the a1/f1 coefficient vs N with the fitted log-log slopes; ``report_<noise>/`` holds each
study's full report (every parameter, coverage, covariance).

Run: ``python -m experiments.sysid_consistency [--quick] [--out DIR]``.
"""

from __future__ import annotations

import argparse
import math

from experiments._common import (
    experiment_parser,
    finish,
    output_dir,
    parse_early,
    readable_log_ticks,
    save_figure,
    study_grid,
    write_table,
)

NAME = "sysid_consistency"


def build_parser() -> argparse.ArgumentParser:
    """The command line (``--help`` lists it); built without importing torch."""
    parser = experiment_parser(NAME, __doc__.splitlines()[0])
    parser.add_argument(
        "--trials",
        type=int,
        default=None,
        help="Monte-Carlo data sets per N (default 200, 60 with --quick)",
    )
    parser.add_argument("--sigma", type=float, default=0.5, help="noise standard deviation")
    parser.add_argument(
        "--ns",
        type=int,
        nargs="+",
        default=None,
        help="data lengths N (default 250 500 1000 2000 4000 8000; 200 800 with --quick)",
    )
    return parser


parse_early(__name__, build_parser)

import json

import numpy as np
import torch

from experiments._common import plt
from sysid import ARX, OE, fit
from sysid.errors import InputValidationError
from sysid.montecarlo import input_signal, simulate_data
from sysid.studies import Study

B_TRUE = [0.5, 0.3]
F_TRUE = [-1.2, 0.5]
TRUTH = {"a1": F_TRUE[0], "a2": F_TRUE[1], "b1": B_TRUE[0], "b2": B_TRUE[1]}
TRUTH |= {"f1": F_TRUE[0], "f2": F_TRUE[1]}
CASES = [("arx_ls", "equation"), ("arx_ls", "output"), ("arx_iv", "output"), ("oe_gn", "output")]
F1 = {"arx_ls": "a1", "arx_iv": "a1", "oe_gn": "f1"}  # the first denominator coefficient
ESTIMATORS = {
    "arx_ls": lambda data: fit(ARX(2, 2, 1), data),
    "arx_iv": lambda data: fit(ARX(2, 2, 1), data, method="iv"),
    "oe_gn": lambda data: fit(OE(2, 2, 1), data),
}
CHUNK = 50  # trials per batched fit, per checkpoint file and per simulate call


def simulate(noise: str):
    """``simulate(point, n, generator)`` of the study with ``noise`` ("equation": the ARX
    model's own noise ``1/F e``; "output": white output noise)."""
    th_arx = torch.tensor(F_TRUE + B_TRUE, dtype=torch.float64)

    def draw(point, n, generator):
        u = input_signal("white", point["N"], (n,), generator=generator)
        kind = "model" if noise == "equation" else "output"
        return simulate_data(
            ARX(2, 2, 1), u, theta=th_arx, noise_std=point["sigma"], noise=kind, generator=generator
        )

    return draw


GRID = {"N": [250, 500, 1000, 2000, 4000, 8000], "sigma": [0.5]}
TRIALS, SEED = 200, 7


def declare(grid=None, trials=TRIALS, seed=SEED, chunk=CHUNK, noise="output") -> Study:
    """The declared study of one noise kind (``"equation"`` or ``"output"``): the estimators
    of :data:`CASES` for it, ``grid`` (factors ``N``, ``sigma``; default :data:`GRID`),
    ``trials`` per grid point, master ``seed``, ``chunk`` trials per batched fit (and per
    ``simulate`` call)."""
    if noise not in ("equation", "output"):
        raise InputValidationError(f"noise must be 'equation' or 'output', got {noise!r}.")
    names = [name for name, kind in CASES if kind == noise]
    return Study(
        simulate(noise),
        {name: ESTIMATORS[name] for name in names},
        grid=study_grid(grid, GRID),
        trials=trials,
        seed=seed,
        chunk=chunk,
        block=chunk,
        truth=TRUTH,
        version=json.dumps({"study": "consistency", "noise": noise}),
    )


def rows_of(done: Study, noise: str) -> list[dict]:
    """One row per N and estimator: the a1/f1 statistics and the overall spread."""
    summary = done.summary()
    rows = []
    for (N, name), group in summary.groupby(["N", "estimator"], sort=False):
        f1 = group[group["parameter"] == F1[name]].iloc[0]
        rows.append(
            {
                "N": int(N),
                "trials": int(f1["trials"]),
                "sigma": float(f1["sigma"]),
                "estimator": name,
                "noise": noise,
                "bias_f1": float(f1["bias"]),
                "std_f1": float(f1["std"]),
                "bias_se_f1": float(f1["bias_se"]),
                "bias_norm": float(np.linalg.norm(group["bias"])),
                "rms_std": float(np.sqrt((group["std"] ** 2).mean())),
                "mse": float((group["rmse"] ** 2).sum()),
                "converged": float(f1["converged"]),
            }
        )
    return rows


def loglog_slope(ns, values) -> float:
    """Least-squares slope of log(values) vs log(N)."""
    return float(np.polyfit(np.log(ns), np.log(np.abs(values)), 1)[0])


def main(argv=None):
    args = build_parser().parse_args(argv)
    out = output_dir(args, NAME)
    trials = args.trials or (60 if args.quick else TRIALS)
    ns = args.ns or ([200, 800] if args.quick else GRID["N"])
    rows = []
    for noise in ("equation", "output"):
        grid = {"N": ns, "sigma": [args.sigma]}
        done = declare(grid, trials, noise=noise).run(out / f"study_{noise}")
        done.report(out / f"report_{noise}")
        rows += rows_of(done, noise)
    rows.sort(key=lambda r: (r["estimator"], r["noise"], r["N"]))
    summary = []
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for (name, noise), style in zip(CASES, ["o-", "s-", "^-", "d-"], strict=True):
        sel = [r for r in rows if r["estimator"] == name and r["noise"] == noise]
        n = np.array([r["N"] for r in sel])
        bias = np.array([abs(r["bias_f1"]) for r in sel])
        std = np.array([r["std_f1"] for r in sel])
        label = f"{name} ({noise} noise)"
        axes[0].loglog(n, bias, style, label=label)
        axes[1].loglog(n, std, style, label=label)
        summary.append(
            {
                "estimator": name,
                "noise": noise,
                "bias_f1_at_min_N": sel[0]["bias_f1"],
                "bias_f1_at_max_N": sel[-1]["bias_f1"],
                "bias_over_se_at_max_N": abs(sel[-1]["bias_f1"]) / sel[-1]["bias_se_f1"],
                "std_slope": loglog_slope(n, std) if len(n) > 1 else math.nan,
            }
        )
    n_all = np.array(sorted({r["N"] for r in rows}))
    axes[1].loglog(n_all, rows[0]["std_f1"] * np.sqrt(n_all[0] / n_all), "k:", label="1/sqrt(N)")
    axes[0].set_title("|bias| of a1 (ARX) / f1 (OE)")
    axes[1].set_title("standard deviation of a1 / f1")
    axes[0].set_ylabel("|mean estimate - true value|")
    axes[1].set_ylabel("standard deviation over the data sets")
    for ax in axes:
        ax.set_xlabel("N (samples)")
        ax.set_xticks(n_all, [str(n) for n in n_all])  # one label per data length, no minor labels
        ax.minorticks_off()
        readable_log_ticks(ax.yaxis)
        ax.legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, out / "consistency.png")
    write_table(rows, out / "consistency_table")
    markdown = write_table(summary, out / "consistency_summary")
    (out / "README.md").write_text(f"# {NAME}\n\n{__doc__}\n\n{markdown}")
    finish(out, markdown)
    return summary


if __name__ == "__main__":
    main()
