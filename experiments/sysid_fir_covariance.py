"""Monte-Carlo check of the FIR least-squares covariance sigma^2 (U'U)^{-1} (eq. 4.101).

A declared study (:class:`sysid.studies.Study`, see :func:`declare`): per input kind (white
noise or PRBS) ONE input record is fixed and thousands of noise realisations are drawn; each
chunk of data sets is one batched ``sysid.fit(FIR(20, 0), data, method="lls")`` call. The
empirical covariance of the estimates is compared with eq. 4.101 (relative Frobenius error),
``U`` the regressor of the rows whose lags all lie inside the record, and with the covariance
the fit reports from each data set's own residuals.

The study's chunks are kept in ``study/`` (Parquet, resumable; other options in the same
folder are refused: use another ``--out``), its full report in ``report/``.

Run: ``python -m experiments.sysid_fir_covariance [--quick] [--out DIR]``.
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

NAME = "sysid_fir_covariance"


def build_parser() -> argparse.ArgumentParser:
    """The command line (``--help`` lists it); built without importing torch."""
    parser = experiment_parser(NAME, __doc__.splitlines()[0])
    parser.add_argument(
        "--trials",
        type=int,
        default=None,
        help="Monte-Carlo data sets (default 20000, 2000 with --quick)",
    )
    parser.add_argument(
        "--n", type=int, default=None, help="samples per data set (default 1000, 300 with --quick)"
    )
    parser.add_argument("--sigma", type=float, default=0.5, help="noise standard deviation")
    return parser


parse_early(__name__, build_parser)

import functools
import json

import torch

from experiments._common import plt
from experiments.sysid_fir_inputs import true_fir
from sysid import FIR, IOData, fit
from sysid.montecarlo import INPUT_KINDS, fir_regressor, input_signal, noise_signal
from sysid.studies import Study

N_TAPS = 20
MODEL = FIR(N_TAPS, 0)  # y_k = b1 u_k + ... + b20 u_{k-19}
INPUT_SEED = 1  # the fixed input records' seed (the noise comes from the study's seed)
GRID = {"input": ["white", "prbs"], "N": [1000], "sigma": [0.5]}
TRIALS, SEED, CHUNK = 20_000, 1, 1000
ESTIMATORS = {"fir_ls": lambda data: fit(MODEL, data, method="lls")}


@functools.lru_cache(maxsize=16)
def fixed_input(kind: str, N: int) -> torch.Tensor:
    """The input record ``(N,)`` shared by every trial of one grid point (``kind``: an
    :func:`~sysid.montecarlo.input_signal` kind), drawn from :data:`INPUT_SEED`."""
    generator = torch.Generator().manual_seed(INPUT_SEED)
    return input_signal(kind, N, generator=generator)[:, 0]


def regressor(point: dict) -> torch.Tensor:
    """``U`` ``(N - 19, 20)`` of eq. 4.101: the fixed input's FIR regressor (from rest),
    rows whose lags all lie inside the record (those ``fit`` uses)."""
    return fir_regressor(fixed_input(point["input"], point["N"]), N_TAPS)[N_TAPS - 1 :]


def simulate(point: dict, n: int, generator: torch.Generator) -> IOData:
    """``n`` data sets ``y = U b + e`` of the grid point's fixed input, ``e`` white with
    standard deviation ``point["sigma"]`` (the system at rest before sample 0)."""
    u = fixed_input(point["input"], point["N"])
    e = noise_signal((n, point["N"]), std=point["sigma"], generator=generator)
    y = fir_regressor(u, N_TAPS) @ true_fir(N_TAPS) + e
    return IOData(u.expand(n, -1).unsqueeze(-1), y.unsqueeze(-1))


def theory(point: dict, estimator: str) -> torch.Tensor:
    """``sigma^2 (U'U)^-1`` (eq. 4.101), ``(20, 20)``."""
    U = regressor(point)
    return point["sigma"] ** 2 * torch.linalg.inv(U.mT @ U)


def declare(grid=None, trials=TRIALS, seed=SEED, chunk=CHUNK) -> Study:
    """The declared study: ``grid`` (factors ``input``, ``N``, ``sigma``; default
    :data:`GRID`), ``trials`` per grid point, master ``seed``, ``chunk`` trials per batched
    fit (and per ``simulate`` call)."""
    grid = study_grid(grid, GRID, {"input": INPUT_KINDS})
    truth = dict(zip(MODEL.parameter_names(), true_fir(N_TAPS).tolist(), strict=True))
    return Study(
        simulate,
        ESTIMATORS,
        grid=grid,
        trials=trials,
        seed=seed,
        chunk=chunk,
        block=chunk,
        truth=truth,
        theory=theory,
        version=json.dumps({"study": "fir_covariance", "taps": N_TAPS, "input_seed": INPUT_SEED}),
    )


def at(frame, point: dict):
    """The rows of ``frame`` (a study table) at grid point ``point``."""
    mask = True
    for factor, value in point.items():
        mask = mask & (frame[factor] == value)
    return frame[mask]


def rows_of(done: Study) -> list[dict]:
    """One row per grid point: covariance errors, bias, coverage, noise variance."""
    summary = done.summary(level=0.95)
    covariance = done.covariance_summary()
    results = done.results
    rows = []
    for point in done.points:
        s, c, r = (at(frame, point) for frame in (summary, covariance, results))
        c = c.iloc[0]
        U = regressor(point)
        loss = r.drop_duplicates("trial")["loss"].to_numpy()
        rows.append(
            {
                "input": point["input"],
                "N": point["N"],
                "trials": int(c["trials"]),
                "rel_frobenius_emp_vs_4.101": float(c["rel_frobenius_theory"]),
                "rel_frobenius_reported_vs_4.101": float(c["rel_frobenius_reported_vs_theory"]),
                "max_bias_over_se": float((s["bias"].abs() / s["bias_se"]).max()),
                "coverage_95_per_tap": float(s["coverage"].mean()),
                # the loss is half the residual sum of squares: sigma^2 = 2 loss / (M - p)
                "sigma2_hat_mean": float((2 * loss / (U.shape[0] - MODEL.n_params)).mean()),
                "cond_UtU": float(torch.linalg.cond(U.mT @ U)),
            }
        )
    return rows


def main(argv=None):
    args = build_parser().parse_args(argv)
    out = output_dir(args, NAME)
    trials = args.trials or (2000 if args.quick else TRIALS)
    N = args.n or (300 if args.quick else GRID["N"][0])
    grid = {**GRID, "N": [N], "sigma": [args.sigma]}
    done = declare(grid, trials).run(out / "study")
    done.report(out / "report")
    rows = rows_of(done)
    markdown = write_table(rows, out / "fir_covariance")
    fig, axes = plt.subplots(2, 3, figsize=(12, 7))
    for r, point in enumerate(done.points):
        c = done.covariances(r, "fir_ls")
        emp, pred = (c[key].numpy() for key in ("empirical", "theory"))
        vmax = abs(pred).max()
        axes[r, 0].imshow(emp, cmap="RdBu_r", vmin=-vmax, vmax=vmax)
        axes[r, 0].set_title(f"{point['input']}: empirical covariance")
        axes[r, 1].imshow(pred, cmap="RdBu_r", vmin=-vmax, vmax=vmax)
        axes[r, 1].set_title("sigma^2 (U'U)^-1 (eq. 4.101)")
        for ax in axes[r, :2]:
            ax.set_xlabel("tap j")
            ax.set_ylabel("tap i")
        axes[r, 2].plot(emp.diagonal() ** 0.5, "ko", label="empirical std")
        axes[r, 2].plot(pred.diagonal() ** 0.5, "-", color="0.5", label="predicted std")
        axes[r, 2].set_xlabel("tap")
        axes[r, 2].set_ylabel("standard deviation")
        axes[r, 2].legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, out / "fir_covariance.png")
    (out / "README.md").write_text(f"# {NAME}\n\n{__doc__}\n\n{markdown}")
    finish(out, markdown)
    return rows


if __name__ == "__main__":
    main()
