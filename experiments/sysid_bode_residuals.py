"""Bode plots of identified vs true systems and residual tests (MATLAB's ``bode``/``resid``).

Data: the OE system ``y = B/F u + e`` (``B = 0.5 q^-1 + 0.3 q^-2``,
``F = 1 - 1.2 q^-1 + 0.5 q^-2``, white output noise) and a Box-Jenkins system with the same
G and coloured noise ``H = (1 + 0.4 q^-1) / (1 - 0.6 q^-1)``. Fitted: ARX(2, 2) by least
squares and OE(2, 2) by Gauss-Newton on the OE data; BJ(2, 1, 1, 2) and OE(2, 2) on the BJ
data. For each fit: the frequency response against the truth, the simulation fit on fresh
validation data, and the residual test (whiteness of the one-step prediction errors, and
their independence from past inputs). A correct model structure passes both tests; the ARX
model on output-noise data has a biased G and coloured residuals; the OE model on BJ data has
the right G (consistent) but coloured residuals (the noise model is missing).

Run: ``python -m experiments.sysid_bode_residuals [--quick] [--out DIR]``.
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

NAME = "sysid_bode_residuals"


def build_parser() -> argparse.ArgumentParser:
    """The command line (``--help`` lists it); built without importing torch."""
    parser = experiment_parser(NAME, __doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=2000, help="samples of the data set")
    parser.add_argument("--sigma", type=float, default=0.3, help="noise standard deviation")
    return parser


parse_early(__name__, build_parser)

import numpy as np
import torch

from experiments._common import plt
from sysid import ARX, BJ, OE, fit, fit_percent, residual_test
from sysid.montecarlo import input_signal, simulate_data

TH_OE = [0.5, 0.3, -1.2, 0.5]
TH_BJ = [0.5, 0.3, 0.4, -0.6, -1.2, 0.5]


def main(argv=None):
    args = build_parser().parse_args(argv)
    out = output_dir(args, NAME)
    N = 600 if args.quick else args.n
    g = torch.Generator().manual_seed(5)
    true = OE(2, 2, 1)
    true.set_parameter_vector(torch.tensor(TH_OE, dtype=torch.float64))
    bj_true = BJ(2, 1, 1, 2, 1)
    bj_true.set_parameter_vector(torch.tensor(TH_BJ, dtype=torch.float64))
    u, u_val = (input_signal("white", N, generator=g) for _ in range(2))
    oe_data = simulate_data(true, u, noise_std=args.sigma, generator=g)
    bj_data = simulate_data(bj_true, u, noise_std=args.sigma, noise="model", generator=g)
    validation = simulate_data(true, u_val)  # noise-free validation output
    specs = [
        ("ARX(2,2) LS", "OE data", ARX(2, 2, 1), oe_data),
        ("OE(2,2) GN", "OE data", OE(2, 2, 1), oe_data),
        ("OE(2,2) GN", "BJ data", OE(2, 2, 1), bj_data),
        ("BJ(2,1,1,2) GN", "BJ data", BJ(2, 1, 1, 2, 1), bj_data),
    ]
    cases = [
        (name, on, fit(model, data), data)
        for name, on, model, data in progress(specs, "model fits")
    ]
    omega = torch.logspace(-2, np.log10(np.pi), 200, dtype=torch.float64)
    G_true = true.frequency_response(omega)[:, 0]
    rows, tests = [], []
    fig, (ax_mag, ax_ph) = plt.subplots(2, 1, figsize=(8, 7), sharex=True)
    ax_mag.loglog(omega, G_true.abs(), "k-", lw=2.5, label="true G")
    ax_ph.semilogx(omega, np.unwrap(G_true.angle().numpy()) * 180 / np.pi, "k-", lw=2.5)
    for name, on, res, data in cases:
        model = res.model
        G = model.frequency_response(omega)[:, 0]
        label = f"{name} on {on}"
        ax_mag.loglog(omega, G.abs(), "--", label=label)
        ax_ph.semilogx(omega, np.unwrap(G.angle().numpy()) * 180 / np.pi, "--")
        with torch.no_grad():
            e = model.prediction_errors(data)
            y_val = model.simulate(validation)
        rt = residual_test(e, data.u, max_lag=25, alpha=0.01)
        tests.append((label, rt))
        rows.append(
            {
                "model": name,
                "data": on,
                "max_rel_error_G": ((G - G_true).abs() / G_true.abs()).max().item(),
                "fit_validation_pct": fit_percent(validation.y, y_val).item(),
                "whiteness_p": rt.whiteness_pvalue.item(),
                "white": bool(rt.white),
                "independence_p": rt.independence_pvalue.min().item(),
                "independent": bool(rt.independent),
                "stable": bool(model.is_stable()),
            }
        )
    ax_mag.set_ylabel("|G|")
    ax_ph.set_ylabel("phase [deg]")
    ax_ph.set_xlabel("omega [rad/sample]")
    ax_mag.legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, out / "bode.png")
    fig, axes = plt.subplots(len(tests), 2, figsize=(11, 2.3 * len(tests)))
    for i, (label, rt) in enumerate(tests):
        axes[i, 0].stem(rt.lags[1:], rt.autocorrelation[1:], basefmt=" ")
        axes[i, 0].axhspan(-rt.bound, rt.bound, color="0.85")
        axes[i, 0].set_title(f"{label}: residual autocorrelation", fontsize=8)
        axes[i, 0].set_ylabel("correlation")
        axes[i, 1].stem(rt.cross_lags, rt.cross_correlation[0], basefmt=" ")
        axes[i, 1].axhspan(-rt.bound, rt.bound, color="0.85")
        axes[i, 1].set_title("cross-correlation with input (lag > 0: past inputs)", fontsize=8)
    axes[-1, 0].set_xlabel("lag [samples]")
    axes[-1, 1].set_xlabel("lag [samples]")
    fig.tight_layout()
    save_figure(fig, out / "residuals.png")
    markdown = write_table(rows, out / "bode_residuals")
    (out / "README.md").write_text(f"# {NAME}\n\n{__doc__}\n\n{markdown}")
    finish(out, markdown)
    return rows


if __name__ == "__main__":
    main()
