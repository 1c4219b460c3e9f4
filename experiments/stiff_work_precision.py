"""Computation time vs accuracy, implicit vs explicit RK (notes §7.3, Fig. 7.3, eq. 7.24-7.25).

Part 1, Fig. 7.3: Van der Pol, eq. (6.43) (mu = 1, not stiff), x0 = (0, 2) on [0, T], fixed
steps dt = 1e-2 (the notes' value) and a range of dt, explicit midpoint (RK2) and RK4 against
Gauss-Legendre s = 1, 2, 3 and Radau IIA s = 3 (fixed step). Error at T against a scipy DOP853
reference (rtol = atol = 1e-13). On a non-stiff problem the explicit methods reach a given
accuracy faster: every implicit step pays Newton iterations and linear solves (eq. 7.23).

Part 2, stiff Van der Pol (``sysid.zoo.StiffVanDerPol``): y1' = y2,
eps y2' = (1 - y1^2) y2 - y1, y(0) = (2, 0). The Jacobian has an eigenvalue ~ -(y1^2 - 1)/eps,
so dopri5 (real stability interval ~[-3.3, 0]) is stable only for dt <~ 3.3 eps / (y1^2 - 1),
about 1.1 eps at y1 = 2, whatever the tolerance, while L-stable Radau IIA follows the slow
manifold with large steps. Adaptive dopri5 (``odeint(method="dopri5")``) and adaptive Radau IIA
s = 3 (``odeint(method="radau_iia")``) run over a range of tolerances (rtol = tol, atol = tol); the
table gives steps, f evaluations, rejected steps, wall time and the error at T against scipy
``solve_ivp(method="Radau", rtol=1e-12, atol=1e-12)`` (an independent reference).

Wall times are the best of ``--repeats`` runs on this machine and compare rows only.

Run: ``python -m experiments.stiff_work_precision [--quick] [--out DIR] [--repeats N]``.
"""

from __future__ import annotations

import argparse
import time

from experiments._common import (
    experiment_parser,
    finish,
    output_dir,
    parse_early,
    progress,
    save_figure,
    write_table,
)

NAME = "stiff_work_precision"


def build_parser() -> argparse.ArgumentParser:
    """The command line (``--help`` lists it); built without importing torch."""
    parser = experiment_parser(NAME, "Work-precision of implicit vs explicit RK (Fig. 7.3).")
    parser.add_argument(
        "--repeats",
        type=int,
        default=None,
        help="timings are the best of this many runs (default 3, 1 with --quick)",
    )
    return parser


parse_early(__name__, build_parser)

import numpy as np
import torch
from scipy.integrate import solve_ivp

from experiments._common import plt
from integrators import ButcherTableau, gauss_legendre, odeint, radau_iia, tableau
from sysid.zoo import StiffVanDerPol, VanDerPol

IMPLICIT_TOL = dict(rtol=1e-10, atol=1e-12)  # Newton tolerance of the fixed-step runs


def _is_implicit(method) -> bool:
    return isinstance(method, ButcherTableau) and not method.is_explicit


def _count(value) -> int:
    return int(torch.as_tensor(value).sum())


def timed_odeint(plant, x0, t, repeats: int, **options):
    """(solution, best wall time in seconds) of ``odeint`` without autograd."""
    best, sol = float("inf"), None
    for _ in range(repeats):
        start = time.perf_counter()
        with torch.no_grad():
            sol = odeint(plant, x0, t, **options)
        best = min(best, time.perf_counter() - start)
    return sol, best


def scipy_reference(plant, x0: torch.Tensor, t_end: float, method: str, tol: float):
    """x(t_end) from scipy ``solve_ivp`` at tolerance ``tol`` (numpy (nx,))."""

    def rhs(t, x):
        with torch.no_grad():
            return plant(t, torch.from_numpy(x)).numpy()

    res = solve_ivp(rhs, (0.0, t_end), x0.numpy(), method=method, rtol=tol, atol=tol)
    return res.y[:, -1]


def fixed_step_methods() -> dict[str, dict]:
    """label -> odeint options of Fig. 7.3."""
    return {
        "midpoint (ERK2)": dict(method=tableau("midpoint")),
        "rk4 (ERK4)": dict(method="rk4"),
        "gauss_1 (IRK2)": dict(method=gauss_legendre(1), **IMPLICIT_TOL),
        "gauss_2 (IRK4)": dict(method=gauss_legendre(2), **IMPLICIT_TOL),
        "gauss_3 (IRK6)": dict(method=gauss_legendre(3), **IMPLICIT_TOL),
        "radau_3 (IRK5)": dict(method=radau_iia(3), adaptive=False, **IMPLICIT_TOL),
    }


def nonstiff_study(quick: bool, repeats: int) -> list[dict]:
    plant = VanDerPol(mu=1.0)
    x0 = torch.tensor([0.0, 2.0], dtype=torch.float64)
    t_end = 1.0 if quick else 10.0
    ref = scipy_reference(plant, x0, t_end, "DOP853", 1e-13)
    dts = [0.1, 0.02] if quick else [0.2, 0.1, 0.05, 0.02, 1e-2]
    rows = []
    for label, options in progress(fixed_step_methods().items(), "fixed-step methods"):
        for dt in dts:
            t = torch.linspace(0.0, t_end, round(t_end / dt) + 1, dtype=torch.float64)
            sol, seconds = timed_odeint(plant, x0, t, repeats, **options)
            rows.append(
                {
                    "problem": "vanderpol_mu1",
                    "method": label,
                    "implicit": _is_implicit(options["method"]),
                    "dt": dt,
                    "status": int(sol.status),
                    "error": float(np.abs(sol.x[-1].numpy() - ref).max()),
                    "time_s": seconds,
                    "n_f_evals": _count(sol.stats.n_f_evals),
                    "n_newton_iters": _count(sol.stats.n_newton_iters),
                }
            )
    return rows


def stiff_study(quick: bool, repeats: int) -> tuple[list[dict], float]:
    eps = 1e-3 if quick else 1e-4
    plant = StiffVanDerPol(eps=eps)
    x0 = torch.tensor([2.0, 0.0], dtype=torch.float64)
    t_end = 0.5 if quick else 2.0
    ref = scipy_reference(plant, x0, t_end, "Radau", 1e-12)
    t = torch.tensor([0.0, t_end], dtype=torch.float64)
    tols = [1e-5] if quick else [1e-3, 1e-4, 1e-5, 1e-6, 1e-7, 1e-8]
    rows = []
    for method in ("dopri5", "radau_iia"):
        for tol in tols:
            sol, seconds = timed_odeint(
                plant, x0, t, repeats, method=method, rtol=tol, atol=tol, max_steps=1_000_000
            )
            rows.append(
                {
                    "problem": f"stiff_vanderpol_eps{eps:g}",
                    "method": method,
                    "tol": tol,
                    "status": int(sol.status),
                    "error": float(np.abs(sol.x[-1].numpy() - ref).max()),
                    "rel_error": float(np.abs(sol.x[-1].numpy() - ref).max() / np.abs(ref).max()),
                    "n_steps": _count(sol.stats.n_steps),
                    "n_rejected": _count(sol.stats.n_rejected),
                    "n_f_evals": _count(sol.stats.n_f_evals),
                    "n_newton_iters": _count(sol.stats.n_newton_iters),
                    "time_s": seconds,
                }
            )
    return rows, eps


def main(argv=None) -> list[dict]:
    args = build_parser().parse_args(argv)
    out = output_dir(args, NAME)
    repeats = args.repeats or (1 if args.quick else 3)

    nonstiff = nonstiff_study(args.quick, repeats)
    write_table(nonstiff, out / "vanderpol_fixed_step")
    stiff, eps = stiff_study(args.quick, repeats)
    markdown = write_table(stiff, out / "stiff_vanderpol")

    fig, (ax1, ax2, ax3) = plt.subplots(1, 3, figsize=(16, 4.8))
    for label in fixed_step_methods():
        pts = [r for r in nonstiff if r["method"] == label and r["status"] == 0]
        style = "s--" if pts and pts[0]["implicit"] else "o-"
        ax1.loglog([r["error"] for r in pts], [r["time_s"] for r in pts], style, label=label)
    ax1.set_xlabel("error at T")
    ax1.set_ylabel("wall time [s]")
    ax1.set_title("Van der Pol mu = 1, fixed dt (Fig. 7.3)")
    ax1.legend(fontsize=7)
    for method, style in (("dopri5", "o-"), ("radau_iia", "s--")):
        pts = [r for r in stiff if r["method"] == method]
        ax2.loglog([r["error"] for r in pts], [r["n_steps"] for r in pts], style, label=method)
        ax3.loglog([r["error"] for r in pts], [r["time_s"] for r in pts], style, label=method)
    for ax, ylabel in ((ax2, "accepted steps"), (ax3, "wall time [s]")):
        ax.set_xlabel("error at T vs scipy Radau (1e-12)")
        ax.set_ylabel(ylabel)
        ax.set_title(f"stiff Van der Pol, eps = {eps:g}")
        ax.legend()
    save_figure(fig, out / "work_precision.png")
    finish(out, markdown)
    return stiff


if __name__ == "__main__":
    main()
