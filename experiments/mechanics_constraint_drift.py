"""Constraint drift of index-1 mechanical models with and without Baumgarte stabilisation.

Notes §2.7, Fig. 2.10: the index-1 form (eq. 2.168) imposes cddot = 0 only, so numerical
errors make c(q(t)) drift (eq. 2.185); Baumgarte stabilisation cddot + 2 alpha cdot +
alpha^2 c = 0 (eq. 2.186) pulls it back. The bowl (eq. 2.170-2.174) and the rigid-rod crane in
Cartesian coordinates (eq. 2.175-2.178) are integrated with RK4 at a coarse step from
consistent initial conditions, for several alpha in one batched simulation (alpha as a
(batch, 1) tensor). Writes ``constraint_drift.csv/.md`` (max |c| over the first and second
half of the run, max |cdot|) and ``constraint_drift.png`` (|c(t)|).
"""

from __future__ import annotations

import argparse

from experiments._common import (
    experiment_parser,
    finish,
    output_dir,
    parse_early,
    save_figure,
    write_table,
)

NAME = "mechanics_constraint_drift"


def build_parser() -> argparse.ArgumentParser:
    """The command line (``--help`` lists it); built without importing torch."""
    parser = experiment_parser(NAME, __doc__.splitlines()[0])
    parser.add_argument("--dt", type=float, default=0.05, help="RK4 step [s]")
    parser.add_argument("--t-end", type=float, default=40.0, help="simulated horizon [s]")
    return parser


parse_early(__name__, build_parser)

import torch

from experiments._common import plt
from integrators import odeint
from sysid.zoo import Bowl, RigidCraneCartesian

DT = torch.float64


def _initial_states(plant, n):
    if isinstance(plant, Bowl):
        q = torch.tensor([[1.0, 0.0, 0.25]], dtype=DT)
        qd = torch.tensor([[0.0, 1.5, 0.0]], dtype=DT)
    else:
        theta = torch.tensor(0.8, dtype=DT)
        q = torch.stack([torch.tensor(0.0, dtype=DT), torch.sin(theta), torch.cos(theta)])[None]
        qd = torch.tensor([[0.3, 0.0, 0.0]], dtype=DT)
    q, qd = plant.project_consistent(q, qd)  # eq. (2.182)
    return torch.cat([q, qd], -1).expand(n, -1)


def run(plant_name, alphas, dt, t_end):
    alpha = torch.tensor(alphas, dtype=DT)[:, None]
    plant = Bowl(baumgarte=alpha) if plant_name == "bowl" else RigidCraneCartesian(baumgarte=alpha)
    x0 = _initial_states(plant, len(alphas))
    t = torch.arange(0.0, t_end + dt / 2, dt, dtype=DT)
    with torch.no_grad():
        sol = odeint(plant, x0, t, method="rk4", compile=False)
        c, cdot = plant.drift(sol.x)
    half = len(t) // 2
    rows = [
        {
            "plant": plant_name,
            "alpha": a,
            "dt": dt,
            "t_end": t_end,
            "max_c_first_half": float(c[i, :half].abs().max()),
            "max_c_second_half": float(c[i, half:].abs().max()),
            "max_cdot": float(cdot[i].abs().max()),
        }
        for i, a in enumerate(alphas)
    ]
    return rows, t, c[..., 0].abs()


def main(argv=None):
    args = build_parser().parse_args(argv)
    if args.quick:
        args.dt, args.t_end = 0.1, 8.0
    out = output_dir(args, NAME)
    alphas = [0.0, 1.0, 4.0]
    rows = []
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8))
    for ax, plant_name in zip(axes, ("bowl", "crane"), strict=True):
        r, t, c = run(plant_name, alphas, args.dt, args.t_end)
        rows += r
        for i, a in enumerate(alphas):
            label = "no stabilisation" if a == 0 else f"Baumgarte alpha={a:g}"
            ax.semilogy(t, c[i].clamp_min(1e-16), label=label)
        ax.set_title(f"{plant_name}: |c(q(t))|, RK4 dt={args.dt:g}")
        ax.set_xlabel("t [s]")
        ax.set_ylabel("constraint residual |c(q)|")
        ax.legend(fontsize=8)
    save_figure(fig, out / "constraint_drift.png")
    finish(out, write_table(rows, out / "constraint_drift"))
    return rows


if __name__ == "__main__":
    main()
