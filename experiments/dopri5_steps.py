"""Step sizes chosen by the adaptive Dormand-Prince 5(4) solver on Van der Pol (Fig. 6.17-6.18).

Van der Pol in the notes' state order (eq. 6.43): x1' = mu (1 - x2^2) x1 - x2, x2' = x1, with
mu = 1 as printed, and mu = 5, the relaxation regime that matches the figure's description
("fairly benign most of the time, but regularly go through very sharp changes"). Each run is
``odeint(method="dopri5", rtol=1e-6, atol=1e-6)`` from x0 = [0, 2].

Where the step sizes come from: ``Solution`` does not expose the accepted steps (only their
counts, ``stats.n_steps`` / ``n_rejected``, and ``stats.extra["n_iterations"]``,
``["n_rhs_calls"]``). They are recovered from the times at which the solver evaluates the
right-hand side: an explicit RK attempt from t_k with step h evaluates stages 2..s at
t_k + c_i h in order (stage 1 is reused, first-same-as-last, eq. 6.45), so the calls after the
start-up evaluations group into blocks of s - 1 whose times give t_k and h exactly. An
attempt is accepted when the next one starts at t_k + h. The reconstruction is checked
against the solver's own counters (accepted and rejected steps, final time) and raises if
they disagree, so a change inside the solver cannot silently corrupt the figure.

Run: ``python -m experiments.dopri5_steps [--quick] [--out DIR]``.
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

NAME = "dopri5_steps"


def build_parser() -> argparse.ArgumentParser:
    """The command line (``--help`` lists it); built without importing torch."""
    parser = experiment_parser(NAME, "dopri5 step sizes on Van der Pol (Fig. 6.17-6.18).")
    parser.add_argument("--t-end", type=float, default=30.0, help="simulated horizon [s]")
    return parser


parse_early(__name__, build_parser)

import numpy as np
import torch

from experiments._common import plt
from integrators import odeint, tableau
from sysid.zoo import VanDerPol

X0 = (0.0, 2.0)
RTOL = ATOL = 1e-6
MUS = (1.0, 5.0)
TRANSIENT = 2.0  # [s] excluded from the statistics: the first steps ramp up from dt0


def accepted_steps(plant, x0: torch.Tensor, t_end: float, rtol: float, atol: float):
    """Run dopri5 on [0, t_end] and recover its accepted steps.

    Returns:
        (t_k (N,), h_k (N,), n_rejected, solution): start times and sizes of the accepted
        steps as float64 arrays, the number of rejected attempts, and the Solution.

    Raises:
        RuntimeError: if the reconstruction disagrees with the solver's counters.
    """
    tab = tableau("dopri5")
    call_times: list[float] = []

    def recording_rhs(t, x):
        call_times.append(float(t.reshape(-1)[0]))
        return plant(t, x)

    grid = torch.tensor([0.0, t_end], dtype=torch.float64)
    with torch.no_grad():
        sol = odeint(recording_rhs, x0, grid, method="dopri5", rtol=rtol, atol=atol)
    n_iter = int(sol.stats.extra["n_iterations"])
    per_attempt = tab.stages - 1 if tab.is_fsal else tab.stages
    calls = np.asarray(call_times)
    n_init = calls.size - per_attempt * n_iter
    blocks = calls[n_init:].reshape(n_iter, per_attempt)
    c = tab.c[tab.stages - per_attempt :]
    h = (blocks[:, -1] - blocks[:, 0]) / (c[-1] - c[0])
    start = blocks[:, -1] - c[-1] * h
    if n_init < 1 or not np.allclose(blocks, start[:, None] + c[None, :] * h[:, None], atol=1e-12):
        raise RuntimeError(
            "the right-hand-side calls of the dopri5 solver do not follow the stage pattern "
            "t_k + c_i h; the step-size reconstruction needs updating."
        )
    moving = h > 0  # finished samples take zero-size steps until the loop notices
    start, h = start[moving], h[moving]
    accepted = np.append(np.isclose(start[1:], start[:-1] + h[:-1], rtol=0.0, atol=1e-12), True)
    n_acc, n_rej = int(accepted.sum()), int((~accepted).sum())
    t_k, h_k = start[accepted], h[accepted]
    if (
        n_acc != int(sol.stats.n_steps)
        or n_rej != int(sol.stats.n_rejected)
        or not np.isclose(t_k[-1] + h_k[-1], t_end, rtol=1e-12)
    ):
        raise RuntimeError(
            f"reconstructed {n_acc} accepted / {n_rej} rejected steps ending at "
            f"{t_k[-1] + h_k[-1]}, the solver reports {int(sol.stats.n_steps)} / "
            f"{int(sol.stats.n_rejected)} ending at {t_end}."
        )
    return t_k, h_k, n_rej, sol


def study(mu: float, t_end: float) -> tuple[dict, dict]:
    """Steps of one run and their relation to the speed |x'| at the step midpoints."""
    plant = VanDerPol(mu=mu)
    x0 = torch.tensor(X0, dtype=torch.float64)
    t_k, h_k, n_rej, _ = accepted_steps(plant, x0, t_end, RTOL, ATOL)
    mid = t_k + h_k / 2
    fine = np.linspace(0.0, t_end, 1001)
    with torch.no_grad():  # |x'| at the step midpoints, from a tighter run's dense output
        grid = torch.as_tensor(np.union1d(mid, fine))
        ref = odeint(plant, x0, grid, method="dopri5", rtol=1e-8, atol=1e-10)
        times = ref.t.numpy()
        speed_all = plant(ref.t, ref.x).norm(dim=-1).numpy()
    speed = speed_all[np.searchsorted(times, mid)]
    keep = mid > TRANSIENT
    keep[-1] = False  # the last step is cut short to land on t_end
    h, v = h_k[keep], speed[keep]
    q1, q3 = np.quantile(v, [0.25, 0.75])
    smallest = h <= np.quantile(h, 0.1)
    row = {
        "mu": mu,
        "t_end": t_end,
        "n_steps": len(h_k),
        "n_rejected": n_rej,
        "dt_min": float(h.min()),
        "dt_max": float(h.max()),
        "mean_dt_fast_quartile": float(h[v >= q3].mean()),
        "mean_dt_slow_quartile": float(h[v <= q1].mean()),
        "corr_log_dt_log_speed": float(np.corrcoef(np.log(h), np.log(v))[0, 1]),
        "median_speed_at_smallest_10pct_dt": float(np.median(v[smallest])),
        "median_speed": float(np.median(v)),
        "speed_rank_at_dt_min": float(np.mean(v < v[np.argmin(h)])),
    }
    curves = {"t_k": t_k, "h_k": h_k, "t": times, "x": ref.x.numpy(), "speed": speed_all}
    return row, curves


def main(argv=None) -> list[dict]:
    args = build_parser().parse_args(argv)
    out = output_dir(args, NAME)
    t_end = min(args.t_end, 12.0) if args.quick else args.t_end
    rows, curves = [], {}
    for mu in MUS:
        row, curves[mu] = study(mu, t_end)
        rows.append(row)
    markdown = write_table(rows, out / "dopri5_steps")

    fig, axes = plt.subplots(2, len(MUS), figsize=(12, 6), sharex=True)
    for col, mu in enumerate(MUS):
        data = curves[mu]
        axes[0, col].plot(data["t"], data["x"][:, 1], "k", label="x2 (position)")
        axes[0, col].plot(data["t"], data["x"][:, 0], color="0.6", label="x1 = x2'")
        axes[0, col].set_title(f"Van der Pol, mu = {mu:g} (eq. 6.43)")
        axes[0, col].set_ylabel("state")
        axes[0, col].legend(fontsize=8)
        axes[1, col].semilogy(data["t_k"], data["h_k"], ".-k", ms=3)
        axes[1, col].set_ylabel("dt chosen by dopri5")
        axes[1, col].set_xlabel("t [s]")
    fig.tight_layout()
    save_figure(fig, out / "dopri5_steps.png")
    finish(out, markdown)
    return rows


if __name__ == "__main__":
    main()
