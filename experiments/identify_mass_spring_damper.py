"""Main job: from a physical plant to identified models, end to end, in batched calls.

Run with no arguments (``python -m experiments.identify_mass_spring_damper``); ``--quick``
is the seconds-long variant the tests use.

1. Plant: the spring-mass-damper of the zoo, m y'' + xi y' + K y = u (notes eq. 1.26-1.28),
   driven by a random binary force held between samples (zero-order hold, eq. 8.34) and
   simulated with the differentiable fixed-step RK4 integrator.
2. Data: ``trials`` data sets with white output noise, generated in one batched call from a
   seeded ``torch.Generator``.
3. Truth: the exact ZOH discretisation (eq. 1.55) is an output-error model
   y = B(q)/F(q) u + e with nb = nf = 2, nk = 1.
4. Black-box identification of all data sets in one call each: ARX(2, 2, 1) by least squares
   (biased under output noise, notes §4.6) and OE(2, 2, 1) by Gauss-Newton (consistent),
   with bias, standard deviation and the coverage of the reported standard errors.
5. Grey-box identification: the physical parameters (m, xi, K) of the zoo plant estimated
   directly by ``fit`` of a ``GreyBoxModel``: Gauss-Newton on the simulation error of the ODE
   with Jacobians from the forward sensitivities of the RK4 recursion (notes eq. 8.17-8.18),
   batched over data sets.
6. Validation: fit on fresh data, residual whiteness test, Bode plots of true vs identified.
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

NAME = "identify_mass_spring_damper"


def build_parser() -> argparse.ArgumentParser:
    """The command line (``--help`` lists it); built without importing torch."""
    parser = experiment_parser(NAME, __doc__.splitlines()[0])
    parser.add_argument(
        "--trials",
        type=int,
        default=None,
        help="number of data sets (default 500, 24 with --quick)",
    )
    parser.add_argument(
        "--samples",
        type=int,
        default=None,
        help="samples per data set (default 1000, 200 with --quick)",
    )
    parser.add_argument("--noise", type=float, default=0.02, help="output noise std")
    parser.add_argument("--seed", type=int, default=0, help="seed of inputs and noise")
    return parser


parse_early(__name__, build_parser)

import control
import numpy as np
import torch

from experiments._common import plt
from sysid import (
    ARX,
    OE,
    GreyBoxModel,
    IOData,
    Param,
    fit,
    fit_percent,
    residual_test,
    zoh_discretize,
)
from sysid.montecarlo import input_signal
from sysid.zoo import SpringMassDamper

TRUE_PHYSICAL = {"m": 1.0, "xi": 0.5, "K": 4.0}


PHYSICAL_NAMES = ("m", "xi", "K")


def plant_model(params: dict, substeps: int) -> GreyBoxModel:
    """The zoo plant as a grey-box model measured by its position, from rest."""
    return GreyBoxModel(SpringMassDamper(), params, output=["y"], substeps=substeps)


def simulate_plant(p: torch.Tensor, u: torch.Tensor, Ts: float, substeps: int) -> torch.Tensor:
    """Positions y_k (*batch, N, 1) at t_k = k Ts from rest, for ZOH inputs u (*batch, N, 1)
    and physical parameters p = (m, xi, K) of shape (3,) or (*batch, 3)."""
    values = {k: p[..., j] for j, k in enumerate(PHYSICAL_NAMES)}
    return plant_model(dict(TRUE_PHYSICAL), substeps).simulate(IOData(u, u, Ts=Ts), values)


def true_oe_parameters(Ts: float) -> dict[str, float]:
    """B(q)/F(q) of the exact ZOH discretisation of the continuous plant (eq. 1.55)."""
    m, xi, K = (TRUE_PHYSICAL[k] for k in ("m", "xi", "K"))
    A = torch.tensor([[0.0, 1.0], [-K / m, -xi / m]], dtype=torch.float64)
    B = torch.tensor([[0.0], [1.0 / m]], dtype=torch.float64)
    Ad, Bd = zoh_discretize(A, B, Ts)
    tf = control.ss2tf(control.ss(Ad.numpy(), Bd.numpy(), [[1.0, 0.0]], [[0.0]], Ts))
    num = np.atleast_1d(np.squeeze(tf.num[0][0]))[-2:]  # b1 z + b2 = z (b1 + b2 z^-1)
    den = np.atleast_1d(np.squeeze(tf.den[0][0]))  # z^2 + f1 z + f2
    return {"b1": num[0], "b2": num[1], "f1": den[1] / den[0], "f2": den[2] / den[0]}


def _summarise(label, theta, se, names, truth) -> list[dict]:
    rows = []
    for j, name in enumerate(names):
        true = truth[name]
        est = theta[:, j]
        covered = ((est - true).abs() <= 3 * se[:, j]).double().mean()
        rows.append(
            {
                "estimator": label,
                "parameter": name,
                "true": true,
                "mean": float(est.mean()),
                "bias": float(est.mean() - true),
                "std": float(est.std()),
                "mean_reported_se": float(se[:, j].mean()),
                "coverage_3se": float(covered),
            }
        )
    return rows


def grey_box_fit(data: IOData, substeps: int):
    """``fit`` of the grey-box model over (m, xi, K), all data sets in one batch, from a start
    50 % off, with the positive parameters estimated through their logarithms."""
    start = {"m": 1.5, "xi": 1.0, "K": 3.0}
    model = plant_model({k: Param(v, min=0.0) for k, v in start.items()}, substeps)
    return fit(model, data)


def main(argv=None):
    args = build_parser().parse_args(argv)
    out = output_dir(args, NAME)
    trials = args.trials or (24 if args.quick else 500)
    N = args.samples or (200 if args.quick else 1000)
    grey_trials = min(trials, 3 if args.quick else 50)
    Ts, substeps = 0.1, 2  # RK4 at h = 0.05 s: relative error ~1e-6, far below the noise
    gen = torch.Generator().manual_seed(args.seed)

    note(f"simulating {trials} data sets of {N} samples")
    u = input_signal("prbs", N, (trials,), hold=3, generator=gen)
    p_true = torch.tensor([TRUE_PHYSICAL[k] for k in PHYSICAL_NAMES], dtype=torch.float64)
    y_clean = simulate_plant(p_true, u, Ts, substeps)
    y = y_clean + args.noise * torch.randn(y_clean.shape, generator=gen, dtype=y_clean.dtype)
    data = IOData(u, y, Ts=Ts)
    truth = true_oe_parameters(Ts)

    note("fitting ARX(2, 2, 1) and OE(2, 2, 1) to every data set")
    arx = fit(ARX(2, 2, 1, Ts=Ts), data)
    oe = fit(OE(2, 2, 1, Ts=Ts), data, method="gauss_newton")
    rows = _summarise("ARX least squares", _arx_as_oe(arx), arx.standard_errors, _OE, truth)
    rows += _summarise("OE Gauss-Newton", oe.theta, oe.standard_errors, oe.parameter_names, truth)

    n_grey = min(N, 100 if args.quick else 400)
    note(f"grey-box Gauss-Newton on {grey_trials} data sets of {n_grey} samples")
    grey = grey_box_fit(IOData(u[:grey_trials, :n_grey], y[:grey_trials, :n_grey], Ts=Ts), substeps)
    grey_se = grey.standard_errors
    rows += _summarise(
        "grey-box (m, xi, K)", grey.theta, grey_se, list(PHYSICAL_NAMES), TRUE_PHYSICAL
    )
    markdown = write_table(rows, out / "estimates")

    note("validating on fresh data")
    u_val = input_signal("prbs", N, (1,), hold=3, generator=gen)
    y_val = simulate_plant(p_true, u_val, Ts, substeps)
    val = IOData(u_val, y_val + args.noise * torch.randn(y_val.shape, generator=gen), Ts=Ts)
    model = oe.model[0]
    fit_val = float(fit_percent(val.y, model.simulate(val.u).detach()).reshape(-1)[0])
    whiteness = residual_test(oe.residuals[:1].unsqueeze(-1), u[:1])
    summary = [
        {
            "trials": trials,
            "samples": N,
            "noise_std": args.noise,
            "oe_converged": float(oe.converged.double().mean()),
            "grey_converged": float(grey.converged.double().mean()),
            "validation_fit_percent": fit_val,
            "residual_whiteness_p": float(np.asarray(whiteness.whiteness_pvalue).reshape(-1)[0]),
        }
    ]
    markdown += "\n\n" + write_table(summary, out / "summary")
    _bode(model, truth, Ts, out)
    normalised = {
        "OE Gauss-Newton": _normalised_errors(oe.theta, oe.standard_errors, _OE, truth),
        "grey-box (m, xi, K)": _normalised_errors(
            grey.theta, grey_se, PHYSICAL_NAMES, TRUE_PHYSICAL
        ),
    }
    _estimates_figure(rows, normalised, out)
    (out / f"{NAME}.md").write_text(markdown + "\n")
    finish(out, markdown)
    return rows, summary


_OE = ["b1", "b2", "f1", "f2"]


def _arx_as_oe(arx_result) -> torch.Tensor:
    """ARX parameters in OE order: B(q)/A(q), so f_i = a_i (names a1, a2, b1, b2)."""
    names = arx_result.parameter_names
    col = {n: arx_result.theta[:, names.index(n)] for n in names}
    return torch.stack([col["b1"], col["b2"], col["a1"], col["a2"]], -1)


def _bode(model, truth, Ts, out) -> None:
    omega = np.logspace(-1.5, np.log10(np.pi / Ts) - 0.01, 200)
    true_sys = control.tf([truth["b1"], truth["b2"]], [1.0, truth["f1"], truth["f2"]], Ts)
    g_true = np.asarray(true_sys(np.exp(1j * omega * Ts))).reshape(-1)
    g_est = model.frequency_response(torch.as_tensor(omega)).reshape(-1).numpy()
    fig, (ax_mag, ax_phase) = plt.subplots(2, 1, figsize=(6, 6), sharex=True)
    ax_mag.loglog(omega, np.abs(g_true), "k", label="true (exact ZOH)")
    ax_mag.loglog(omega, np.abs(g_est), "r--", label="OE(2,2,1) estimate")
    ax_phase.semilogx(omega, np.unwrap(np.angle(g_true)) * 180 / np.pi, "k")
    ax_phase.semilogx(omega, np.unwrap(np.angle(g_est)) * 180 / np.pi, "r--")
    ax_mag.set_ylabel("|G|")
    ax_phase.set_ylabel("phase (deg)")
    ax_phase.set_xlabel("omega (rad/s)")
    ax_mag.legend()
    save_figure(fig, out / "bode.png")


def _normalised_errors(theta, se, names, truth) -> np.ndarray:
    """(estimate - truth) / reported SE of every data set and parameter, flattened; data sets
    whose fit reported no finite SE are left out. Shapes: theta, se (trials, p)."""
    true = torch.tensor([truth[n] for n in names], dtype=theta.dtype)
    z = ((theta.detach() - true) / se.detach()).reshape(-1).numpy()
    return z[np.isfinite(z)]


#: Colour and short label of each estimator in the estimates figure.
_ESTIMATOR_STYLE = {
    "ARX least squares": ("C3", "ARX"),
    "OE Gauss-Newton": ("C0", "OE"),
    "grey-box (m, xi, K)": ("C2", "grey-box"),
}


def _estimates_figure(rows: list[dict], normalised: dict[str, np.ndarray], out) -> None:
    """The study's story: top, per parameter, the mean estimate +- the mean reported standard
    error against the truth (ARX biased, OE and grey-box on the truth); bottom, histograms of
    the normalised errors (estimate - truth) / SE against the N(0, 1) density, which they
    follow when the estimator is unbiased and its reported SE is right.

    Args:
        rows: the ``estimates`` table (keys estimator, parameter, true, mean,
            mean_reported_se).
        normalised: estimator -> normalised errors (1-D array), from :func:`_normalised_errors`.
        out: results folder (writes ``estimates.png``).
    """
    parameters = list(dict.fromkeys(r["parameter"] for r in rows))
    fig = plt.figure(figsize=(2.0 * len(parameters), 7.5))
    grid = fig.add_gridspec(2, len(parameters), height_ratios=(1.0, 1.1), hspace=0.45, wspace=0.5)
    fig.suptitle(
        "Top: mean estimate +- mean reported standard error (SE); dashed: truth. "
        "Bottom: normalised errors against N(0, 1)."
    )
    for j, name in enumerate(parameters):
        ax = fig.add_subplot(grid[0, j])
        sel = [r for r in rows if r["parameter"] == name]
        for x, r in enumerate(sel):
            color, short = _ESTIMATOR_STYLE[r["estimator"]]
            ax.errorbar(x, r["mean"], yerr=r["mean_reported_se"], fmt="o", color=color, capsize=4)
        ax.axhline(sel[0]["true"], color="k", ls="--", lw=1)
        ax.set_xticks(range(len(sel)), [_ESTIMATOR_STYLE[r["estimator"]][1] for r in sel])
        ax.set_xlim(-0.6, len(sel) - 0.4)
        ax.set_title(name)
        ax.set_xlabel("estimator", fontsize=8)
        ax.tick_params(axis="y", labelsize=7)
        if j == 0:
            ax.set_ylabel("estimate")
    z_grid = np.linspace(-4.0, 4.0, 200)
    density = np.exp(-0.5 * z_grid**2) / np.sqrt(2.0 * np.pi)
    half = len(parameters) // 2
    spans = (slice(0, half), slice(len(parameters) - half, len(parameters)))
    for span, (label, z) in zip(spans, normalised.items(), strict=True):
        ax = fig.add_subplot(grid[1, span])
        color, short = _ESTIMATOR_STYLE[label]
        ax.hist(
            z,
            bins=np.linspace(-4.0, 4.0, 25),
            density=True,
            color=color,
            alpha=0.6,
            label=f"{short}: {z.size} estimates",
        )
        ax.plot(z_grid, density, "k", lw=1.5, label="N(0, 1) density")
        ax.set_xlabel("(estimate - truth) / reported SE")
        ax.set_ylabel("density")
        ax.set_title(f"{label}: normalised errors", fontsize=9)
        ax.legend(fontsize=7)
    save_figure(fig, out / "estimates.png")


if __name__ == "__main__":
    main()
