"""FIR model with 20 taps estimated from six inputs (notes Fig. 4.1, eq. 4.8–4.11, 4.93).

The same 20-tap system is excited by white noise, a random binary signal, a step and a
sinusoid (the notes' four), and a maximum-length binary sequence and a random-phase
multisine, with a slight measurement noise, starting at rest (so the regressor U of eq. 4.8
uses every sample with u_k = 0 for k < 0; without that transient, a step or a sinusoid makes
U'U exactly singular). For each input: the least-squares estimate (eq. 4.11) by ``sysid.lls``, the
condition number of U'U, the parameter error and the fit of the simulated output, both on the
estimation data and on fresh white-noise validation data. The sinusoid (and the step) excite
only one or two directions of the 20-dimensional parameter space: U'U is near singular, the
estimates are poor although the output fit on the estimation data is excellent; the
maximum-length sequence and the multisine excite all directions evenly (U'U best conditioned).

Run: ``python -m experiments.sysid_fir_inputs [--quick] [--out DIR]``.
"""

from __future__ import annotations

import argparse
import warnings

from experiments._common import (
    experiment_parser,
    finish,
    output_dir,
    parse_early,
    save_figure,
    write_table,
)

NAME = "sysid_fir_inputs"


def build_parser() -> argparse.ArgumentParser:
    """The command line (``--help`` lists it); built without importing torch."""
    parser = experiment_parser(NAME, __doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=200, help="samples per experiment")
    parser.add_argument("--noise", type=float, default=0.01, help="measurement noise std")
    return parser


parse_early(__name__, build_parser)

import torch

from experiments._common import plt
from sysid import FIR, fit_percent, lls
from sysid.errors import PoorExcitationWarning
from sysid.montecarlo import fir_regressor, input_signal, simulate_data

KINDS = ("white", "prbs", "step", "sinusoid", "mls", "multisine")


def true_fir(n_taps: int = 20) -> torch.Tensor:
    """A decaying oscillating impulse response ``b_k = 0.8^k cos(0.6 k)`` (k = 0..19)."""
    k = torch.arange(n_taps, dtype=torch.float64)
    return 0.8**k * torch.cos(0.6 * k)


def main(argv=None):
    args = build_parser().parse_args(argv)
    out = output_dir(args, NAME)
    N = args.n  # the study is small; --quick changes nothing but is accepted
    n_taps = 20
    b = true_fir(n_taps)
    model = FIR(n_taps, nk=0)
    g = torch.Generator().manual_seed(0)
    u_val = input_signal("white", N, generator=g)
    val = simulate_data(model, u_val, theta=b)
    rows, fits = [], {}
    for kind in KINDS:
        u = input_signal(kind, N, generator=g, omega=0.3)
        data = simulate_data(model, u, theta=b, noise_std=args.noise, generator=g)
        U = fir_regressor(u[:, 0], n_taps)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            res = lls(U, data.y[:, 0])
        warned = any(issubclass(w.category, PoorExcitationWarning) for w in caught)
        theta = res.theta
        y_est = model.simulate(data, theta=theta)
        fits[kind] = (data, y_est, theta)
        rows.append(
            {
                "input": kind,
                "cond_UtU": res.condition_number.item(),
                "poor_excitation_warning": warned,
                "param_error_rel": (torch.linalg.norm(theta - b) / torch.linalg.norm(b)).item(),
                "fit_estimation_pct": fit_percent(data.y, y_est).item(),
                "fit_validation_pct": fit_percent(val.y, model.simulate(val, theta=theta)).item(),
                "max_std_err": res.standard_errors.max().item(),
            }
        )
    markdown = write_table(rows, out / "fir_inputs")
    fig, axes = plt.subplots(len(KINDS), 3, figsize=(12, 2.4 * len(KINDS)))
    for row, kind in enumerate(KINDS):
        data, y_est, theta = fits[kind]
        axes[row, 0].plot(data.u[:, 0], color="k")
        axes[row, 0].set_ylabel(f"{kind} input")
        axes[row, 1].plot(data.y[:, 0], color="k", label="system")
        axes[row, 1].plot(y_est[:, 0], color="0.6", ls="--", label="model")
        axes[row, 2].plot(b, "ko-", ms=3, label="true")
        axes[row, 2].plot(theta, "o--", color="0.6", ms=3, label="estimated")
    axes[0, 0].set_title("input u")
    axes[0, 1].set_title("output y (estimation data)")
    axes[0, 2].set_title("FIR parameters")
    for ax in axes[-1, :2]:
        ax.set_xlabel("sample k")
    axes[-1, 2].set_xlabel("tap")
    axes[0, 1].legend(fontsize=7)
    axes[0, 2].legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, out / "fir_inputs.png")
    (out / "README.md").write_text(f"# {NAME}\n\n{__doc__}\n\n{markdown}")
    finish(out, markdown)
    return rows


if __name__ == "__main__":
    main()
