"""Tikhonov's theorem in numbers: stiff ODEs eps z' = g(x, z) converge to their DAE limit as
eps -> 0 (notes §5.3, Theorem 8, Fig. 5.1 and 5.3).

Three singularly perturbed families, each simulated for all eps in one batched call (eps is a
(batch, 1) parameter tensor) with adaptive Radau IIA (``odeint(method="radau_iia")``), and its
limit (eq. 5.35) simulated apart:

- ``eq5.36``: x1' = -x1 + x2, eps x2' = x1 - a x2 + u with a = 2 (``SingularlyPerturbedLinear``);
  limit: the DAE (5.37) by ``daeint`` on a ``SemiExplicitDAE`` (its reduced ODE is eq. 5.38).
- ``two-mass m1``: the two-mass system eq. (5.41) with eps = m1 (K = 1e3, rho = 1, m2 = 1).
  Written as x1' = v1, m1 v1' = K (x2 - 2 x1) - rho v1 + u it is eq. (5.33) with the fast
  state z = v1 (dg/dz = -rho, stable); its limit is the ODE (5.43) (= 5.42), simulated by
  Radau IIA from ``TwoMassSystem.ode_543``.
- ``two-mass rho/K``: eq. (5.43) with its small factor rho/K replaced by eps (the formal
  second Tikhonov step of the notes: only the factor in front of x1' shrinks, the slow
  equation 5.43b keeps rho = 1, K = 1e3); limit: the DAE (5.44) by ``daeint``.

Fig. 5.3 compares eq. (5.41) directly with the DAE (5.44) while only m1 shrinks. That is the
composition of the last two steps with rho/K = 1e-3 fixed, so the gap to (5.44) cannot go below
the rho/K-step deviation at eps = 1e-3; the ``fig5.3 saturation`` row of the table measures it.

The input is piecewise constant (as in the figures). Each constant piece is integrated by its
own solver call, restarted at the jump with the state reached: a jump of u is a discontinuity
of the right-hand side, which error control should not have to find by rejections. (Measured:
without the restart, adaptive Radau IIA at rtol = 1e-9, atol = 1e-12 stops with STEP_TOO_SMALL
at the jump for eps = 1e-4 and 1e-6; scipy's ``solve_ivp(method="Radau")`` stops at the same
jump with "Required step size is less than spacing between numbers" for eps = 1e-6.)

Deviation: max over t and over the slow states of |x_eps(t) - x_0(t)| (the slow states are
continuous, so this is uniform in t, initial layer included); fast/algebraic states are compared
only after the layers, i.e. outside [t_j, t_j + w) after each jump t_j (and t = 0), with
w = (eps / lambda0) (2 ln(1/eps) + 5) and lambda0 eps the decay rate of the fast dynamics.
Independent check: all three families are linear, so the exact solutions (ODE and limit) come
from matrix exponentials (scipy ``expm``) piece by piece; the table reports the integration
errors against them (slow states) and the deviation computed from the exact solutions.
Theorem 8 for these linear, exponentially stable fast subsystems gives a deviation O(eps): the
fitted log-log slope (over the three smallest eps, where eps is small against the slow time
scales) is about 1.

Writes ``tikhonov_deviation.csv/.md`` (one row per family and eps), ``tikhonov_slopes.csv/.md``
and ``tikhonov.png``.

Run: ``python -m experiments.dae_tikhonov [--quick] [--out DIR]``.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable
from dataclasses import dataclass
from itertools import pairwise

from experiments._common import (
    experiment_parser,
    finish,
    output_dir,
    parse_early,
    progress,
    save_figure,
    write_table,
)

NAME = "dae_tikhonov"


def build_parser() -> argparse.ArgumentParser:
    """The command line (``--help`` lists it); built without importing torch."""
    parser = experiment_parser(NAME, "Tikhonov convergence eps -> 0 (notes Theorem 8).")
    parser.add_argument(
        "--rtol",
        type=float,
        default=None,
        help="solver rtol, atol = rtol/100 (default 1e-10, 1e-7 with --quick)",
    )
    return parser


parse_early(__name__, build_parser)

import numpy as np
import torch
from scipy.linalg import expm
from torch import nn

from experiments._common import plt
from integrators import SemiExplicitDAE, Status, daeint, odeint
from sysid.zoo import SingularlyPerturbedLinear, TwoMassSystem

DT = torch.float64
A_536 = 2.0  # a of eq. (5.36), Fig. 5.1
K, RHO, M2 = 1e3, 1.0, 1.0  # two-mass parameters of Fig. 5.3
FULL_EPS = (1e-1, 1e-2, 1e-3, 1e-4, 1e-5, 1e-6)


class FastFactorTwoMass(nn.Module):
    """Eq. (5.43) in s = (x1, x2, x2dot) with its factor rho/K in front of x1' replaced by
    ``eps`` ((batch, 1)): eps x1' = x2 - 2 x1 + u/K; eq. (5.43b) unchanged."""

    def __init__(self, plant: TwoMassSystem, eps: torch.Tensor):
        super().__init__()
        self.plant = plant
        self.register_buffer("eps", eps)

    def forward(self, t, s, u=None):
        out = self.plant.ode_543(t, s, u)
        ratio = (self.plant.rho / self.plant.K).to(s)  # undo the factor K / rho of ode_543
        return torch.cat([out[..., :1] * ratio / self.eps.to(s), out[..., 1:]], -1)


@dataclass
class Family:
    """One singularly perturbed family and its limit.

    ``stiff(eps)`` returns the ODE module for eps (batch, 1); ``limit(x0, t, u)`` simulates the
    limit piece with constant input and returns (slow (T, n_slow), fast (T, n_fast), stats);
    ``matrices(eps)`` / ``limit_matrices()`` give the linear models for the exact solution:
    (A, B) of the stiff ODE, and (A0, B0, Cz, Dz) of the limit x' = A0 x + B0 u,
    z = Cz x + Dz u.
    """

    name: str
    eps_quick: tuple
    stiff: Callable
    x0: tuple
    slow: list
    fast: list
    limit: Callable
    matrices: Callable
    limit_matrices: Callable
    lambda0: float
    u_levels: tuple
    piece: float
    piece_quick: float
    slow_label: str
    fast_label: str
    plot_slow: int = 0  # which slow state (position in ``slow``) is drawn


def _no_grad_module(module: nn.Module) -> nn.Module:
    return module.requires_grad_(False)


# ---------------------------------------------------------------- eq. (5.36)
def _stiff_536(eps):
    return _no_grad_module(SingularlyPerturbedLinear(eps=eps, a=A_536))


def _limit_536(x0, t, u, rtol, atol):
    plant = _no_grad_module(SingularlyPerturbedLinear(eps=1.0, a=A_536))
    z_guess = torch.zeros(1, 1, dtype=DT)
    sol = daeint(SemiExplicitDAE(plant.f, plant.g), x0[None], z_guess, t, u=u, rtol=rtol, atol=atol)
    return sol.x[0], sol.z[0], sol


def _matrices_536(eps):
    return np.array([[-1.0, 1.0], [1 / eps, -A_536 / eps]]), np.array([0.0, 1 / eps])


def _limit_matrices_536():
    return (
        np.array([[1 / A_536 - 1]]),
        np.array([1 / A_536]),
        np.array([[1 / A_536]]),
        np.array([1 / A_536]),
    )  # eq. (5.38)


# ---------------------------------------------------------------- two-mass, eps = m1
def _two_mass(m1=1e-2):
    return _no_grad_module(TwoMassSystem(m1=m1, m2=M2, K=K, rho=RHO))


def _limit_m1(x0, t, u, rtol, atol):
    plant = _two_mass()
    sol = odeint(plant.ode_543, x0[None], t, method="radau_iia", u=u, rtol=rtol, atol=atol)
    x1, x2, u0 = sol.x[0, :, 0:1], sol.x[0, :, 1:2], u[:1]
    v1 = K / RHO * (x2 - 2 * x1 + u0 / K)  # x1' of eq. (5.43a)
    return sol.x[0], v1, sol


def _matrices_m1(m1):
    a = np.array(
        [
            [0.0, 0.0, 1.0, 0.0],
            [0.0, 0.0, 0.0, 1.0],
            [-2 * K / m1, K / m1, -RHO / m1, 0.0],
            [K / M2, -K / M2, 0.0, -RHO / M2],
        ]
    )
    return a, np.array([0.0, 0.0, 1 / m1, 0.0])  # eq. (5.41)


def _matrices_543(eps):
    a = np.array([[-2 / eps, 1 / eps, 0.0], [0.0, 0.0, 1.0], [K / M2, -K / M2, -RHO / M2]])
    return a, np.array([1 / (K * eps), 0.0, 0.0])


def _limit_matrices_m1():
    a, b = _matrices_543(RHO / K)
    return a, b, K / RHO * np.array([[-2.0, 1.0, 0.0]]), np.array([1 / RHO])


# ---------------------------------------------------------------- two-mass, eps = rho / K
def _stiff_rho(eps):
    return FastFactorTwoMass(_two_mass(), eps)


def _limit_rho(x0, t, u, rtol, atol):
    plant = _two_mass()
    z_guess = torch.zeros(1, 1, dtype=DT)
    problem = SemiExplicitDAE(plant.f_544, plant.g_544)
    sol = daeint(problem, x0[None], z_guess, t, u=u, rtol=rtol, atol=atol)
    return sol.x[0], sol.z[0], sol


def _limit_matrices_rho():
    # eq. (5.44): x1 = (x2 + u/K) / 2, m2 x2'' = K (x1 - x2) - rho x2'
    a = np.array([[0.0, 1.0], [-K / (2 * M2), -RHO / M2]])
    return a, np.array([0.0, 1 / (2 * M2)]), np.array([[0.5, 0.0]]), np.array([0.5 / K])


FAMILIES = (
    Family(
        "eq5.36",
        (1e-2, 1e-3, 1e-4),
        _stiff_536,
        (1.0, 1.0),
        [0],
        [1],
        _limit_536,
        _matrices_536,
        _limit_matrices_536,
        A_536,
        (0.0, 2.0, -1.0, 1.0),
        2.0,
        1.0,
        "x1",
        "x2",
    ),
    Family(
        "two-mass m1",
        (1e-4, 1e-5, 1e-6),
        lambda eps: _two_mass(eps),
        (1.0, 1.0, 0.0, 0.0),
        [0, 1, 3],
        [2],
        _limit_m1,
        _matrices_m1,
        _limit_matrices_m1,
        RHO,
        (0.0, 1e3, -5e2, 0.0),
        1.0,
        0.25,
        "x2",
        "x1dot",
        1,
    ),
    Family(
        "two-mass rho/K",
        (1e-4, 1e-5, 1e-6),
        _stiff_rho,
        (1.0, 1.0, 0.0),
        [1, 2],
        [0],
        _limit_rho,
        _matrices_543,
        _limit_matrices_rho,
        2.0,
        (0.0, 1e3, -5e2, 0.0),
        1.0,
        0.25,
        "x2",
        "x1",
    ),
)


def piece_grids(piece: float, n_pieces: int, n_per_piece: int) -> list[torch.Tensor]:
    """Output grids of the constant-input pieces [j piece, (j + 1) piece]."""
    return [
        torch.linspace(j * piece, (j + 1) * piece, n_per_piece + 1, dtype=DT)
        for j in range(n_pieces)
    ]


def join_pieces(pieces: list[torch.Tensor]) -> torch.Tensor:
    """Concatenate per-piece outputs (..., T_j, n) along time; at a shared boundary the value
    of the later piece is kept (right-continuous, like the input)."""
    kept = [p[..., :-1, :] for p in pieces[:-1]] + [pieces[-1]]
    return torch.cat(kept, -2)


def exact_pieces(a, b, x0, levels, grids, c=None, d=None):
    """Exact solution of x' = a x + b u (and z = c x + d u) with u constant on each piece, by
    the matrix exponential of the augmented matrix [[a, b u], [0, 0]]; (T, n) per piece."""
    n = a.shape[0]
    x = np.asarray(x0, dtype=np.float64)
    xs, zs = [], []
    for level, grid in zip(levels, grids, strict=True):
        aug = np.zeros((n + 1, n + 1))
        aug[:n, :n], aug[:n, n] = a, b * level
        tau = (grid - grid[0]).numpy()
        traj = np.stack([(expm(aug * s) @ np.append(x, 1.0))[:n] for s in tau])
        xs.append(torch.as_tensor(traj))
        if c is not None:
            zs.append(torch.as_tensor(traj @ c.T + d * level))
        x = traj[-1]
    return xs, zs


def layer_mask(t: torch.Tensor, jumps, eps: float, lambda0: float) -> torch.Tensor:
    """True where t lies outside every fast layer [t_j, t_j + w), w = (eps / lambda0)
    (2 ln(1/eps) + 5) (after w the layer has decayed to about eps^2 e^-5 of its size)."""
    width = eps / lambda0 * (2 * math.log(1 / eps) + 5)
    inside = torch.zeros_like(t, dtype=torch.bool)
    for tj in jumps:
        inside |= (t >= tj) & (t < tj + width)
    return ~inside


def fitted_slope(eps, dev) -> float:
    """Least-squares slope of log10(dev) against log10(eps)."""
    return float(np.polyfit(np.log10(eps), np.log10(dev), 1)[0])


def run_family(fam: Family, eps_values, n_pieces, n_per_piece, piece, rtol, atol):
    """Simulate the family for all eps at once (pieces of length ``piece``) and its limit;
    returns the table rows, the time grid, the curves and the limit curves."""
    eps = torch.tensor(eps_values, dtype=DT)[:, None]
    model = fam.stiff(eps)
    levels = fam.u_levels[:n_pieces]
    grids = piece_grids(piece, n_pieces, n_per_piece)
    x = torch.tensor(fam.x0, dtype=DT).expand(len(eps_values), -1)
    slow0 = torch.tensor([fam.x0[i] for i in fam.slow], dtype=DT)
    ode_pieces, lim_slow, lim_fast, status = [], [], [], torch.zeros(len(eps_values), dtype=int)
    n_steps = torch.zeros(len(eps_values), dtype=torch.int64)
    with torch.no_grad():
        for level, grid in zip(levels, grids, strict=True):
            u = torch.full((len(grid), 1), level, dtype=DT)
            sol = odeint(model, x, grid, method="radau_iia", u=u, rtol=rtol, atol=atol)
            status = torch.maximum(status, sol.status.long())
            n_steps += sol.stats.n_steps
            ode_pieces.append(sol.x)
            x = sol.x[:, -1]
            slow_piece, fast_piece, lim_sol = fam.limit(slow0, grid, u, rtol, atol)
            if int(lim_sol.status.max()) != Status.SUCCESS:
                raise RuntimeError(f"{fam.name}: limit solver failed: {lim_sol.messages}")
            lim_slow.append(slow_piece)
            lim_fast.append(fast_piece)
            slow0 = slow_piece[-1]
    t = join_pieces([g[:, None] for g in grids])[:, 0]
    x_ode = join_pieces(ode_pieces)
    slow_lim, fast_lim = join_pieces(lim_slow), join_pieces(lim_fast)

    a0, b0, cz, dz = fam.limit_matrices()
    exact_lim, exact_lim_z = exact_pieces(a0, b0, np.array(fam.x0)[fam.slow], levels, grids, cz, dz)
    exact_lim, exact_lim_z = join_pieces(exact_lim), join_pieces(exact_lim_z)
    limit_error = float((slow_lim - exact_lim).abs().max())
    limit_fast_error = float((fast_lim - exact_lim_z).abs().max())
    jumps = [float(g[0]) for g in grids]
    rows, curves = [], []
    for i, e in enumerate(eps_values):
        a, b = fam.matrices(e)
        exact_ode = join_pieces(exact_pieces(a, b, np.array(fam.x0), levels, grids)[0])
        mask = layer_mask(t, jumps, e, fam.lambda0)
        slow_i, fast_i = x_ode[i][:, fam.slow], x_ode[i][:, fam.fast]
        fast_dev = (fast_i - fast_lim)[mask].abs()
        rows.append(
            {
                "family": fam.name,
                "eps": e,
                "dev_slow": float((slow_i - slow_lim).abs().max()),
                "dev_slow_exact": float((exact_ode[:, fam.slow] - exact_lim).abs().max()),
                "dev_fast_after_layer": float(fast_dev.max()) if fast_dev.numel() else math.nan,
                "ode_integration_error": float((slow_i - exact_ode[:, fam.slow]).abs().max()),
                "limit_integration_error": limit_error,
                "limit_fast_error": limit_fast_error,
                "radau_steps": int(n_steps[i]),
                "status": int(status[i]),
            }
        )
        curves.append((slow_i[:, fam.plot_slow], fast_i[:, 0]))
    return rows, t, curves, (slow_lim[:, fam.plot_slow], fast_lim[:, 0])


def saturation_row(n_pieces, n_per_piece, piece) -> dict:
    """Fig. 5.3 as drawn: eq. (5.41) with m1 -> 0 at fixed rho/K = 1e-3 against the DAE (5.44),
    from the exact solutions: the gap tends to the (5.43)-vs-(5.44) gap, not to zero."""
    levels = FAMILIES[1].u_levels[:n_pieces]
    grids = piece_grids(piece, n_pieces, n_per_piece)
    a0, b0, _, _ = _limit_matrices_rho()
    dae = join_pieces(exact_pieces(a0, b0, np.array([1.0, 0.0]), levels, grids)[0])
    a, b = _matrices_m1(1e-7)
    ode = join_pieces(exact_pieces(a, b, np.array(FAMILIES[1].x0), levels, grids)[0])
    a, b = _matrices_543(RHO / K)
    ode543 = join_pieces(exact_pieces(a, b, np.array([1.0, 1.0, 0.0]), levels, grids)[0])
    return {
        "family": "fig5.3 saturation (5.41, m1=1e-7, vs DAE 5.44)",
        "eps": 1e-7,
        "dev_slow_exact": float((ode[:, 1] - dae[:, 0]).abs().max()),
        "dev_5_43_vs_5_44": float((ode543[:, 1] - dae[:, 0]).abs().max()),
    }


def run_all(args, rtol, atol, n_pieces, n_per_piece):
    """All families and the Fig. 5.3 saturation row: (rows, slope rows, plot data)."""
    rows, slopes, plots = [], [], []
    for fam in progress(FAMILIES, "families"):
        eps_values = fam.eps_quick if args.quick else FULL_EPS
        piece = fam.piece_quick if args.quick else fam.piece
        fam_rows, t, curves, limit = run_family(
            fam, eps_values, n_pieces, n_per_piece, piece, rtol, atol
        )
        rows += fam_rows
        plots.append((fam, eps_values, t, curves, limit, fam_rows))
        fit = fam_rows[-3:]
        dev = [r["dev_slow"] for r in fam_rows]
        slopes.append(
            {
                "family": fam.name,
                "fit_eps_min": fit[-1]["eps"],
                "fit_eps_max": fit[0]["eps"],
                "slope": fitted_slope([r["eps"] for r in fit], [r["dev_slow"] for r in fit]),
                "slope_exact": fitted_slope(
                    [r["eps"] for r in fit], [r["dev_slow_exact"] for r in fit]
                ),
                "monotone_decreasing": bool(all(b < a for a, b in pairwise(dev))),
                "all_success": bool(all(r["status"] == Status.SUCCESS for r in fam_rows)),
            }
        )
    two_mass = FAMILIES[1]
    rows.append(
        saturation_row(
            n_pieces, n_per_piece, two_mass.piece_quick if args.quick else two_mass.piece
        )
    )
    return rows, slopes, plots


def main(argv=None) -> list[dict]:
    args = build_parser().parse_args(argv)
    out = output_dir(args, NAME)
    rtol = args.rtol or (1e-7 if args.quick else 1e-10)
    atol = rtol / 100
    n_pieces, n_per_piece = (2, 25) if args.quick else (4, 200)

    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # tiny tensors: intra-op threads only add hand-off latency
    try:
        rows, slopes, plots = run_all(args, rtol, atol, n_pieces, n_per_piece)
    finally:
        torch.set_num_threads(threads)
    markdown = write_table(rows, out / "tikhonov_deviation")
    markdown += "\n" + write_table(slopes, out / "tikhonov_slopes")

    fig, axes = plt.subplots(len(plots), 3, figsize=(15, 3.6 * len(plots)), layout="constrained")
    for row_axes, (fam, eps_values, t, curves, limit, fam_rows) in zip(axes, plots, strict=True):
        shades = np.linspace(0.8, 0.35, len(eps_values))
        for k in range(2):
            for shade, e, curve in zip(shades, eps_values, curves, strict=True):
                row_axes[k].plot(t, curve[k], color=str(shade), lw=1, label=f"eps = {e:g}")
            row_axes[k].plot(t, limit[k], "k", lw=1.5, label="limit (eps = 0)")
            label = (fam.slow_label, fam.fast_label)[k]
            row_axes[k].set_title(f"{fam.name}: {label}")
            row_axes[k].set_xlabel("t [s]")
            row_axes[k].set_ylabel(label)
        row_axes[0].legend(fontsize=7)
        e = np.array([r["eps"] for r in fam_rows])
        row_axes[2].loglog(e, [r["dev_slow"] for r in fam_rows], "o", label="Radau IIA vs limit")
        row_axes[2].loglog(e, [r["dev_slow_exact"] for r in fam_rows], "-", label="exact (expm)")
        ref = fam_rows[-1]["dev_slow_exact"] * e / e[-1]
        row_axes[2].loglog(e, ref, "k:", label="slope 1")
        row_axes[2].set_xlabel("eps")
        row_axes[2].set_ylabel("deviation from the limit")
        row_axes[2].set_title("max |x_eps - x_0| over slow states")
        row_axes[2].legend(fontsize=7)
    save_figure(fig, out / "tikhonov.png")
    finish(out, markdown)
    return rows


if __name__ == "__main__":
    main()
