"""Multiple against single shooting from poor starting values on a lightly damped oscillator.

Plant: m y'' + xi y' + K y = u (notes eq. 1.26-1.28) with light damping (xi = 0.1, damping
ratio 0.025), a random binary force held 3 samples, only the position y measured with white
noise. ONE data set is fitted from ``starts`` random starting values, each parameter's start
drawn log-uniformly within a factor ``exp(+-spread)`` of the truth, by both criteria of
``sysid.fit``:

* ``"simulation"`` (single shooting): the free-run simulation error of the whole record.
  From a wrong natural frequency the simulated and measured oscillations drift out of phase
  and the criterion has local minima;
* ``"multiple_shooting"``: segments of ``segment_length`` samples with free node states
  (velocity unmeasured), continuity by a penalty continuation, then the simulation-error
  polish: short segments keep the criterion nearly convex in the parameters.

Both run batched: the data set is replicated once per start and every start is one member
of one ``fit`` call. The starts enter as an extra constant input channel: the model's
parameters are ``p = p_start * c`` with the free factors ``c`` (``Param(1, min=0)``, i.e.
``log c`` is the coordinate), the same Levenberg-Marquardt iteration as a fit started at
``p_start`` in the logarithmic coordinates of ``Param(p_start, min=0)``.

Success: every estimate within ``tolerance`` (relative) of the truth. Reported: the success
rate of each criterion overall and by start distance ``max_j |log(p_start,j / p_true,j)|``.

Run: ``python -m experiments.greybox_shooting [--quick] [--out DIR]``.
"""

from __future__ import annotations

import argparse

from experiments._common import (
    experiment_parser,
    finish,
    note,
    output_dir,
    parse_early,
    save_figure,
    write_table,
)

NAME = "greybox_shooting"


def build_parser() -> argparse.ArgumentParser:
    """The command line (``--help`` lists it); built without importing torch."""
    parser = experiment_parser(NAME, __doc__.splitlines()[0])
    parser.add_argument(
        "--starts", type=int, default=None, help="random starts (default 200, 16 with --quick)"
    )
    parser.add_argument(
        "--samples",
        type=int,
        default=None,
        help="samples of the data set (default 200, 120 with --quick)",
    )
    parser.add_argument(
        "--spread",
        type=float,
        default=2.0,
        help="starts drawn log-uniformly within exp(+-spread) of each true parameter",
    )
    parser.add_argument(
        "--segment-length", type=int, default=10, help="multiple-shooting segment length"
    )
    parser.add_argument(
        "--tolerance", type=float, default=0.05, help="relative distance counted as success"
    )
    parser.add_argument(
        "--max-iter",
        type=int,
        default=None,
        help="iterations per minimisation (default 20, 12 with --quick)",
    )
    parser.add_argument("--seed", type=int, default=0, help="seed of data and starts")
    return parser


parse_early(__name__, build_parser)

import warnings

import numpy as np
import torch

from experiments._common import plt
from sysid import GreyBoxModel, IOData, Param, fit
from sysid.montecarlo import input_signal

TRUE = {"m": 1.0, "xi": 0.1, "K": 4.0}
NAMES = tuple(TRUE)
TS, NOISE = 0.1, 0.01


def oscillator(t, x, u, p):
    """m y'' + xi y' + K y = u[0] with (m, xi, K) = (c_m, c_xi, c_K) * u[1:4] (the start
    values carried by the input, constant over the record)."""
    m, xi, K = (p["c_" + n] * u[..., 1 + j] for j, n in enumerate(NAMES))
    acc = (u[..., 0] - xi * x[..., 1] - K * x[..., 0]) / m
    return torch.stack([x[..., 1], acc], -1)


def record(N: int, seed: int) -> IOData:
    """One data set: the position under a random binary force, white noise ``NOISE``."""
    g = torch.Generator().manual_seed(seed)
    force = input_signal("prbs", N, (), hold=3, generator=g)
    ones = torch.ones(N, len(NAMES), dtype=force.dtype)
    truth_start = ones * torch.tensor([TRUE[n] for n in NAMES], dtype=force.dtype)
    u = torch.cat([force, truth_start], -1)
    truth = GreyBoxModel(oscillator, {"c_" + n: 1.0 for n in NAMES}, nx=2, output=[0], substeps=4)
    y = truth.simulate(IOData(u, force, Ts=TS))
    return IOData(force, y + NOISE * torch.randn(y.shape, generator=g, dtype=y.dtype), Ts=TS)


def draw_starts(starts: int, spread: float, seed: int) -> torch.Tensor:
    """(starts, 3) start values, log-uniform within exp(+-spread) of the truth."""
    g = torch.Generator().manual_seed(seed + 1)
    truth = torch.tensor([TRUE[n] for n in NAMES], dtype=torch.float64)
    log_factor = spread * (2 * torch.rand(starts, len(NAMES), generator=g, dtype=torch.float64) - 1)
    return truth * torch.exp(log_factor)


def fit_from_starts(data: IOData, start: torch.Tensor, criterion: str, args) -> torch.Tensor:
    """(starts, 3) estimates of one batched fit of the replicated data set."""
    B, N = start.shape[0], data.N
    u = torch.cat([data.u.expand(B, N, 1), start[:, None, :].expand(B, N, len(NAMES))], -1)
    replicated = IOData(u, data.y.expand(B, N, 1), Ts=data.Ts)
    factors = {"c_" + n: Param(1.0, min=0.0) for n in NAMES}
    model = GreyBoxModel(oscillator, factors, nx=2, output=[0], substeps=2)
    kw = {"segment_length": args.segment_length} if criterion == "multiple_shooting" else {}
    with warnings.catch_warnings():
        # the starts that end in a local minimum warn: counting them is the point
        warnings.simplefilter("ignore")
        res = fit(model, replicated, criterion=criterion, max_iter=args.max_iter, **kw)
    factor = torch.stack([res.params["c_" + n] for n in NAMES], -1)
    return start * factor


def main(argv=None):
    args = build_parser().parse_args(argv)
    out = output_dir(args, NAME)
    starts = args.starts or (16 if args.quick else 200)
    samples = args.samples or (120 if args.quick else 200)
    args.max_iter = args.max_iter or (12 if args.quick else 20)
    data = record(samples, args.seed)
    start = draw_starts(starts, args.spread, args.seed)
    truth = torch.tensor([TRUE[n] for n in NAMES], dtype=torch.float64)
    distance = (start / truth).log().abs().amax(-1)
    success = {}
    for criterion in ("simulation", "multiple_shooting"):
        note(f"{criterion}: one batched fit from {starts} starts")
        est = fit_from_starts(data, start, criterion, args)
        success[criterion] = ((est - truth).abs() <= args.tolerance * truth).all(-1)
    edges = np.linspace(0.0, args.spread, 5)
    rows = []
    for lo, hi in zip(edges[:-1], edges[1:], strict=True):
        inside = (distance >= lo) & (distance <= hi)
        count = int(inside.sum())
        rows.append(
            {
                "start_distance": f"{lo:.2f}-{hi:.2f}",
                "starts": count,
                **{
                    f"success_{c}": float(s[inside].double().mean()) if count else float("nan")
                    for c, s in success.items()
                },
            }
        )
    summary = [
        {
            "starts": starts,
            "samples": samples,
            "max_iter": args.max_iter,
            "segment_length": args.segment_length,
            "tolerance": args.tolerance,
            **{f"success_{c}": float(s.double().mean()) for c, s in success.items()},
        }
    ]
    fig, ax = plt.subplots(figsize=(5.5, 3.5))
    centres = 0.5 * (edges[:-1] + edges[1:])
    for c, marker in (("simulation", "o-"), ("multiple_shooting", "s-")):
        ax.plot(centres, [r[f"success_{c}"] for r in rows], marker, label=c)
    ax.set_xlabel("start distance max |log(p_start / p_true)|")
    ax.set_ylabel("success rate")
    ax.set_ylim(-0.05, 1.05)
    ax.set_title(f"lightly damped oscillator, {starts} starts")
    ax.legend()
    save_figure(fig, out / "success_vs_distance.png")
    tables = [write_table(summary, out / "summary"), write_table(rows, out / "by_distance")]
    finish(out, *tables)
    return summary[0], rows


if __name__ == "__main__":
    main()
