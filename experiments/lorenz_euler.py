"""Explicit Euler on the Lorenz system, eq. (6.9), against a high-accuracy reference
(notes Fig. 6.2-6.5).

Parameters as in the notes: sigma = 10, rho = 28, beta = 3 (not the classic 8/3), x0 = [1, 1, 1].
The reference is scipy's DOP853 with rtol = atol = 1e-12 (dense output), independent of our
integrators. For dt = 1e-2, 10^-2.5 and 1e-3 the table gives the *departure time*: the first
t_k where ||x_k - x(t_k)||_inf exceeds 10 % of the reference's amplitude max_t ||x(t)||_inf.
Chaos amplifies the O(dt) global error (eq. 6.7) exponentially, so a smaller dt only postpones
the departure. A second table is the global error at t = 1 for a range of dt (Fig. 6.5) with its
log-log slope over the three finest steps (order 1 expected, eq. 6.7).

Run: ``python -m experiments.lorenz_euler [--quick] [--out DIR]``.
"""

from __future__ import annotations

import argparse

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

NAME = "lorenz_euler"


def build_parser() -> argparse.ArgumentParser:
    """The command line (``--help`` lists it); built without importing torch."""
    parser = experiment_parser(NAME, "Explicit Euler on the Lorenz system (Fig. 6.2-6.5).")
    parser.add_argument("--t-end", type=float, default=20.0, help="horizon of Fig. 6.2-6.4 [s]")
    return parser


parse_early(__name__, build_parser)

import numpy as np
import torch
from scipy.integrate import solve_ivp

from experiments._common import plt
from integrators import odeint
from sysid.zoo import Lorenz

X0 = (1.0, 1.0, 1.0)
FIGURE_DTS = (1e-2, 10**-2.5, 1e-3)
DEPARTURE_FRACTION = 0.1


def reference(plant: Lorenz, t_end: float):
    """DOP853 (rtol = atol = 1e-12) dense solution ``sol(t) -> (3, len(t))`` of the plant."""

    def rhs(t, x):
        with torch.no_grad():
            return plant(t, torch.from_numpy(x)).numpy()

    result = solve_ivp(
        rhs, (0.0, t_end), X0, method="DOP853", rtol=1e-12, atol=1e-12, dense_output=True
    )
    if not result.success:
        raise RuntimeError(f"reference solve failed: {result.message}")
    return result.sol


def euler(plant: Lorenz, dt: float, t_end: float) -> tuple[np.ndarray, np.ndarray]:
    """Explicit Euler (eq. 6.4) on t_k = k dt up to t_end: (t (N+1,), x (N+1, 3)).

    Eager mode (``compile=False``): the one-off ``torch.compile`` that ``"auto"`` would start
    after many steps costs more than it saves in a study of this size.
    """
    t = torch.arange(round(t_end / dt) + 1, dtype=torch.float64) * dt
    with torch.no_grad():
        x0 = torch.tensor(X0, dtype=torch.float64)
        x = odeint(plant, x0, t, method="euler", compile=False).x
    return t.numpy(), x.numpy()


def departure_time(t: np.ndarray, error: np.ndarray, threshold: float) -> float:
    """First t where error > threshold, or inf when it never exceeds it."""
    above = np.flatnonzero(error > threshold)
    return float(t[above[0]]) if above.size else float("inf")


def main(argv=None) -> dict[str, list[dict]]:
    args = build_parser().parse_args(argv)
    out = output_dir(args, NAME)
    t_end = min(args.t_end, 10.0) if args.quick else args.t_end
    plant = Lorenz(sigma=10.0, rho=28.0, beta=3.0)
    note(f"DOP853 reference on [0, {t_end:g}] s")
    ref = reference(plant, t_end)
    amplitude = float(np.abs(ref(np.linspace(0.0, t_end, 20001))).max())
    threshold = DEPARTURE_FRACTION * amplitude

    departure_rows, runs = [], {}
    for dt in progress(FIGURE_DTS, "Euler runs of Fig. 6.2-6.4"):
        t, x = euler(plant, dt, t_end)
        error = np.abs(x - ref(t).T).max(axis=1)
        runs[dt] = (t, x, error)
        departure_rows.append(
            {
                "dt": dt,
                "log10_dt": float(np.log10(dt)),
                "n_steps": len(t) - 1,
                "threshold": threshold,
                "departure_time": departure_time(t, error, threshold),
                "error_at_t1": float(error[np.argmin(np.abs(t - 1.0))]),
            }
        )
    markdown = write_table(departure_rows, out / "departure")

    exponents = np.arange(-2.5, -3.26, -0.25) if args.quick else np.arange(-2.0, -4.01, -0.25)
    error_rows = []
    for log_dt in progress(exponents, "step sizes (global error at t = 1)"):
        dt = 10.0**log_dt
        t, x = euler(plant, dt, 1.0)
        error_rows.append(
            {
                "dt": dt,
                "t_end": float(t[-1]),
                "global_error": float(np.abs(x[-1] - ref(t[-1])).max()),
            }
        )
    # Fit over the 3 finest steps (larger steps are far from the asymptotic range on Lorenz).
    fit = sorted(error_rows, key=lambda r: r["dt"])[:3]
    slope = float(
        np.polyfit(np.log([r["dt"] for r in fit]), np.log([r["global_error"] for r in fit]), 1)[0]
    )
    for row in error_rows:
        row["fitted_slope"] = slope
    markdown += "\n" + write_table(error_rows, out / "global_error")

    fig, axes = plt.subplots(len(FIGURE_DTS) + 1, 1, figsize=(9, 11))
    for ax, dt in zip(axes[:-1], FIGURE_DTS, strict=True):
        t, x, _ = runs[dt]
        reference_states = ref(t)
        for i, color in enumerate(("C0", "C1", "C2")):
            ax.plot(t, reference_states[i], color=color, lw=2.5, alpha=0.3)
            ax.plot(t, x[:, i], color=color, lw=0.8, label=f"x{i + 1}")
        ax.plot([], [], color="0.5", lw=2.5, alpha=0.4, label="DOP853 reference (wide, pale)")
        ax.axvline(
            departure_rows[FIGURE_DTS.index(dt)]["departure_time"],
            color="r",
            ls="--",
            label="departure time",
        )
        ax.set_title(f"explicit Euler, dt = 10^{np.log10(dt):.1f}")
        ax.set_ylabel("state")
    axes[0].legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8)
    axes[-2].set_xlabel("t [s]")
    dts = np.array([r["dt"] for r in error_rows])
    errors = [r["global_error"] for r in error_rows]
    axes[-1].loglog(dts, errors, "o-k", label="Euler at t = 1")
    reference_slope(axes[-1], dts, errors, 1.0, color="C0", label="reference slope dt^1")
    axes[-1].set_xlabel("dt")
    readable_log_ticks(axes[-1].xaxis)
    readable_log_ticks(axes[-1].yaxis)
    axes[-1].set_ylabel("global error")
    axes[-1].legend()
    fig.tight_layout()
    save_figure(fig, out / "lorenz_euler.png")
    finish(out, markdown)
    return {"departure": departure_rows, "global_error": error_rows}


if __name__ == "__main__":
    main()
