"""Monte-Carlo check of the FIR least-squares covariance sigma^2 (U'U)^{-1} (eq. 4.101).

One input record (white noise or PRBS) is fixed and thousands of noise realisations are
drawn; all estimates come from ONE batched ``sysid.lls`` call (the shared regressor is
factorised once). The empirical covariance of the estimates is compared with eq. 4.101 (relative
Frobenius error) and with the covariance ``lls`` reports from each data set's own residuals.

Run: ``python -m experiments.sysid_fir_covariance [--quick] [--out DIR]``.
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

NAME = "sysid_fir_covariance"


def build_parser() -> argparse.ArgumentParser:
    """The command line (``--help`` lists it); built without importing torch."""
    parser = experiment_parser(NAME, __doc__.splitlines()[0])
    parser.add_argument("--trials", type=int, default=20_000, help="Monte-Carlo data sets")
    parser.add_argument("--n", type=int, default=1000, help="samples per data set")
    parser.add_argument("--sigma", type=float, default=0.5, help="noise standard deviation")
    return parser


parse_early(__name__, build_parser)

import torch

from experiments._common import plt
from experiments.sysid_fir_inputs import true_fir
from sysid import lls
from sysid.montecarlo import fir_regressor, input_signal, noise_signal, summarize_estimates


def main(argv=None):
    args = build_parser().parse_args(argv)
    out = output_dir(args, NAME)
    trials = 2000 if args.quick else args.trials
    N = 300 if args.quick else args.n
    n_taps = 20
    b = true_fir(n_taps)
    g = torch.Generator().manual_seed(1)
    rows, mats = [], {}
    for kind in progress(("white", "prbs"), "input kinds"):
        u = input_signal(kind, N, generator=g)[:, 0]
        U = fir_regressor(u, n_taps)
        e = noise_signal((trials, N), std=args.sigma, generator=g)
        res = lls(U, U @ b + e)  # one call, `trials` data sets
        predicted = args.sigma**2 * res.normal_inverse  # eq. 4.101
        s = summarize_estimates(
            res.theta,
            b,
            predicted_covariance=predicted,
            standard_errors=res.standard_errors,
            k=1.96,
        )
        reported = res.covariance.mean(0)
        rows.append(
            {
                "input": kind,
                "N": N,
                "trials": trials,
                "rel_frobenius_emp_vs_4.101": s.relative_frobenius_error.item(),
                "rel_frobenius_reported_vs_4.101": (
                    torch.linalg.matrix_norm(reported - predicted)
                    / torch.linalg.matrix_norm(predicted)
                ).item(),
                "max_bias_over_se": (s.bias.abs() / s.bias_standard_error).max().item(),
                "coverage_95_per_tap": ((res.theta - b).abs() <= 1.96 * res.standard_errors)
                .double()
                .mean()
                .item(),
                "sigma2_hat_mean": res.sigma2.mean().item(),
                "cond_UtU": res.condition_number.item(),
            }
        )
        mats[kind] = (s.covariance, predicted)
    markdown = write_table(rows, out / "fir_covariance")
    fig, axes = plt.subplots(2, 3, figsize=(12, 7))
    for r, kind in enumerate(mats):
        emp, pred = (m.detach().cpu().numpy() for m in mats[kind])  # matplotlib takes arrays
        vmax = abs(pred).max()
        axes[r, 0].imshow(emp, cmap="RdBu_r", vmin=-vmax, vmax=vmax)
        axes[r, 0].set_title(f"{kind}: empirical covariance")
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
