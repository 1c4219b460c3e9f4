"""Two-pendulum crane: polar coordinates (eq. 2.98-2.109) vs Cartesian coordinates with
constraints (eq. 2.150-2.158, index-1 KKT form eq. 2.168 with Baumgarte eq. 2.186).

Which model does a question need? Both describe the same motion; the polar model has 3
states pairs and a q-dependent mass matrix (costly symbolic inverse in the notes, an autograd
W and a 3x3 solve here), the Cartesian model has 5 coordinates, a constant diagonal W and two
multipliers (a 2x2 Schur solve) but must keep its constraints (drift). Measured: the cost of
one right-hand-side evaluation for a batch of states; for RK4 simulations at several steps,
the error of the mass positions at the final time against a fine polar reference, the wall
time, and the constraint residual of the Cartesian model.
"""

from __future__ import annotations

import argparse
import time

from experiments._common import (
    experiment_parser,
    finish,
    output_dir,
    parse_early,
    save_figure,
    write_table,
)

NAME = "mechanics_two_pendulum"


def build_parser() -> argparse.ArgumentParser:
    """The command line (``--help`` lists it); built without importing torch."""
    parser = experiment_parser(NAME, __doc__.splitlines()[0])
    parser.add_argument("--t-end", type=float, default=3.0, help="simulated horizon [s]")
    parser.add_argument(
        "--batch", type=int, default=256, help="states in the right-hand-side timing batch"
    )
    parser.add_argument(
        "--alpha",
        type=float,
        default=5.0,
        help="Baumgarte stabilisation gain of the Cartesian model",
    )
    return parser


parse_early(__name__, build_parser)

import torch

from experiments._common import plt
from integrators import odeint
from sysid.zoo import TwoPendulumCraneCartesian, TwoPendulumCranePolar

DT = torch.float64


def polar_to_cartesian(polar, x):
    """Map polar states (x, theta1, theta2, rates) to Cartesian states (vertical axis down)."""
    q, qd = x[..., :3], x[..., 3:]
    p = polar.positions(q)  # (.., 3, 2) cart, mass 1, mass 2 (vertical axis up)
    v = polar.point_velocities(q, qd)
    flip = torch.tensor([1.0, -1.0], dtype=DT)
    pos = torch.cat([p[..., 0, :1], p[..., 1, :] * flip, p[..., 2, :] * flip], -1)
    vel = torch.cat([v[..., 0, :1], v[..., 1, :] * flip, v[..., 2, :] * flip], -1)
    return torch.cat([pos, vel], -1)


def _rhs_time(model, x, repeats):
    with torch.no_grad():
        model(None, x)
        best = float("inf")
        for _ in range(repeats):
            start = time.perf_counter()
            model(None, x)
            best = min(best, time.perf_counter() - start)
    return best


def _simulate(model, x0, t_end, dt):
    t = torch.arange(0.0, t_end + dt / 2, dt, dtype=DT)
    start = time.perf_counter()
    with torch.no_grad():
        sol = odeint(model, x0, t, method="rk4", compile=False)
    return t, sol.x, time.perf_counter() - start


def main(argv=None):
    args = build_parser().parse_args(argv)
    steps = [0.04, 0.02, 0.01]
    if args.quick:
        args.t_end, args.batch, steps = 1.0, 16, [0.04, 0.02]
    out = output_dir(args, NAME)
    polar = TwoPendulumCranePolar(m=1.0, L=1.0)
    cart = TwoPendulumCraneCartesian(m=1.0, L=1.0, baumgarte=args.alpha)
    gen = torch.Generator().manual_seed(0)
    xb = 0.5 * torch.randn(args.batch, 6, dtype=DT, generator=gen)
    rhs_polar = _rhs_time(polar, xb, 10)
    rhs_cart = _rhs_time(cart, polar_to_cartesian(polar, xb).detach(), 10)

    x0 = torch.tensor([[0.0, 0.6, -0.4, 0.0, 0.0, 0.5]], dtype=DT)
    _, ref, _ = _simulate(polar, x0, args.t_end, steps[-1] / (4 if args.quick else 8))
    ref_pos = polar_to_cartesian(polar, ref[:, -1]).detach()[..., :5]
    x0_cart = polar_to_cartesian(polar, x0).detach()
    rows = []
    for dt in steps:
        for name, model, start in (("polar", polar, x0), ("cartesian", cart, x0_cart)):
            _, x, wall = _simulate(model, start, args.t_end, dt)
            if name == "polar":
                pos = polar_to_cartesian(polar, x[:, -1]).detach()[..., :5]
                residual = 0.0
            else:
                pos = x[:, -1, :5]
                c, _ = cart.drift(x)
                residual = float(c.detach().abs().max())
            rows.append(
                {
                    "model": name,
                    "dt": dt,
                    "position_error": float((pos - ref_pos).abs().max()),
                    "wall_s": round(wall, 4),
                    "rhs_ms_batch": round(1e3 * (rhs_polar if name == "polar" else rhs_cart), 3),
                    "batch": args.batch,
                    "max_constraint": residual,
                }
            )
    fig, ax = plt.subplots(figsize=(5, 3.8))
    for name in ("polar", "cartesian"):
        sel = [r for r in rows if r["model"] == name]
        ax.loglog([r["dt"] for r in sel], [r["position_error"] for r in sel], "o-", label=name)
    ax.set_xlabel("RK4 step dt")
    ax.set_ylabel(f"max position error at t={args.t_end:g}")
    ax.legend()
    save_figure(fig, out / "two_pendulum.png")
    finish(out, write_table(rows, out / "two_pendulum"))
    return rows


if __name__ == "__main__":
    main()
