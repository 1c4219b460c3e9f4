"""Global error vs dt of implicit collocation methods (notes §7.3, Fig. 7.2, eq. 7.20).

Test problem: the logistic equation x' = x (1 - x), x(0) = 0.1 on [0, 8], with closed form
x(t) = 1 / (1 + 9 exp(-t)). It is nonlinear (every rooted tree contributes to the error),
smooth and non-stiff, so fixed steps dt = 8 / N show the classical orders.

1. Fig. 7.2: explicit midpoint (RK2, eq. 6.19, s = 2, order 2) against Gauss-Legendre s = 2
   (order 2 s = 4), N = 4 ... 2048, down to the floor set by round-off and the Newton
   tolerance (the error then stops decreasing, around 1e-14 here; the notes saw 1e-10 -
   1e-11).
2. Observed order of Gauss-Legendre s = 1..5 (order 2 s) and Radau IIA s = 1..5 (2 s - 1):
   least-squares slope of log(error) vs log(dt) over the finest ``POINTS_IN_FIT`` steps whose
   error is above ``ROUND_OFF_FLOOR`` (the asymptotic range clear of round-off). Steps whose
   Newton solve failed (``Solution.status`` != SUCCESS, at the largest dt) are excluded and
   counted in ``n_failed`` (Newton runs with up to 30 iterations so that it converges at
   dt up to ~2 for s >= 3). For s = 5 the whole useful range is 2-3 steps wide in float64,
   so those slopes are rough (the table says how many points were fitted).
3. Newton tolerance: the fixed-step solver stops Newton on a norm scaled by
   ``atol + rtol |x|`` (``integrators.implicit.newton_tolerance``), so ``rtol`` bounds the
   accuracy of fixed-step implicit runs too. The last table reports Gauss s = 3 at N = 64
   (truncation error ~ 2e-13) for a range of ``rtol``: at the default 1e-6 the error is
   already limited by the Newton tolerance, so parts 1-2 use rtol = 1e-10, atol = 1e-12.

Run: ``python -m experiments.convergence_implicit [--quick] [--out DIR]``.
"""

from __future__ import annotations

import argparse
import math

from experiments._common import (
    experiment_parser,
    finish,
    note,
    output_dir,
    parse_early,
    progress,
    readable_log_ticks,
    reference_slope,
    save_figure,
    write_table,
)

NAME = "convergence_implicit"


def build_parser() -> argparse.ArgumentParser:
    """The command line (``--help`` lists it); built without importing torch."""
    parser = experiment_parser(NAME, "Global error vs dt of Gauss-Legendre and Radau IIA.")
    return parser


parse_early(__name__, build_parser)

import numpy as np
import torch

from experiments._common import plt
from integrators import gauss_legendre, odeint, radau_iia, tableau

T_END = 8.0
X0 = 0.1
ROUND_OFF_FLOOR = 1e-12
POINTS_IN_FIT = 4
NEWTON = dict(rtol=1e-10, atol=1e-12, max_iter=30)


def logistic(t, x):
    """x' = x (1 - x)."""
    return x * (1.0 - x)


def exact_final() -> float:
    """x(T) = 1 / (1 + (1/x0 - 1) exp(-T))."""
    return 1.0 / (1.0 + (1.0 / X0 - 1.0) * math.exp(-T_END))


def global_error(method, n_steps: int, **options) -> tuple[float, int]:
    """(|x_N - x(T)|, status) after n_steps fixed steps of ``method``."""
    t = torch.linspace(0.0, T_END, n_steps + 1, dtype=torch.float64)
    x0 = torch.tensor([X0], dtype=torch.float64)
    with torch.no_grad():
        sol = odeint(logistic, x0, t, method=method, **options)
    return abs(float(sol.x[-1, 0]) - exact_final()), int(sol.status)


def fitted_slope(dts, errors) -> tuple[float, int]:
    """Least-squares slope over the finest POINTS_IN_FIT points above ROUND_OFF_FLOOR, and the
    number of points used (nan when fewer than two)."""
    pairs = sorted((d, e) for d, e in zip(dts, errors, strict=True) if e > ROUND_OFF_FLOOR)
    pairs = pairs[:POINTS_IN_FIT]
    if len(pairs) < 2:
        return float("nan"), len(pairs)
    d, e = np.array(pairs).T
    return float(np.polyfit(np.log(d), np.log(e), 1)[0]), len(pairs)


def collocation_runs(stages, steps) -> tuple[list[dict], dict, list[dict]]:
    """Observed orders of Gauss-Legendre and Radau IIA (one row per family and s), the curves
    {(family, s): (dts, errors)} and one row per successful run."""
    rows, curves, points = [], {}, []
    for family, build in (("gauss_legendre", gauss_legendre), ("radau_iia", radau_iia)):
        for s in progress(stages, f"{family} stages"):
            tab = build(s)
            dts, errors, failed = [], [], 0
            for n in steps:
                err, status = global_error(tab, n, adaptive=False, **NEWTON)
                if status != 0:
                    failed += 1
                    continue
                dts.append(T_END / n)
                errors.append(err)
                if err < 0.1 * ROUND_OFF_FLOOR:
                    break  # finer steps only measure round-off
            slope, used = fitted_slope(dts, errors)
            curves[(family, s)] = (dts, errors)
            points += [
                {"family": family, "stages": s, "dt": d, "error": e}
                for d, e in zip(dts, errors, strict=True)
            ]
            rows.append(
                {
                    "family": family,
                    "stages": s,
                    "order": tab.order,
                    "fitted_slope": slope,
                    "slope_minus_order": slope - tab.order,
                    "points_fitted": used,
                    "n_failed": failed,
                    "error_at_finest_dt": errors[-1] if errors else float("nan"),
                    "finest_dt": dts[-1] if dts else float("nan"),
                }
            )
    return rows, curves, points


def main(argv=None) -> list[dict]:
    args = build_parser().parse_args(argv)
    out = output_dir(args, NAME)

    # 1. Fig. 7.2: explicit RK2 vs Gauss-Legendre s = 2.
    fig72_steps = [4 * 2**k for k in range(7 if args.quick else 10)]
    fig72 = []
    note("Fig. 7.2: explicit midpoint vs Gauss-Legendre s = 2")
    fig72_methods = (("midpoint (ERK2)", tableau("midpoint")), ("gauss_2", gauss_legendre(2)))
    for label, method in fig72_methods:
        options = {} if method.is_explicit else NEWTON
        for n in fig72_steps:
            err, status = global_error(method, n, **options)
            fig72.append(
                {"method": label, "n_steps": n, "dt": T_END / n, "error": err, "status": status}
            )
    write_table(fig72, out / "fig72")

    # 2. Observed orders.
    stages = (1, 2, 3) if args.quick else (1, 2, 3, 4, 5)
    steps = [4, 6, 8, 12, 16, 24, 32, 48, 64]
    if not args.quick:
        steps = [3, 4, 5] + steps[1:] + [96, 128]
    rows, curves, points = collocation_runs(stages, steps)
    markdown = write_table(rows, out / "orders")
    write_table(points, out / "errors")

    # 3. Newton tolerance vs accuracy (Gauss s = 3, N = 64: truncation error ~ 2e-13).
    tol_rows = []
    note("Newton tolerance vs accuracy (Gauss s = 3)")
    for rtol in (1e-6, 1e-8, 1e-10, 1e-12, 1e-13):
        err, status = global_error(gauss_legendre(3), 64, rtol=rtol, atol=rtol * 1e-2)
        tol_rows.append(
            {"rtol": rtol, "atol": rtol * 1e-2, "n_steps": 64, "error": err, "status": status}
        )
    write_table(tol_rows, out / "newton_tolerance")

    fig, (ax72, ax_ord) = plt.subplots(1, 2, figsize=(12, 5))
    for label, method in fig72_methods:
        pts = [r for r in fig72 if r["method"] == label and r["status"] == 0]
        dts, errors = [r["dt"] for r in pts], [r["error"] for r in pts]
        (line,) = ax72.loglog(
            dts, [max(e, 1e-17) for e in errors], "o-", label=f"{label} (p = {method.order})"
        )
        reference_slope(ax72, dts, errors, method.order, ROUND_OFF_FLOOR, color=line.get_color())
    ax72.plot([], [], "k:", label="reference slope dt^p")
    ax72.set_title("ERK2 vs IRK4 (Gauss s = 2), logistic eq. (Fig. 7.2)")
    ax72.set_xlabel("dt")
    ax72.set_ylabel("|x_N - x(T)|")
    ax72.legend()
    orders = {(row["family"], row["stages"]): row["order"] for row in rows}
    for (family, s), (dts, errors) in curves.items():
        style = "o-" if family == "gauss_legendre" else "s--"
        p = orders[(family, s)]
        (line,) = ax_ord.loglog(
            dts, np.maximum(errors, 1e-17), style, ms=3, label=f"{family} s={s} (p = {p})"
        )
        reference_slope(ax_ord, dts, errors, p, ROUND_OFF_FLOOR, color=line.get_color(), lw=1)
    ax_ord.plot([], [], "k:", lw=1, label="reference slope dt^p")
    ax_ord.set_title("Gauss-Legendre (order 2s) and Radau IIA (2s-1)")
    ax_ord.set_xlabel("dt")
    readable_log_ticks(ax_ord.xaxis)
    ax_ord.set_ylabel("|x_N - x(T)|")
    ax_ord.legend(fontsize=7)
    save_figure(fig, out / "convergence.png")
    finish(out, markdown)
    return rows


if __name__ == "__main__":
    main()
