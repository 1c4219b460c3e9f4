"""RK4 on the stiff linear system of eq. (6.42) just below and just above its stability limit
(notes Fig. 6.15-6.16).

Typo in eq. (6.42): as typed, the fast block is *multiplied* by eps = 5e-4, which makes x3, x4
slow (eigenvalues ~ 5e-4) and the system not stiff at all. Fig. 6.16 says RK4 with
dt = 1.5e-3 is near its stability limit, which needs fast eigenvalues of magnitude ~ 1/eps:
the block must be divided by eps. ``sysid.zoo.StiffLinear`` implements that reading; its
eigenvalues are (-0.1 +- i)/eps = -200 +- 2000 i (fast) and about 0.025 +- 5.47 i (slow; note
the slightly positive real part: the slow oscillation grows like exp(0.025 t) in the exact
solution too).

The stability limit of RK4 is computed along the ray of each fast eigenvalue (angle 95.7
degrees, where the boundary of the region sits at |z| = 2.95, not at the real-axis value 2.785):
dt* = min over eigenvalues with Re < 0 of r*(arg lambda) / |lambda| = 1.468e-3. The figure's
dt = 1.5e-3 is 2 % above it (|R(lambda dt)| = 1.20 per step), so "close to the limit" holds, but
on the unstable side. The naive real-axis estimate 2.785 / |lambda_max| = 1.385e-3 would be
too pessimistic.

The fast states start on the slow manifold, z' = 0 at t = 0 (as in Fig. 6.16): with
z = (x3, x4) and A_zz z + A_zx x = 0 solved for z. The reference is expm(A t) x0.

Run: ``python -m experiments.stiff_rk4 [--quick] [--out DIR]``.
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

NAME = "stiff_rk4"


def build_parser() -> argparse.ArgumentParser:
    """The command line (``--help`` lists it); built without importing torch."""
    parser = experiment_parser(NAME, "RK4 at its stability limit on the stiff eq. (6.42).")
    parser.add_argument("--t-end", type=float, default=1.0, help="simulated horizon [s]")
    return parser


parse_early(__name__, build_parser)

import numpy as np
import torch

from experiments._common import plt
from experiments.stability_regions import stability_radius
from integrators import odeint, tableau
from sysid.zoo import StiffLinear

EPS = 5e-4


def stability_limit(A: np.ndarray, method: str = "rk4") -> tuple[float, complex]:
    """Largest stable dt of ``method`` for x' = A x, and the eigenvalue that sets it.

    Only eigenvalues with Re < 0 count (a growing mode grows in the exact solution too).
    """
    tab = tableau(method)
    best = (np.inf, 0j)
    for lam in np.linalg.eigvals(A):
        if lam.real >= 0:
            continue
        dt = stability_radius(tab, float(np.angle(lam))) / abs(lam)
        best = min(best, (dt, complex(lam)), key=lambda item: item[0])
    return best


def initial_state(A: np.ndarray, x_slow=(1.0, 1.0)) -> np.ndarray:
    """x0 = (x_slow, z0) with z0 solving A_zz z0 + A_zx x_slow = 0 (z' = 0 at t = 0)."""
    x_slow = np.asarray(x_slow, dtype=np.float64)
    z0 = np.linalg.solve(A[2:, 2:], -A[2:, :2] @ x_slow)
    return np.concatenate([x_slow, z0])


def run(plant: StiffLinear, x0: torch.Tensor, dt: float, t_end: float):
    """RK4 on t_k = k dt and the exact expm solution there; returns (t, x_rk4, x_exact)."""
    t = torch.arange(round(t_end / dt) + 1, dtype=torch.float64) * dt
    with torch.no_grad():
        x = odeint(plant, x0, t, method="rk4").x
        exact = plant.exact(t, x0)
    return t, x, exact


def main(argv=None) -> list[dict]:
    args = build_parser().parse_args(argv)
    out = output_dir(args, NAME)
    t_end = min(args.t_end, 0.5) if args.quick else args.t_end

    plant = StiffLinear(eps=EPS)
    A = plant.matrix().detach().numpy().astype(np.float64)
    dt_star, lam = stability_limit(A)
    x0 = torch.as_tensor(initial_state(A), dtype=torch.float64)
    tab = tableau("rk4")
    cases = {"0.95 dt*": 0.95 * dt_star, "1.05 dt*": 1.05 * dt_star, "notes 1.5e-3": 1.5e-3}
    rows, runs = [], {}
    for label, dt in cases.items():
        t, x, exact = run(plant, x0, dt, t_end)
        runs[label] = (t, x, exact)
        err = (x - exact).abs().amax(dim=-1)
        finite = bool(torch.isfinite(err).all())
        rows.append(
            {
                "case": label,
                "dt": dt,
                "dt_over_dt_star": dt / dt_star,
                "abs_R_fast": float(np.abs(tab.stability_function(lam * dt))),
                "n_steps": len(t) - 1,
                "max_error": float(err.max()) if finite else float("inf"),
                "final_error": float(err[-1]) if finite else float("inf"),
                "stable": bool(np.abs(tab.stability_function(lam * dt)) <= 1.0),
            }
        )
    rows.append(
        {
            "case": "limits",
            "dt": dt_star,
            "dt_over_dt_star": 1.0,
            "abs_R_fast": 1.0,
            "naive_real_axis_dt": stability_radius(tab, np.pi) / abs(lam),
            "fast_eigenvalue_re": lam.real,
            "fast_eigenvalue_im": abs(lam.imag),
        }
    )
    markdown = write_table(rows, out / "stiff_rk4")

    fig, axes = plt.subplots(1, 3, figsize=(15, 4))
    t, x, exact = runs["0.95 dt*"]
    for i, ax in enumerate(axes[:2]):
        for j, color in zip((2 * i, 2 * i + 1), ("C0", "C1"), strict=True):
            ax.plot(t, exact[:, j], color=color, lw=2.5, alpha=0.3)
            ax.plot(t, x[:, j], ":", color=color, label=f"x{j + 1}, RK4 dt = {0.95 * dt_star:.3g}")
        ax.plot([], [], color="0.5", lw=2.5, alpha=0.4, label="exact (wide, pale)")
        ax.set_title(("slow states x1, x2", "fast states x3, x4")[i])
        ax.set_xlabel("t [s]")
        ax.set_ylabel("state")
        ax.legend(fontsize=8)
    for label, (t, x, exact) in runs.items():
        err = (x - exact).abs().amax(dim=-1).clamp_min(1e-17)
        axes[2].semilogy(t, err, label=label)
    axes[2].set_title(f"max-norm error (dt* = {dt_star:.4g})")
    axes[2].set_xlabel("t [s]")
    axes[2].set_ylabel("max |x - x_exact|")
    axes[2].legend(fontsize=8)
    save_figure(fig, out / "stiff_rk4.png")
    finish(out, markdown)
    return rows


if __name__ == "__main__":
    main()
