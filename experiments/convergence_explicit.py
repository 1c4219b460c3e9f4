"""Observed global error vs dt of every explicit catalogued tableau (notes Fig. 6.10-6.11).

Three problems with closed-form solutions:

* ``linear``: x' = -x, x(0) = 1 on [0, 1] (eq. 6.40, ``sysid.zoo.LinearTestEquation``),
  exact exp(-t). A linear autonomous problem sees only the "tall" rooted trees.
* ``nonautonomous``: x' = -2 t x, x(0) = 1 on [0, 1.5], exact exp(-t^2); the nodes c_i
  matter.
* ``quadratic``: x' = x^2, x(0) = -1 on [0, 1] (eq. 1.44, ``sysid.zoo.Quadratic``), exact
  x0 / (1 - x0 t) = -1 / (1 + t). Nonlinear: every rooted tree contributes.

Every method runs with fixed steps dt = T / N, N = 4 * 2^(k/2) (Dormand-Prince too: its 5th-order
weights b without the embedded row, so ``odeint`` does not switch to step-size control). The
slope of log(error) against log(dt) is fitted by least squares over the 4 finest steps whose
error is above 1e-12 |x(T)| (clear of round-off); it should equal the order (eq. 6.33). A
method stops refining once its error is 10 times below that floor.

Known pre-asymptotic case: Dormand-Prince on ``quadratic``. Its order-5 error constant is
small (the method was tuned for it), so the h^6 term still matters at errors of ~1e-12: the
local slope falls from 7 towards 5 but is still ~5.3 where round-off takes over (from x(0) = 1
instead, the error even changes sign near N = 16). On the other two problems the slope is
5.0 +- 0.1.

Run: ``python -m experiments.convergence_explicit [--quick] [--out DIR]``.
"""

from __future__ import annotations

import argparse
import math

from experiments._common import (
    experiment_parser,
    finish,
    output_dir,
    parse_early,
    progress,
    reference_slope,
    save_figure,
    write_table,
)

NAME = "convergence_explicit"


def build_parser() -> argparse.ArgumentParser:
    """The command line (``--help`` lists it); built without importing torch."""
    parser = experiment_parser(NAME, "Global error vs dt of the explicit RK methods.")
    return parser


parse_early(__name__, build_parser)

import numpy as np
import torch

from experiments._common import plt
from integrators import TABLEAU_NAMES, ButcherTableau, odeint, tableau
from sysid.zoo import LinearTestEquation, Quadratic

ROUND_OFF_FLOOR = 1e-12  # relative to |x(T)|
POINTS_IN_FIT = 4


def fixed_step_tableau(name: str) -> ButcherTableau:
    """The catalogued tableau, stripped of any embedded row so that it runs with fixed steps."""
    tab = tableau(name)
    if tab.b_err is None:
        return tab
    return ButcherTableau(tab.A, tab.b, c=tab.c, order=tab.order, name=f"{name} (fixed step)")


def explicit_methods() -> list[str]:
    """Names of the explicit catalogued tableaus."""
    return [name for name in TABLEAU_NAMES if tableau(name).is_explicit]


def _nonautonomous(t, x):
    """x' = -2 t x (exact solution x0 exp(-t^2))."""
    return -2.0 * t * x


def problems() -> dict[str, tuple]:
    """name -> (f, x0 (1,), t_end, exact x(t_end) (1,))."""
    x0 = torch.ones(1, dtype=torch.float64)
    linear, quadratic = LinearTestEquation(lam=-1.0), Quadratic()
    with torch.no_grad():
        x_lin = linear.exact(torch.tensor([1.0], dtype=torch.float64), x0)[-1]
        x_quad = quadratic.exact(torch.tensor([1.0], dtype=torch.float64), -x0)[-1]
    x_nonaut = x0 * math.exp(-(1.5**2))
    return {
        "linear": (linear, x0, 1.0, x_lin),
        "nonautonomous": (_nonautonomous, x0, 1.5, x_nonaut),
        "quadratic": (quadratic, -x0, 1.0, x_quad),
    }


def global_error(plant, x0, t_end: float, exact, method, n_steps: int) -> float:
    """|x_N - x(T)| after n_steps fixed steps of ``method`` (dt = t_end / n_steps)."""
    t = torch.linspace(0.0, t_end, n_steps + 1, dtype=torch.float64)
    with torch.no_grad():
        x = odeint(plant, x0, t, method=method).x
    return float((x[-1] - exact).abs().max())


def fitted_slope(dts, errors, scale: float = 1.0) -> float:
    """Least-squares slope of log(error) vs log(dt) over the finest POINTS_IN_FIT steps whose
    error is above ROUND_OFF_FLOOR * scale (nan when fewer than two such points)."""
    pairs = [(d, e) for d, e in zip(dts, errors, strict=True) if e > ROUND_OFF_FLOOR * scale]
    pairs = sorted(pairs)[:POINTS_IN_FIT]
    if len(pairs) < 2:
        return float("nan")
    d, e = np.array(pairs).T
    return float(np.polyfit(np.log(d), np.log(e), 1)[0])


def main(argv=None) -> list[dict]:
    args = build_parser().parse_args(argv)
    out = output_dir(args, NAME)
    steps = [round(4 * 2 ** (k / 2)) for k in range(11 if args.quick else 19)]

    rows, curves = [], {}
    setups = problems()
    cases = [(problem, name) for problem in setups for name in explicit_methods()]
    for problem, name in progress(cases, "problem x method"):
        plant, x0, t_end, exact = setups[problem]
        tab = fixed_step_tableau(name)
        scale = float(exact.abs().max())
        errors = []
        for n in steps:
            errors.append(global_error(plant, x0, t_end, exact, tab, n))
            if errors[-1] < 0.1 * ROUND_OFF_FLOOR * scale:
                break  # finer steps only measure round-off
        dts = [t_end / n for n in steps[: len(errors)]]
        slope = fitted_slope(dts, errors, scale=scale)
        curves[(problem, name)] = (dts, errors)
        rows.append(
            {
                "problem": problem,
                "method": name,
                "stages": tab.stages,
                "order": tab.order,
                "fitted_slope": slope,
                "slope_minus_order": slope - tab.order,
                "error_at_finest_dt": errors[-1],
                "finest_dt": dts[-1],
                "n_runs": len(errors),
            }
        )
    markdown = write_table(rows, out / "convergence")

    problem_names = list(problems())
    fig, axes = plt.subplots(1, len(problem_names), figsize=(16, 5))
    fig.suptitle("Global error vs dt of the explicit RK methods (notes Fig. 6.10-6.11)")
    orders = {row["method"]: row["order"] for row in rows}
    for ax, problem in zip(axes, problem_names, strict=True):
        for name in explicit_methods():
            dts, errors = curves[(problem, name)]
            (line,) = ax.loglog(
                dts, np.maximum(errors, 1e-17), "o-", ms=3, label=f"{name} (p = {orders[name]})"
            )
            floor = ROUND_OFF_FLOOR * float(setups[problem][3].abs().max())
            reference_slope(ax, dts, errors, orders[name], floor, color=line.get_color(), lw=1)
        ax.plot([], [], "k:", lw=1, label="reference slope dt^p")
        ax.set_title(problem)
        ax.set_xlabel("dt")
        ax.set_ylabel("|x_N - x(T)|")
        ax.legend(fontsize=7)
    save_figure(fig, out / "convergence.png")
    finish(out, markdown)
    return rows


if __name__ == "__main__":
    main()
