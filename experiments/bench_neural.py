"""Benchmark of neural-ODE training epochs through the RK layers against torchdiffeq, in one
process.

The same MLP right-hand side ``x' = net(x)`` (2 states, tanh, one weight initialisation), the
same data (windows of a Van der Pol trajectory, mu = 1, sampled at dt = 0.1), the same
minibatches of windows (one seeded generator), the same fixed grid: one 3/8-rule RK4 step per
sample interval (torchdiffeq's fixed-grid ``"rk4"`` is the 3/8 rule, so ours runs
``method="rk38"``). One epoch = ``steps`` Adam updates on the mean squared error of the
simulated windows from their measured initial states. Peers:

* ours: ``integrators.odeint(..., method="rk38")`` (backpropagation through the stages),
  eager (``compile=False``) and compiled (``compile=True``: chunks of steps compiled by
  ``torch.compile`` with their backward; the compile, paid once per model and shape, is
  reported as ``compile_s``, the first epoch's excess over the best one; not with
  ``--quick``, and without the saved-bytes column, which counts eager autograd's tensors);
* torchdiffeq ``odeint`` (backpropagation through its stages) and ``odeint_adjoint`` (the
  adjoint ODE solved backwards with the same fixed grid).

Reported: seconds per epoch, the ratio to ours, and the training loss after the same number
of epochs (ours and ``odeint`` compute the same numbers, so they agree to rounding; the
adjoint's gradient is that of the discretised adjoint, close but not equal). Memory of one
long-horizon gradient (a single window of ``long`` intervals): the bytes of the distinct
storages autograd holds for the backward pass after the forward simulation (a
``saved_tensors_hooks`` count, each storage once however many stages saved it: exact and
device-independent; the adjoint saves almost nothing in the forward pass and re-integrates
backwards instead).

Timings: wall clock, on the CPU, torch on one thread.

Run: ``python -m experiments.bench_neural [--quick] [--out DIR]``.
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

NAME = "bench_neural"


def build_parser() -> argparse.ArgumentParser:
    """The command line (``--help`` lists it); built without importing torch."""
    parser = experiment_parser(NAME, __doc__.splitlines()[0])
    parser.add_argument(
        "--epochs", type=int, default=None, help="epochs per peer (default 5, 2 with --quick)"
    )
    parser.add_argument(
        "--horizon",
        type=int,
        default=None,
        help="window length in intervals (default 20, 10 with --quick)",
    )
    parser.add_argument(
        "--long",
        type=int,
        default=None,
        help="intervals of the long-horizon gradient (default 2000, 200 with --quick)",
    )
    parser.add_argument("--hidden", type=int, default=64, help="hidden width of the MLP")
    return parser


parse_early(__name__, build_parser)

import torch
import torchdiffeq
from torch import nn

from experiments._graph_memory import GraphMemory, with_large_stack
from integrators import odeint as rk_odeint

DT = 0.1
STEPS = 10  # Adam updates per epoch
BATCH = 32


class MLP(nn.Module):
    def __init__(self, hidden: int, seed: int = 0):
        super().__init__()
        g = torch.Generator().manual_seed(seed)
        self.net = nn.Sequential(
            nn.Linear(2, hidden),
            nn.Tanh(),
            nn.Linear(hidden, hidden),
            nn.Tanh(),
            nn.Linear(hidden, 2),
        ).double()
        with torch.no_grad():
            for p in self.net.parameters():
                p.uniform_(-0.3, 0.3, generator=g)

    def forward(self, t, x):
        return self.net(x)


def vdp_data(N: int) -> torch.Tensor:
    """(N, 2) Van der Pol (mu = 1) trajectory from (2, 0), fine RK4 reference."""

    def f(t, x):
        return torch.stack([x[..., 1], (1 - x[..., 0] ** 2) * x[..., 1] - x[..., 0]], -1)

    t = DT * torch.arange(N, dtype=torch.float64)
    x0 = torch.tensor([2.0, 0.0], dtype=torch.float64)
    return rk_odeint(f, x0, t, method="rk4", substeps=10).x


def simulate(peer: str, f, x0, t):
    """(..., len(t), 2) states on the grid t, one 3/8-rule step per interval."""
    if peer.startswith("ours"):
        return rk_odeint(f, x0, t, method="rk38", compile=peer == "ours, compiled").x
    solver = torchdiffeq.odeint if peer == "torchdiffeq odeint" else torchdiffeq.odeint_adjoint
    return solver(f, x0, t, method="rk4").movedim(0, -2)


PEERS = ("ours", "ours, compiled", "torchdiffeq odeint", "torchdiffeq odeint_adjoint")


def peers(quick: bool) -> tuple[str, ...]:
    """The peers of a run: all but the compiled one with ``--quick`` (its compile alone
    outlasts a quick run)."""
    return tuple(p for p in PEERS if not (quick and p == "ours, compiled"))


def train(peer, data, hidden, epochs, T):
    f = MLP(hidden)
    opt = torch.optim.Adam(f.parameters(), lr=1e-3)
    gen = torch.Generator().manual_seed(1)
    t = DT * torch.arange(T + 1, dtype=torch.float64)
    offsets = torch.arange(T + 1)
    seconds, loss = [], None
    for _ in range(epochs):
        start, total = time.perf_counter(), 0.0
        for _ in range(STEPS):
            k = torch.randint(data.shape[0] - T, (BATCH,), generator=gen)
            win = data[k[:, None] + offsets]  # (BATCH, T+1, 2)
            opt.zero_grad()
            e = simulate(peer, f, win[:, 0], t) - win
            step_loss = (e * e).mean()
            step_loss.backward()
            opt.step()
            total += float(step_loss.detach())
        seconds.append(time.perf_counter() - start)
        loss = total / STEPS
    return min(seconds), max(seconds[0] - min(seconds), 0.0), loss


def saved_bytes(peer, data, hidden, n):
    """Bytes the autograd graph of one window of n intervals holds for its backward pass
    (:class:`~experiments._graph_memory.GraphMemory`: each storage once, so the weights that
    every stage saves count once)."""
    f = MLP(hidden)
    t = DT * torch.arange(n + 1, dtype=torch.float64)

    def measured():
        with GraphMemory() as meter:
            e = simulate(peer, f, data[0], t) - data[: n + 1]
            loss = (e * e).mean()
            saved = meter.saved_bytes(loss)
        loss.backward()
        return saved

    return with_large_stack(measured)


def main(argv=None):
    args = build_parser().parse_args(argv)
    out = output_dir(args, NAME)
    torch.set_num_threads(1)
    epochs = args.epochs or (2 if args.quick else 5)
    T = args.horizon or (10 if args.quick else 20)
    long = args.long or (200 if args.quick else 2000)
    data = vdp_data(max(long + 1, 500))
    rows = []
    for peer in peers(args.quick):
        note(f"{peer}: {epochs} epochs of {STEPS} minibatches, then a {long}-step gradient")
        sec, first_excess, loss = train(peer, data, args.hidden, epochs, T)
        compiled = peer == "ours, compiled"
        mem = float("nan") if compiled else saved_bytes(peer, data, args.hidden, long)
        rows.append(
            {
                "peer": peer,
                "seconds_per_epoch": sec,
                "compile_s": first_excess if compiled else 0.0,
                "loss_after_epochs": loss,
                "saved_mb_long_gradient": mem / 2**20,
            }
        )
    ours = rows[0]["seconds_per_epoch"]
    for row in rows:
        row["time_vs_ours"] = row["seconds_per_epoch"] / ours
    markdown = write_table(rows, out / NAME)
    finish(out, markdown)
    return rows


if __name__ == "__main__":
    main()
