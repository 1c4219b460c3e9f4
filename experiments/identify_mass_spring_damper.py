"""Main job: from a physical plant to identified models, end to end, in batched calls.

Run with no arguments (``python -m experiments.identify_mass_spring_damper``); ``--quick``
is the seconds-long variant the tests use.

1. Plant: the spring-mass-damper of the zoo, m y'' + xi y' + K y = u (notes eq. 1.26-1.28),
   driven by a random binary force held between samples (zero-order hold, eq. 8.34) and
   simulated with the differentiable fixed-step RK4 integrator.
2. Data: ``trials`` data sets with white output noise, drawn by a declared Monte-Carlo study
   (:class:`sysid.studies.Study`, :func:`declare`): chunks of ``CHUNK`` data sets, each
   simulated in one batched call from a generator derived from the master seed and the
   chunk's coordinates, kept as Parquet files in ``study_black_box/`` and ``study_grey_box/``
   (a rerun resumes; a rerun with other options in the same folder is refused: use another
   ``--out``).
3. Truth: the exact ZOH discretisation (eq. 1.55) is an output-error model
   y = B(q)/F(q) u + e with nb = nf = 2, nk = 1.
4. Black-box identification, one batched call per chunk and estimator: ARX(2, 2, 1) by least
   squares (biased under output noise, notes §4.6) and OE(2, 2, 1) by Gauss-Newton
   (consistent), with bias, standard deviation and the coverage of the reported standard
   errors (the study's summary).
5. Grey-box identification: the physical parameters (m, xi, K) of the zoo plant estimated
   directly by ``fit`` of a ``GreyBoxModel``: Gauss-Newton on the simulation error of the ODE
   with Jacobians from the forward sensitivities of the RK4 recursion (notes eq. 8.17-8.18),
   batched over data sets (a second, smaller study of the same generator; its consistency
   in N is ``experiments/greybox_consistency.py``).
6. Validation: an OE fit of one further data set, its fit on fresh data, residual whiteness
   test, Bode plots of true vs identified.
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
    study_grid,
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

import json
import math

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
from sysid.studies import Study
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


#: Sample time (s) and RK4 steps per sample (h = 0.05 s: relative error ~1e-6, far below the
#: noise) of every simulation and grey-box fit.
TS, SUBSTEPS = 0.1, 2
#: The estimators a study may declare, by the label they carry in the tables.
ARX_LS, OE_GN, GREY_BOX = "ARX least squares", "OE Gauss-Newton", "grey-box (m, xi, K)"
ESTIMATORS = {
    ARX_LS: lambda data: fit(ARX(2, 2, 1, Ts=TS), data),
    OE_GN: lambda data: fit(OE(2, 2, 1, Ts=TS), data, method="gauss_newton"),
    GREY_BOX: lambda data: grey_box_fit(data, SUBSTEPS),
}
#: 3-sigma intervals: the coverage the tables report, 2 Phi(3) - 1.
LEVEL_3SE = math.erf(3 / math.sqrt(2))
_OE = ["b1", "b2", "f1", "f2"]  # OE coefficient order of the tables
CHUNK = 100  # data sets per batched fit, per simulate call and per checkpoint file


def simulate_data(point: dict, n: int, generator: torch.Generator) -> IOData:
    """``n`` data sets of the plant at grid point ``point`` (``N`` samples, output noise std
    ``noise`` m): random binary forces held 3 samples, simulated from rest, plus white noise.
    Shapes: u, y (n, N, 1)."""
    u = input_signal("prbs", point["N"], (n,), hold=3, generator=generator)
    p_true = torch.tensor([TRUE_PHYSICAL[k] for k in PHYSICAL_NAMES], dtype=torch.float64)
    y = simulate_plant(p_true, u, TS, SUBSTEPS)
    noise = torch.randn(y.shape, generator=generator, dtype=y.dtype)
    return IOData(u, y + point["noise"] * noise, Ts=TS)


def truth(point: dict) -> dict[str, float]:
    """True values of every declared parameter: the OE coefficients of the exact ZOH model
    (ARX's a_i are its f_i), and the physical (m, xi, K)."""
    oe = true_oe_parameters(TS)
    return {**oe, "a1": oe["f1"], "a2": oe["f2"], **TRUE_PHYSICAL}


def declare(grid=None, trials=500, seed=0, chunk=CHUNK, estimators=(ARX_LS, OE_GN)) -> Study:
    """The declared Monte-Carlo study of the plant: ``estimators`` (labels of
    :data:`ESTIMATORS`) on ``trials`` data sets per point of ``grid`` (factors ``N`` and
    ``noise``; default ``N = 1000``, ``noise = 0.02``), master ``seed``, ``chunk`` data sets per
    batched fit and per ``simulate`` call."""
    return Study(
        simulate_data,
        {name: ESTIMATORS[name] for name in estimators},
        grid=study_grid(grid, {"N": [1000], "noise": [0.02]}),
        trials=trials,
        seed=seed,
        chunk=chunk,
        block=chunk,
        truth=truth,
        version=json.dumps({"study": NAME, "Ts": TS, "substeps": SUBSTEPS}),
    )


def estimate_rows(study: Study) -> list[dict]:
    """The ``estimates`` table: per estimator and parameter the truth, mean, bias, std, mean
    reported SE and the coverage of the 3-SE intervals (ARX coefficients named in OE order,
    ``b1, b2, f1, f2``, its ``a_i`` being the ``f_i``)."""
    summary = study.summary(LEVEL_3SE)
    rename = {"a1": "f1", "a2": "f2"}
    rows = []
    for estimator, group in summary.groupby("estimator", sort=False):
        sel = group.assign(parameter=group["parameter"].replace(rename))
        if estimator == ARX_LS:
            sel = sel.set_index("parameter").loc[_OE].reset_index()
        for r in sel.itertuples(index=False):
            rows.append(
                {
                    "estimator": estimator,
                    "parameter": r.parameter,
                    "true": float(r.truth),
                    "mean": float(r.mean),
                    "bias": float(r.bias),
                    "std": float(r.std),
                    "mean_reported_se": float(r.mean_se),
                    "coverage_3se": float(r.coverage),
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
    n_grey = min(N, 100 if args.quick else 400)

    note(f"ARX(2, 2, 1) and OE(2, 2, 1) on {trials} data sets of {N} samples")
    black = declare({"N": [N], "noise": [args.noise]}, trials, args.seed).run(
        out / "study_black_box"
    )
    note(f"grey-box Gauss-Newton on {grey_trials} data sets of {n_grey} samples")
    grey = declare(
        {"N": [n_grey], "noise": [args.noise]}, grey_trials, args.seed, estimators=(GREY_BOX,)
    ).run(out / "study_grey_box")
    rows = estimate_rows(black) + estimate_rows(grey)
    markdown = write_table(rows, out / "estimates")

    note("validating an OE fit of one further data set on fresh data")
    gen = torch.Generator().manual_seed(args.seed)
    point = {"N": N, "noise": args.noise}
    data, val = simulate_data(point, 1, gen), simulate_data(point, 1, gen)
    oe = fit(OE(2, 2, 1, Ts=TS), data, method="gauss_newton")
    model = oe.model[0]
    fit_val = float(fit_percent(val.y, model.simulate(val.u).detach()).reshape(-1)[0])
    whiteness = residual_test(oe.residuals.unsqueeze(-1), data.u)
    summary = [
        {
            "trials": trials,
            "samples": N,
            "noise_std": args.noise,
            "oe_converged": float(_converged(black, OE_GN)),
            "grey_converged": float(_converged(grey, GREY_BOX)),
            "validation_fit_percent": fit_val,
            "residual_whiteness_p": float(np.asarray(whiteness.whiteness_pvalue).reshape(-1)[0]),
        }
    ]
    markdown += "\n\n" + write_table(summary, out / "summary")
    _bode(model, true_oe_parameters(TS), TS, out)
    normalised = {
        OE_GN: _normalised_errors(black, OE_GN),
        GREY_BOX: _normalised_errors(grey, GREY_BOX),
    }
    _estimates_figure(rows, normalised, out)
    (out / f"{NAME}.md").write_text(markdown + "\n")
    finish(out, markdown)
    return rows, summary


def _converged(study: Study, estimator: str) -> float:
    """Fraction of the study's data sets on which ``estimator`` converged."""
    results = study.results
    return float(results[results["estimator"] == estimator]["converged"].mean())


def _normalised_errors(study: Study, estimator: str) -> np.ndarray:
    """(estimate - truth) / reported SE of every data set and parameter of ``estimator``,
    flattened (data sets whose fit reported no positive SE are left out)."""
    z = study.normalized_errors()
    return z[z["estimator"] == estimator]["z"].to_numpy()


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


#: Colour and short label of each estimator in the estimates figure.
_ESTIMATOR_STYLE = {ARX_LS: ("C3", "ARX"), OE_GN: ("C0", "OE"), GREY_BOX: ("C2", "grey-box")}


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
