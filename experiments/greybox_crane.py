"""Grey-box crane: Monte-Carlo bias, standard errors and coverage of (M, m, L, d) in one fit.

The crane of the course notes (Modelling and Simulation), eq. 2.55-2.70 (cart mass M, load
mass m, rope length L), with viscous friction ``d`` on the cart, driven by a random force on
the cart; the cart position and the rope angle are measured with white noise. All
``trials`` data sets (one input and noise realisation each) are fitted by ONE batched
``sysid.fit`` of a ``GreyBoxModel`` (RK4, Gauss-Newton / Levenberg-Marquardt with exact
forward sensitivities, simulation-error criterion). Reported per parameter: bias, mean
reported standard error against the empirical standard deviation of the estimates, 95 %
coverage of ``estimate +- 1.96 SE``; the mean correlation matrix of the estimates; a figure
of the normalised errors ``(estimate - truth) / SE`` against the standard normal density.

Identifiability: with the force as the only input, the data determine ``L``, ``M + m`` and
``m L`` through the swing dynamics (linearised: x/F = (L s^2 + g) / (s^2 (M L s^2 +
(M + m) g))); a force that barely swings the load, or one that spins it over, leaves ``m``
and ``L`` nearly collinear. The excitation here, a random binary force of +-3 N held 5
samples (0.25 s, a band that covers the swing frequency sqrt(g (M + m) / (M L)) = 3.9
rad/s), swings the load by about one radian: every correlation stays below 0.98.

Run: ``python -m experiments.greybox_crane [--quick] [--out DIR]``.
"""

from __future__ import annotations

import argparse

from experiments._common import (
    experiment_parser,
    finish,
    note,
    output_dir,
    parse_early,
    save_figure,
    write_table,
)

NAME = "greybox_crane"


def build_parser() -> argparse.ArgumentParser:
    """The command line (``--help`` lists it); built without importing torch."""
    parser = experiment_parser(NAME, __doc__.splitlines()[0])
    parser.add_argument(
        "--trials", type=int, default=None, help="data sets (default 1000, 128 with --quick)"
    )
    parser.add_argument(
        "--samples",
        type=int,
        default=None,
        help="samples per data set (default 400, 150 with --quick)",
    )
    parser.add_argument("--amplitude", type=float, default=3.0, help="force amplitude in N")
    parser.add_argument(
        "--hold", type=int, default=5, help="samples each level of the binary force is held"
    )
    parser.add_argument("--seed", type=int, default=0, help="seed of inputs and noise")
    return parser


parse_early(__name__, build_parser)

import math

import numpy as np
import torch

from experiments._common import plt
from experiments.bench_greybox import crane
from sysid import GreyBoxModel, IOData, Param, fit
from sysid.montecarlo import input_signal

TRUE = {"M": 2.0, "m": 0.5, "L": 0.8, "d": 0.4}
#: starting values, 10-20 % off the truth
START = {"M": 2.4, "m": 0.6, "L": 0.7, "d": 0.5}
TS = 0.05
NOISE = (0.002, 0.002)  # m, rad
#: RK4 steps per sample of the data-generating simulation and of the fitted model
TRUTH_SUBSTEPS, MODEL_SUBSTEPS = 4, 1
Z95 = 1.959964


def crane_data(trials: int, N: int, amplitude: float, hold: int, seed: int) -> IOData:
    """``trials`` records: cart position and angle of the true crane under a random binary
    force (linear between samples), plus white noise of standard deviations ``NOISE``."""
    g = torch.Generator().manual_seed(seed)
    u = amplitude * input_signal("prbs", N, (trials,), hold=hold, generator=g)
    truth = GreyBoxModel(crane, dict(TRUE), nx=4, output=[0, 1], substeps=TRUTH_SUBSTEPS)
    y = truth.simulate(IOData(u, torch.zeros(trials, N, 2), Ts=TS, intersample="foh"))
    y = y + torch.tensor(NOISE, dtype=y.dtype) * torch.randn(y.shape, generator=g, dtype=y.dtype)
    return IOData(u, y, Ts=TS, intersample="foh")


def statistics(res) -> tuple[list[dict], np.ndarray, np.ndarray]:
    """Per-parameter rows, the normalised errors (trials, 4) and the mean correlation."""
    names = res.parameter_names
    truth = torch.tensor([TRUE[n] for n in names], dtype=torch.float64)
    est, se = res.theta, res.standard_errors
    z = (est - truth) / se
    trials = est.shape[0]
    rows = []
    for j, n in enumerate(names):
        std = float(est[:, j].std())
        bias = float(est[:, j].mean() - truth[j])
        rows.append(
            {
                "parameter": n,
                "true": float(truth[j]),
                "mean": float(est[:, j].mean()),
                "bias": bias,
                "bias_over_se": bias / float(se[:, j].mean()),
                "bias_over_its_se": bias / (std / math.sqrt(trials)),
                "mean_reported_se": float(se[:, j].mean()),
                "empirical_std": std,
                "se_over_std": float(se[:, j].mean()) / std,
                "coverage_95": float((z[:, j].abs() <= Z95).double().mean()),
            }
        )
    cov = res.covariance
    sd = torch.diagonal(cov, dim1=-2, dim2=-1).sqrt()
    corr = (cov / (sd[..., :, None] * sd[..., None, :])).mean(0)
    return rows, z.numpy(), corr.numpy()


def figure(z: np.ndarray, names: list[str], out) -> None:
    fig, axes = plt.subplots(1, len(names), figsize=(3.2 * len(names), 3.0), sharey=True)
    grid = np.linspace(-4, 4, 200)
    for j, (ax, n) in enumerate(zip(axes, names, strict=True)):
        ax.hist(z[:, j], bins=25, range=(-4, 4), density=True, alpha=0.6, label="estimates")
        ax.plot(grid, np.exp(-0.5 * grid**2) / math.sqrt(2 * math.pi), "k", label="N(0, 1)")
        ax.set_title(f"{n}: (est - true) / SE")
        ax.set_xlabel("normalised error")
    axes[0].set_ylabel("density")
    axes[0].legend(fontsize=8)
    fig.suptitle(f"grey-box crane, {z.shape[0]} data sets in one batched fit")
    save_figure(fig, out / "normalised_errors.png")


def main(argv=None):
    args = build_parser().parse_args(argv)
    out = output_dir(args, NAME)
    trials = args.trials or (128 if args.quick else 1000)
    N = args.samples or (150 if args.quick else 400)
    data = crane_data(trials, N, args.amplitude, args.hold, args.seed)
    note(f"crane: one batched fit of {trials} data sets of {N} samples")
    start = {n: Param(v, min=0.0) for n, v in START.items()}
    model = GreyBoxModel(crane, start, nx=4, output=[0, 1], substeps=MODEL_SUBSTEPS)
    res = fit(model, data)
    rows, z, corr = statistics(res)
    names = res.parameter_names
    summary = [
        {
            "trials": trials,
            "samples": N,
            "amplitude_N": args.amplitude,
            "hold_samples": args.hold,
            "converged": float(res.converged.double().mean()),
            "max_abs_correlation": float(np.abs(corr - np.eye(len(names))).max()),
            "max_angle_rad": float(data.y[..., 1].abs().max()),
        }
    ]
    corr_rows = [
        {"parameter": a, **{b: float(corr[i, j]) for j, b in enumerate(names)}}
        for i, a in enumerate(names)
    ]
    figure(z, names, out)
    tables = [
        write_table(summary, out / "summary"),
        write_table(rows, out / "estimates"),
        write_table(corr_rows, out / "correlation"),
    ]
    finish(out, *tables)
    return summary[0], rows, corr


if __name__ == "__main__":
    main()
