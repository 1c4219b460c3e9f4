"""Sensitivities of x(T) w.r.t. x0 and parameters, four ways side by side (notes §8).

Model: Van der Pol in the state order of eq. (6.43) with two parameters p = (mu, k),

    x1' = mu (1 - x2^2) x1 - k x2,    x2' = x1,    p = (1, 1),  x0 = (0, 2),

simulated with fixed steps dt on [0, T] by an explicit method (RK4) and an implicit one
(Gauss-Legendre s = 2). For each, A = dx_N/dx0 (nx x nx) and B = dx_N/dp (nx x np) come from

* ``forward``: :func:`integrators.sensitivities` - exact derivatives of the discrete
  simulation, eq. 8.17-8.18 (explicit) and eq. 8.24-8.28 (implicit, IFT on the stage
  equations);
* ``reverse``: ``torch.autograd`` through ``odeint`` (one backward pass per output
  component; for the implicit method the solver differentiates each step by the implicit
  function theorem);
* ``variational``: :func:`integrators.variational_sensitivities`, eq. 8.8 integrated with the
  *same* method and grid. It coincides with ``forward`` to rounding, for the implicit method
  too: a Runge-Kutta discretisation of the variational equations is the derivative of the
  discretised simulation (the notes show it for Euler in §8.2; the stage equations of the
  augmented system are the differentiated stage equations). ``variational_exact`` integrates
  eq. 8.8 with adaptive dopri5 at rtol = atol = 1e-11 (1e-9 with --quick): the sensitivities
  of the ODE itself, which differ from the discrete ones by the discretisation error;
* ``fd``: central finite differences of ``odeint`` with relative step 1e-5, all
  perturbations in one batched call.

Table ``sensitivities.csv``: per method and pair (``forward`` against each other way) the
normwise relative difference max|S - S_ref| / max|S_ref| for A and B, and the wall time of
each way (best of ``--repeats``; comparisons between rows only). The implicit runs use
``odeint(..., rtol=1e-10, atol=1e-12)`` so that the Newton solves are converged well below
the differences measured.

Run: ``python -m experiments.sensitivities_compare [--quick] [--out DIR]``.
"""

from __future__ import annotations

import argparse
import time
from functools import partial

from experiments._common import (
    experiment_parser,
    finish,
    output_dir,
    parse_early,
    progress,
    save_figure,
    write_table,
)

NAME = "sensitivities_compare"


def build_parser() -> argparse.ArgumentParser:
    """The command line (``--help`` lists it); built without importing torch."""
    parser = experiment_parser(NAME, "Forward, variational, reverse-mode and FD sensitivities.")
    parser.add_argument(
        "--repeats",
        type=int,
        default=None,
        help="timings are the best of this many runs (default 3, 1 with --quick)",
    )
    return parser


parse_early(__name__, build_parser)

import torch

from experiments._common import plt
from integrators import odeint, sensitivities, variational_sensitivities

P0 = (1.0, 1.0)
X0 = (0.0, 2.0)
FD_STEP = 1e-5
METHODS = {
    "rk4": dict(method="rk4"),
    "gauss_legendre_2": dict(method="gauss_legendre", stages=2),
}
IMPLICIT_TOL = dict(rtol=1e-10, atol=1e-12)


def vdp(t, x, p):
    """Van der Pol with p = (mu, k) of shape (*batch, 2) (eq. 6.43 for p = (1, 1))."""
    mu, k = p[..., 0:1], p[..., 1:2]
    x1, x2 = x[..., 0:1], x[..., 1:2]
    return torch.cat([mu * (1 - x2**2) * x1 - k * x2, x1], dim=-1)


def _options(name: str) -> dict:
    opts = dict(METHODS[name])
    if name != "rk4":
        opts.update(IMPLICIT_TOL, adaptive=False)
    return opts


def final_state(name: str, x0, p, t) -> torch.Tensor:
    """x(T) of the discrete simulation, x0 (*batch, 2), p (*batch, 2) -> (*batch, 2)."""
    return odeint(lambda tt, x: vdp(tt, x, p), x0, t, **_options(name)).x[..., -1, :]


def forward_way(name, x0, p, t):
    res = sensitivities(vdp, x0, t, p, **METHODS[name])
    return res.A[-1], res.B[-1]


def reverse_way(name, x0, p, t):
    x0 = x0.clone().requires_grad_(True)
    p = p.clone().requires_grad_(True)
    xT = final_state(name, x0, p, t)
    rows_a, rows_b = [], []
    for i in range(xT.shape[-1]):  # one backward pass per output component
        ga, gb = torch.autograd.grad(xT[i], (x0, p), retain_graph=i + 1 < xT.shape[-1])
        rows_a.append(ga)
        rows_b.append(gb)
    return torch.stack(rows_a), torch.stack(rows_b)


def variational_way(name, x0, p, t):
    res = variational_sensitivities(vdp, x0, t, p, **_options(name))
    return res.A[-1], res.B[-1]


def variational_exact_way(name, x0, p, t, tol=1e-11):
    res = variational_sensitivities(vdp, x0, t, p, method="dopri5", rtol=tol, atol=tol)
    return res.A[-1], res.B[-1]


def fd_way(name, x0, p, t):
    """Central differences; all 2 (nx + np) perturbed runs in one batch."""
    nx, n_p = x0.shape[-1], p.shape[-1]
    z = torch.cat([x0, p])
    step = FD_STEP * torch.clamp(z.abs(), min=1.0)
    eye = torch.diag(step)
    zs = torch.cat([z + eye, z - eye])  # (2 (nx + np), nx + np)
    with torch.no_grad():
        xT = final_state(name, zs[:, :nx].contiguous(), zs[:, nx:].contiguous(), t)
    n = nx + n_p
    jac = ((xT[:n] - xT[n:]) / (2 * step[:, None])).T  # (nx, nx + np)
    return jac[:, :nx], jac[:, nx:]


WAYS = {
    "forward": forward_way,
    "reverse": reverse_way,
    "variational": variational_way,
    "variational_exact": variational_exact_way,
    "fd": fd_way,
}


def timed(fn, repeats: int, *args):
    best, out = float("inf"), None
    for _ in range(repeats):
        start = time.perf_counter()
        out = fn(*args)
        best = min(best, time.perf_counter() - start)
    return out, best


def rel_diff(a: torch.Tensor, ref: torch.Tensor) -> float:
    return float((a - ref).abs().max() / ref.abs().max())


def main(argv=None) -> list[dict]:
    args = build_parser().parse_args(argv)
    out = output_dir(args, NAME)
    repeats = args.repeats or (1 if args.quick else 3)
    t_end, dt = (2.0, 0.05) if args.quick else (5.0, 0.02)
    t = torch.linspace(0.0, t_end, round(t_end / dt) + 1, dtype=torch.float64)
    x0 = torch.tensor(X0, dtype=torch.float64)
    p = torch.tensor(P0, dtype=torch.float64)

    rows, results = [], {}
    for name in progress(METHODS, "integration methods"):
        ways = dict(WAYS)
        if args.quick:  # the ODE sensitivities only need to beat the discretisation error
            ways["variational_exact"] = partial(variational_exact_way, tol=1e-9)
        res = {way: timed(fn, repeats, name, x0, p, t) for way, fn in ways.items()}
        results[name] = res
        (a_ref, b_ref), t_ref = res["forward"]
        for way in ("reverse", "variational", "variational_exact", "fd"):
            (a, b), seconds = res[way]
            rows.append(
                {
                    "method": name,
                    "reference": "forward",
                    "way": way,
                    "rel_diff_dx_dx0": rel_diff(a, a_ref),
                    "rel_diff_dx_dp": rel_diff(b, b_ref),
                    "time_way_s": seconds,
                    "time_forward_s": t_ref,
                    "t_end": t_end,
                    "dt": dt,
                }
            )
    markdown = write_table(rows, out / "sensitivities")
    values = []
    for name, res in results.items():
        for way, ((a, b), _) in res.items():
            entry = {"method": name, "way": way}
            entry.update({f"A{i}{j}": float(a[i, j]) for i in range(2) for j in range(2)})
            entry.update({f"B{i}{j}": float(b[i, j]) for i in range(2) for j in range(2)})
            values.append(entry)
    write_table(values, out / "values")

    fig, ax = plt.subplots(figsize=(8, 4.5))
    ways = ["reverse", "variational", "variational_exact", "fd"]
    offset = 0.15
    # points, not bars: a bar's length means nothing on a log axis
    for k, (name, marker) in enumerate(zip(METHODS, "os^D", strict=False)):
        diffs = [
            max(r["rel_diff_dx_dx0"], r["rel_diff_dx_dp"], 1e-17)
            for r in rows
            if r["method"] == name
        ]
        x = [i + (k - (len(METHODS) - 1) / 2) * offset for i in range(len(ways))]
        ax.semilogy(x, diffs, marker, ms=7, label=name)
    ax.set_xticks(range(len(ways)), ways)
    ax.set_xlabel("way of computing the sensitivities")
    ax.grid(axis="y", color="0.9")
    ax.set_ylabel("max relative difference to forward (eq. 8.18 / 8.28)")
    ax.set_title("Sensitivities of x(T) of Van der Pol (eq. 6.43) w.r.t. x0 and (mu, k)")
    ax.legend()
    save_figure(fig, out / "sensitivities.png")
    finish(out, markdown)
    return rows


if __name__ == "__main__":
    main()
