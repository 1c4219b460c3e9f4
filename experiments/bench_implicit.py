"""Benchmark: implicit Runge-Kutta (Radau IIA, Gauss-Legendre) against scipy and torchdiffeq.

1. Stiff Van der Pol ``y1' = y2, y2' = ((1 - y1^2) y2 - y1) / eps``, ``y(0) = (2, 0)``,
   ``t in [0, 2]`` (``eps = 1e-6``): adaptive Radau IIA (s = 3, ``solve_implicit_ode``) vs
   ``scipy.integrate.solve_ivp(method="Radau")`` at the same rtol = atol, for one trajectory
   and for a batch of trajectories with different ``eps`` (scipy in a Python loop, ours one
   batched call with per-sample step sizes). Errors are relative to scipy Radau at
   rtol = atol = 1e-12 (``--quick``: 1e-10), at the final time, max over components (and
   over the checked members of the batch).
2. Fixed step on the non-stiff Van der Pol (mu = 1, t in [0, 10], dt = 0.01, notes Fig. 7.3):
   Gauss-Legendre s = 2 and Radau IIA s = 3 vs torchdiffeq's only implicit fixed-grid solver,
   ``"implicit_adams"`` (an Adams-Bashforth-Moulton predictor-corrector; torchdiffeq ships no
   implicit Runge-Kutta), at equal step: error vs scipy DOP853 (rtol 1e-13), wall time of
   the forward pass and of forward + backward (gradient of ``|x(T)|^2`` w.r.t. ``x0``, ``mu``).

All peers run in this process; times are the best of ``--repeats`` runs. Results: table
``bench_implicit.csv/.md`` and figure ``bench_implicit.png`` (wall times).
"""

from __future__ import annotations

import time

import numpy as np
import torch
from scipy.integrate import solve_ivp

from experiments._common import experiment_parser, output_dir, plt, save_figure, write_table
from integrators import solve_implicit_ode

NAME = "bench_implicit"


def _timed(fn, repeats):
    best, out = float("inf"), None
    for _ in range(repeats):
        start = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - start)
    return best, out


def _vdp_scipy(eps, t_end, rtol):
    def rhs(t, y):
        return [y[1], ((1 - y[0] ** 2) * y[1] - y[0]) / eps]

    def jac(t, y):
        return [[0.0, 1.0], [(-2 * y[0] * y[1] - 1) / eps, (1 - y[0] ** 2) / eps]]

    sol = solve_ivp(rhs, (0.0, t_end), [2.0, 0.0], method="Radau", rtol=rtol, atol=rtol, jac=jac)
    return sol.y[:, -1]


def _vdp_torch(eps):
    def rhs(t, y):
        y1, y2 = y[..., 0:1], y[..., 1:2]
        return torch.cat([y2, ((1 - y1**2) * y2 - y1) / eps], -1)

    return rhs


def stiff_rows(t_end, rtols, batch, n_check, ref_rtol, repeats, batch_rtols=None):
    """Section 1: one trajectory (at ``rtols``) and a batch (at ``batch_rtols``, default
    ``rtols``), ours vs scipy Radau."""
    batch_rtols = rtols if batch_rtols is None else batch_rtols
    rows = []
    eps_one = 1e-6
    ref_one = _vdp_scipy(eps_one, t_end, ref_rtol)
    eps_batch = np.logspace(-6, -3, batch)
    check = np.unique(np.linspace(0, batch - 1, n_check).round().astype(int))
    ref_batch = np.stack([_vdp_scipy(eps_batch[i], t_end, ref_rtol) for i in check])
    t = torch.tensor([0.0, t_end])
    eps_t = torch.as_tensor(eps_batch)[:, None]
    x0 = torch.tensor([2.0, 0.0]).expand(batch, 2)
    for rtol in rtols:
        ours_t, ours = _timed(
            lambda rtol=rtol: solve_implicit_ode(
                _vdp_torch(eps_one),
                torch.tensor([[2.0, 0.0]]),
                t,
                "radau_iia",
                rtol=rtol,
                atol=rtol,
            ),
            repeats,
        )
        sc_t, sc = _timed(lambda rtol=rtol: _vdp_scipy(eps_one, t_end, rtol), repeats)
        rows.append(
            {
                "case": "stiff VdP eps=1e-6, 1 trajectory",
                "rtol": rtol,
                "ours_error": float(
                    np.max(np.abs(ours.x[0, -1].numpy() - ref_one) / np.abs(ref_one))
                ),
                "peer_error": float(np.max(np.abs(sc - ref_one) / np.abs(ref_one))),
                "ours_s": ours_t,
                "peer": "scipy Radau",
                "peer_s": sc_t,
                "speedup": sc_t / ours_t,
                "ours_steps": int(ours.stats.n_steps.max()),
            }
        )
        ours_t, ours = _timed(
            lambda rtol=rtol: solve_implicit_ode(
                _vdp_torch(eps_t), x0, t, "radau_iia", rtol=rtol, atol=rtol
            ),
            1,
        )
        start = time.perf_counter()
        sc = np.stack([_vdp_scipy(e, t_end, rtol) for e in eps_batch])
        sc_t = time.perf_counter() - start
        rows.append(
            {
                "case": f"stiff VdP eps in [1e-6, 1e-3], batch {batch}",
                "rtol": rtol,
                "ours_error": float(
                    np.max(np.abs(ours.x[check, -1].numpy() - ref_batch) / np.abs(ref_batch))
                ),
                "peer_error": float(np.max(np.abs(sc[check] - ref_batch) / np.abs(ref_batch))),
                "ours_s": ours_t,
                "peer": "scipy Radau (loop)",
                "peer_s": sc_t,
                "speedup": sc_t / ours_t,
                "ours_steps": int(ours.stats.n_steps.max()),
            }
        )
    return rows


class _VdP(torch.nn.Module):
    def __init__(self, mu):
        super().__init__()
        self.mu = torch.nn.Parameter(torch.tensor(mu))

    def forward(self, t, x):
        return torch.stack([self.mu * (1 - x[..., 1] ** 2) * x[..., 0] - x[..., 1], x[..., 0]], -1)


def fixed_rows(t_end, dt, repeats):
    """Section 2: fixed-step Gauss / Radau vs torchdiffeq implicit_adams at equal step."""
    import torchdiffeq

    x0_np = np.array([0.5, 1.0])
    ref = solve_ivp(
        lambda t, x: [(1 - x[1] ** 2) * x[0] - x[1], x[0]],
        (0, t_end),
        x0_np,
        method="DOP853",
        rtol=1e-13,
        atol=1e-13,
    ).y[:, -1]
    t = torch.linspace(0.0, t_end, int(round(t_end / dt)) + 1)
    rows = []

    def run(kind, backward):
        model = _VdP(1.0)
        x0 = torch.tensor(x0_np[None], requires_grad=backward)
        with torch.set_grad_enabled(backward):
            if kind == "implicit_adams":
                x = torchdiffeq.odeint(model, x0, t, method="implicit_adams")[-1]
            else:
                method, s = kind
                x = solve_implicit_ode(model, x0, t, method, stages=s, adaptive=False).x[:, -1]
            if backward:
                x.square().sum().backward()
        return x.detach()

    peer_f, peer_x = _timed(lambda: run("implicit_adams", False), repeats)
    peer_b, _ = _timed(lambda: run("implicit_adams", True), repeats)
    peer_err = float(np.max(np.abs(peer_x[0].numpy() - ref)))
    for kind in (("gauss_legendre", 2), ("radau_iia", 3)):
        ours_f, ours_x = _timed(lambda kind=kind: run(kind, False), repeats)
        ours_b, _ = _timed(lambda kind=kind: run(kind, True), repeats)
        for label, o, p in (("forward", ours_f, peer_f), ("forward+backward", ours_b, peer_b)):
            rows.append(
                {
                    "case": f"VdP mu=1 fixed dt={dt}, {kind[0]} s={kind[1]}, {label}",
                    "rtol": None,
                    "ours_error": float(np.max(np.abs(ours_x[0].numpy() - ref))),
                    "peer_error": peer_err,
                    "ours_s": o,
                    "peer": "torchdiffeq implicit_adams",
                    "peer_s": p,
                    "speedup": p / o,
                    "ours_steps": len(t) - 1,
                }
            )
    return rows


def main(argv=None):
    parser = experiment_parser(NAME, __doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--batch", type=int, default=256, help="trajectories in the batch case")
    parser.add_argument(
        "--batch-rtols",
        type=float,
        nargs="+",
        default=[1e-6, 1e-9],
        help="tolerances of the batch case (scipy's loop at 1e-9 takes long)",
    )
    args = parser.parse_args(argv)
    out = output_dir(args, NAME)
    previous_dtype = torch.get_default_dtype()
    torch.set_default_dtype(torch.float64)
    try:
        if args.quick:
            rows = stiff_rows(
                t_end=0.3, rtols=(1e-4,), batch=8, n_check=3, ref_rtol=1e-10, repeats=1
            )
            rows += fixed_rows(t_end=1.0, dt=0.05, repeats=1)
        else:
            rows = stiff_rows(
                t_end=2.0,
                rtols=(1e-6, 1e-9),
                batch=256,
                n_check=8,
                ref_rtol=1e-12,
                repeats=args.repeats,
            )
            rows += fixed_rows(t_end=10.0, dt=0.01, repeats=args.repeats)
        write_table(rows, out / NAME)
        fig, ax = plt.subplots(figsize=(9, 4))
        y = np.arange(len(rows))
        ax.barh(y - 0.2, [r["ours_s"] for r in rows], height=0.4, label="ours")
        ax.barh(y + 0.2, [r["peer_s"] for r in rows], height=0.4, label="peer")
        ax.set_yticks(y, [f"{r['case']} rtol={r['rtol']}" for r in rows], fontsize=6)
        ax.set_xscale("log")
        ax.set_xlabel("wall time [s]")
        ax.legend()
        fig.tight_layout()
        save_figure(fig, out / f"{NAME}.png")
        return rows
    finally:
        torch.set_default_dtype(previous_dtype)


if __name__ == "__main__":
    main()
