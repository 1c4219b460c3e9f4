"""Implicit Euler on the stiff linear system eq. (6.42) (notes §7.1.1, Fig. 7.1).

The plant is ``sysid.zoo.StiffLinear(eps=5e-4)``, x' = A x with the fast block scaled by 1/eps
(the notes' eq. 6.42 multiplies by eps, a typo resolved in the plant's docstring: only 1/eps
gives the fast eigenvalues (-0.1 +- i)/eps = -200 +- 2000i that Fig. 6.16 shows). The exact
solution is expm(A t) x0 (``StiffLinear.exact``). As in Fig. 6.16 the fast states start on the
slow manifold, z' = 0 at t = 0: with x = (x1, x2) = (0, 1) that gives z = (x3, x4) =
(1, 0.1) / 1.01.

Implicit Euler (eq. 7.2, ``odeint(method="implicit_euler")``, Newton on eq. 7.3) runs at the
two steps of Fig. 7.1, dt = 2e-2 and 1e-3 (and, in the full run, the steps in between). Its
stability function R(z) = 1 / (1 - z) (eq. 7.11) has |R| < 1 at lambda dt = -4 +- 40i and
-0.2 +- 2i, so it stays bounded at both steps, and its global error falls like dt (eq. 7.7).
For contrast explicit Euler at dt = 2e-2 has |1 + lambda dt| ~ 40 (eq. 7.9) and blows up.

Table columns: ``error_final`` = max_i |x_i(T) - x_i,N|, ``error_max`` = max over the whole
grid, ``max_abs_x`` = largest |x| reached (boundedness), ``abs_R`` = |R(lambda dt)| at the fast
eigenvalues (|lambda| > 100).
The slope of log(error_final) vs log(dt) between the largest and smallest implicit step is
written to ``slope.csv``.

Run: ``python -m experiments.implicit_euler_stiff [--quick] [--out DIR]``.
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

NAME = "implicit_euler_stiff"


def build_parser() -> argparse.ArgumentParser:
    """The command line (``--help`` lists it); built without importing torch."""
    parser = experiment_parser(NAME, "Implicit Euler on the stiff system eq. 6.42 (Fig. 7.1).")
    return parser


parse_early(__name__, build_parser)

import numpy as np
import torch

from experiments._common import plt
from integrators import odeint, tableau
from sysid.zoo import StiffLinear

EPS = 5e-4


def initial_state() -> torch.Tensor:
    """x0 = (0, 1, 1/1.01, 0.1/1.01): fast states at rest (z' = 0), as in Fig. 6.16."""
    return torch.tensor([0.0, 1.0, 1.0 / 1.01, 0.1 / 1.01], dtype=torch.float64)


def fast_growth(method: str, plant: StiffLinear, dt: float) -> float:
    """max |R(lambda dt)| over the fast eigenvalues lambda of A (|lambda| > 100; eq. 7.11)."""
    with torch.no_grad():
        lam = torch.linalg.eigvals(plant.matrix()).numpy()
    fast = lam[np.abs(lam) > 100.0]
    return float(np.abs(tableau(method).stability_function(fast * dt)).max())


def simulate(plant, x0, t_end: float, dt: float, method: str):
    """(grid (N+1,), numerical x (N+1, 4), exact x (N+1, 4), status) for fixed steps dt."""
    n = round(t_end / dt)
    t = torch.linspace(0.0, t_end, n + 1, dtype=torch.float64)
    with torch.no_grad():
        sol = odeint(plant, x0, t, method=method)
        exact = plant.exact(t, x0)
    return t, sol.x, exact, int(sol.status)


def main(argv=None) -> list[dict]:
    args = build_parser().parse_args(argv)
    out = output_dir(args, NAME)
    plant = StiffLinear(eps=EPS)
    x0 = initial_state()
    t_end = 0.4 if args.quick else 2.0
    steps = [2e-2, 1e-3] if args.quick else [2e-2, 1e-2, 5e-3, 2e-3, 1e-3]
    runs = [("implicit_euler", dt) for dt in steps] + [("euler", 2e-2)]

    rows, curves = [], {}
    for method, dt in runs:
        t, x, exact, status = simulate(plant, x0, t_end, dt, method)
        err = (x - exact).abs()
        curves[(method, dt)] = (t, x)
        rows.append(
            {
                "method": method,
                "dt": dt,
                "t_end": t_end,
                "status": status,
                "abs_R": fast_growth(method, plant, dt),
                "error_final": float(err[-1].max()),
                "error_max": float(err.max()),
                "max_abs_x": float(x.abs().max()),
            }
        )
    markdown = write_table(rows, out / "implicit_euler")
    implicit = [r for r in rows if r["method"] == "implicit_euler"]
    coarse, fine = implicit[0], implicit[-1]
    slope = math.log(coarse["error_final"] / fine["error_final"]) / math.log(
        coarse["dt"] / fine["dt"]
    )
    write_table([{"dt_coarse": coarse["dt"], "dt_fine": fine["dt"], "slope": slope}], out / "slope")

    t_ref = torch.linspace(0.0, t_end, 2001, dtype=torch.float64)
    with torch.no_grad():
        ref = plant.exact(t_ref, x0)
    fig, axes = plt.subplots(2, 2, figsize=(11, 7), sharex=True)
    for i, ax in enumerate(axes.ravel()):
        ax.plot(t_ref, ref[:, i], "k-", lw=1, label="exact (expm)")
        for (method, dt), marker in zip(
            [("implicit_euler", steps[0]), ("implicit_euler", steps[-1])], ["o", "s"], strict=True
        ):
            t, x = curves[(method, dt)]
            every = max(1, len(t) // 40)
            ax.plot(t[::every], x[::every, i], marker, ms=3, mfc="none", label=f"{method} dt={dt}")
        ax.set_title(f"x{i + 1}")
        ax.set_xlabel("t [s]")
        ax.set_ylabel(f"x{i + 1}")
    axes[0, 0].legend(fontsize=8)
    fig.suptitle("Implicit Euler on the stiff system (6.42) (Fig. 7.1)")
    save_figure(fig, out / "trajectories.png")

    fig, ax = plt.subplots(figsize=(6, 4))
    ax.loglog(
        [r["dt"] for r in implicit], [r["error_final"] for r in implicit], "o-", label="implicit"
    )
    ax.set_xlabel("dt")
    ax.set_ylabel("|x_N - x(T)|")
    ax.set_title(f"implicit Euler global error (slope {slope:.2f}, eq. 7.7)")
    ax.legend()
    save_figure(fig, out / "error.png")
    finish(out, markdown)
    return rows


if __name__ == "__main__":
    main()
