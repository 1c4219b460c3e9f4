"""Benchmark: cost of the autograd-built Lagrangian right-hand side vs hand-written forms.

The hanging chain of N masses in 3-D (notes eq. 2.91-2.97) for a batch of B states: time per
evaluation of ``HangingChain.forward`` (LagrangianSystem: one reverse pass through V with a
constant diagonal W) against the hand-written closed form eq. (2.97) (signs fixed), in the
same process, interleaved, taking the minimum over repeats (robust to a loaded machine).
Both run with the plant's parameters requiring grad (training setting, graphs built) and
under ``torch.no_grad()`` (simulation only). As a second case, the two-pendulum crane in
polar coordinates (q-dependent W: nq + 1 reverse passes and a batched solve) against its
transcribed closed form (eq. 2.105-2.109, typos fixed).

Run: ``python experiments/bench_mechanics.py [--quick] [--out DIR]``; writes
``bench_mechanics.csv`` / ``.md`` with the times, the ratios and the largest difference
between the two accelerations.
"""

from __future__ import annotations

import argparse
import time

from experiments._common import (
    experiment_parser,
    finish,
    note,
    output_dir,
    parse_early,
    write_table,
)

NAME = "bench_mechanics"


def build_parser() -> argparse.ArgumentParser:
    """The command line (``--help`` lists it); built without importing torch."""
    parser = experiment_parser(NAME, __doc__.splitlines()[0])
    parser.add_argument("--masses", type=int, default=50, help="masses of the hanging chain")
    parser.add_argument("--batch", type=int, default=1024, help="states evaluated in one batch")
    parser.add_argument(
        "--repeats", type=int, default=50, help="timings are the best of this many runs"
    )
    parser.add_argument("--seed", type=int, default=0, help="seed of the random states")
    return parser


parse_early(__name__, build_parser)

import torch

from sysid.zoo import HangingChain, TwoPendulumCranePolar


def chain_closed_form(plant: HangingChain, x: torch.Tensor) -> torch.Tensor:
    """xdot of the chain written by hand from eq. (2.97) (signs fixed, see HangingChain)."""
    n = plant.nq
    q, qd = x[..., :n], x[..., n:]
    p = q.reshape(*q.shape[:-1], plant.n_masses, 3)
    left = torch.cat([plant.p_start.to(q).expand(*q.shape[:-1], 1, 3), p[..., :-1, :]], -2)
    right = torch.cat([p[..., 1:, :], plant.p_end.to(q).expand(*q.shape[:-1], 1, 3)], -2)
    k_over_m = plant.K.to(q) / plant.m.to(q)
    acc = k_over_m * (left + right - 2 * p)
    acc = acc - plant.g.to(q) * torch.tensor([0.0, 0.0, 1.0], dtype=q.dtype, device=q.device)
    return torch.cat([qd, acc.reshape(q.shape)], -1)


def crane_closed_form(plant: TwoPendulumCranePolar, x: torch.Tensor) -> torch.Tensor:
    q, qd = x[..., :3], x[..., 3:]
    return torch.cat([qd, plant.closed_form_acceleration(q, qd)], -1)


def _min_time(fn, x, repeats):
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        fn(x)
        best = min(best, time.perf_counter() - start)
    return best


def _case(name, plant, closed, x, repeats):
    rows = []
    builder = lambda s: plant(None, s)  # noqa: E731
    hand = lambda s: closed(plant, s)  # noqa: E731
    with torch.no_grad():
        diff = float((builder(x) - hand(x)).abs().max())
    for mode in ("grad", "no_grad"):
        ctx = torch.enable_grad() if mode == "grad" else torch.no_grad()
        with ctx:
            builder(x), hand(x)  # warm-up
            t_b, t_h = float("inf"), float("inf")
            for _ in range(repeats):  # interleave so both see the same machine load
                t_b = min(t_b, _min_time(builder, x, 1))
                t_h = min(t_h, _min_time(hand, x, 1))
        rows.append(
            {
                "case": name,
                "mode": mode,
                "batch": x.shape[0],
                "builder_ms": round(1e3 * t_b, 4),
                "closed_form_ms": round(1e3 * t_h, 4),
                "ratio": round(t_b / t_h, 3),
                "max_abs_diff": f"{diff:.2e}",
            }
        )
    return rows


def main(argv=None):
    args = build_parser().parse_args(argv)
    if args.quick:
        args.masses, args.batch, args.repeats = 10, 64, 5
    out = output_dir(args, NAME)
    gen = torch.Generator().manual_seed(args.seed)
    chain = HangingChain(n_masses=args.masses, m=0.05, K=20.0)
    x = torch.randn(args.batch, 2 * chain.nq, dtype=torch.float64, generator=gen)
    note(f"hanging chain, {args.masses} masses, batch {args.batch}")
    rows = _case(f"chain N={args.masses}", chain, chain_closed_form, x, args.repeats)
    crane = TwoPendulumCranePolar()
    x = torch.randn(args.batch, 6, dtype=torch.float64, generator=gen)
    note("two-pendulum crane (polar)")
    rows += _case("two-pendulum crane (polar)", crane, crane_closed_form, x, args.repeats)
    finish(out, write_table(rows, out / NAME))
    return rows


if __name__ == "__main__":
    main()
