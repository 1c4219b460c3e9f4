"""Explicit Euler on x' = -lambda x, lambda = 10: stable iff dt <= 2 / lambda = 0.2 (Fig. 6.6).

Euler's step on eq. (6.10) is x_{k+1} = (1 - lambda dt) x_k (eq. 6.12), so |x_N| grows iff
|1 - lambda dt| > 1, i.e. dt > 2 / lambda (eq. 6.13). The table gives |x_N| after N steps of
``odeint(method="euler")`` next to the closed form |1 - lambda dt|^N |x_0| and the exact
|x(t_N)| = exp(-lambda t_N) |x_0| (eq. 6.11).

Run: ``python -m experiments.euler_stability [--quick] [--out DIR]``.
"""

from __future__ import annotations

import argparse
import math

from experiments._common import (
    experiment_parser,
    finish,
    output_dir,
    parse_early,
    save_figure,
    write_table,
)

NAME = "euler_stability"


def build_parser() -> argparse.ArgumentParser:
    """The command line (``--help`` lists it); built without importing torch."""
    parser = experiment_parser(NAME, "Stability limit dt = 2/lambda of explicit Euler (Fig. 6.6).")
    parser.add_argument("--t-end", type=float, default=3.0, help="simulated horizon [s]")
    return parser


parse_early(__name__, build_parser)

import torch

from experiments._common import plt
from integrators import odeint
from sysid.zoo import LinearTestEquation

LAMBDA = 10.0
DTS = (0.05, 0.1, 0.19, 0.2, 0.21, 0.3)
PLOTTED = (0.05, 0.19, 0.21)


def simulate(dt: float, t_end: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Euler solution of x' = -LAMBDA x, x0 = 1, on t_k = k dt, k = 0..round(t_end / dt)."""
    n_steps = max(1, round(t_end / dt))
    t = torch.arange(n_steps + 1, dtype=torch.float64) * dt
    plant = LinearTestEquation(lam=-LAMBDA)
    with torch.no_grad():
        sol = odeint(plant, torch.ones(1, dtype=torch.float64), t, method="euler")
    return t, sol.x[:, 0]


def main(argv=None) -> list[dict]:
    args = build_parser().parse_args(argv)
    out = output_dir(args, NAME)
    t_end = min(args.t_end, 2.0) if args.quick else args.t_end
    rows, runs = [], {}
    for dt in DTS:
        t, x = simulate(dt, t_end)
        runs[dt] = (t, x)
        n = len(t) - 1
        x_n = abs(float(x[-1]))
        rows.append(
            {
                "dt": dt,
                "lambda_dt": LAMBDA * dt,
                "n_steps": n,
                "t_N": float(t[-1]),
                "abs_x_N": x_n,
                "closed_form_abs_x_N": abs(1.0 - LAMBDA * dt) ** n,
                "exact_abs_x_tN": math.exp(-LAMBDA * float(t[-1])),
                "amplification": abs(1.0 - LAMBDA * dt),
                "grows": x_n > 1.0 + 1e-9,
            }
        )
    markdown = write_table(rows, out / "euler_stability")

    fig, axes = plt.subplots(1, len(PLOTTED), figsize=(12, 3.5), sharey=False)
    fine = torch.linspace(0.0, t_end, 400, dtype=torch.float64)
    for ax, dt in zip(axes, PLOTTED, strict=True):
        t, x = runs[dt]
        ax.plot(fine, torch.exp(-LAMBDA * fine), color="0.6", label="exact (6.11)")
        ax.plot(t, x, "o-", ms=3, color="k", label=f"Euler, dt = {dt}")
        ax.set_title(f"lambda dt = {LAMBDA * dt:.1f}")
        ax.set_xlabel("t [s]")
        ax.legend(fontsize=8)
    axes[0].set_ylabel("x")
    save_figure(fig, out / "euler_stability.png")
    finish(out, markdown)
    return rows


if __name__ == "__main__":
    main()
