"""A neural ODE learns Van der Pol from a few trajectories, validated by a free run.

Run with no arguments (``python -m experiments.neural_vanderpol``); ``--quick`` is the
seconds-long variant the tests use.

1. Data: the zoo's Van der Pol oscillator (mu = 1, notes eq. 6.43; state (x1, x2) = (velocity,
   position)), ``trajectories`` free responses from initial states drawn uniformly in
   [-2, 2]^2, sampled at Ts = 0.1 s (reference RK4 at Ts / 10), both states measured, with
   optional white output noise.
2. Model: ``NeuralODE(2, 0)``, a tanh MLP right-hand side normalised by the states' standard
   deviations and scaled to the sample time (derivatives of order x_scale / Ts), simulated by
   RK4 at the sample time.
3. Training through ``sysid.fit``: Adam on minibatches of random windows (curriculum on the
   window length, initial states of the windows estimated), then L-BFGS on the full set of
   windows tiling the records.
4. Validation: a FREE RUN from a held-out initial condition (not in the training set) over
   ``t_val`` seconds, started at the true state: fit % (MATLAB's), RMSE and R² per state.

Writes ``summary.csv/.md`` (training time, epochs, losses, validation fit) and
``neural_vanderpol.png`` (phase portrait and time series of the validation free run, loss
history).
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

NAME = "neural_vanderpol"


def build_parser() -> argparse.ArgumentParser:
    """The command line (``--help`` lists it); built without importing torch."""
    parser = experiment_parser(NAME, __doc__.splitlines()[0])
    parser.add_argument(
        "--trajectories",
        type=int,
        default=None,
        help="training trajectories (default 16, 8 with --quick)",
    )
    parser.add_argument(
        "--t-train",
        type=float,
        default=None,
        help="length of each training trajectory in s (default 15, 10 with --quick)",
    )
    parser.add_argument(
        "--t-val",
        type=float,
        default=None,
        help="validation horizon in s (default 20, 10 with --quick)",
    )
    parser.add_argument(
        "--hidden",
        type=int,
        default=None,
        help="width of both hidden layers (default 32, 16 with --quick)",
    )
    parser.add_argument("--noise", type=float, default=0.0, help="output noise std")
    parser.add_argument("--seed", type=int, default=0, help="seed of data and training")
    return parser


parse_early(__name__, build_parser)

import time

import torch

from experiments._common import plt
from integrators import odeint
from sysid import IOData, fit
from sysid.continuous import NeuralODE
from sysid.zoo import VanDerPol

TS = 0.1
MU = 1.0


def vanderpol_records(x0: torch.Tensor, N: int, Ts: float = TS) -> torch.Tensor:
    """States (*batch, N, 2) of the unforced Van der Pol oscillator from x0 (*batch, 2) at
    t_k = k Ts (RK4 at Ts / 10: error ~1e-8, far below every figure reported)."""
    t = Ts * torch.arange(N, dtype=torch.float64)
    with torch.no_grad():
        return odeint(VanDerPol(MU).double(), x0, t, method="rk4", substeps=10).x


def train_vanderpol(data: IOData, hidden: int, adam_epochs: int, lbfgs_epochs: int, seed: int):
    """Adam (windows of 10 then 30 intervals, cosine learning rate) then L-BFGS (windows of 30)
    on a ``NeuralODE(2, 0)`` with two hidden layers of ``hidden`` tanh units.

    Returns:
        (result of the L-BFGS stage, loss history of both stages (epochs,), CPU seconds).
    """
    scale = data.y.reshape(-1, 2).std(0)
    model = NeuralODE(2, 0, hidden=(hidden, hidden), Ts=data.Ts, x_scale=scale, seed=seed)
    start = time.process_time()
    adam = fit(
        model,
        data,
        method="adam",
        horizon=[(0, 10), (adam_epochs // 3, 30)],
        batch_size=32,
        epochs=adam_epochs,
        steps_per_epoch=10,
        lr=1e-2,
        schedule="cosine",
        seed=seed,
    )
    lbfgs = fit(
        adam.model, data, method="lbfgs", horizon=30, epochs=lbfgs_epochs, lr=1.0, seed=seed
    )
    seconds = time.process_time() - start
    return lbfgs, torch.cat([adam.train_loss, lbfgs.train_loss]), seconds


def main(argv=None):
    args = build_parser().parse_args(argv)
    out = output_dir(args, NAME)
    B = args.trajectories or (8 if args.quick else 16)
    t_train = args.t_train or (10.0 if args.quick else 15.0)
    t_val = args.t_val or (10.0 if args.quick else 20.0)
    hidden = args.hidden or (16 if args.quick else 32)
    adam_epochs, lbfgs_epochs = (9, 8) if args.quick else (60, 30)
    torch.manual_seed(args.seed)
    gen = torch.Generator().manual_seed(args.seed)

    note(f"simulating {B} training trajectories of {t_train:g} s and one validation run")
    x0 = 4 * torch.rand(B + 1, 2, generator=gen, dtype=torch.float64) - 2
    N, N_val = round(t_train / TS) + 1, round(t_val / TS) + 1
    x = vanderpol_records(x0[:B], N)
    x = x + args.noise * torch.randn(x.shape, generator=gen, dtype=x.dtype)
    x_val = vanderpol_records(x0[B:], N_val)
    data = IOData(x.new_zeros(B, N, 0), x, Ts=TS)
    val = IOData(x.new_zeros(1, N_val, 0), x_val, Ts=TS)

    note(f"training: Adam {adam_epochs} epochs, then L-BFGS {lbfgs_epochs} epochs")
    result, losses, seconds = train_vanderpol(data, hidden, adam_epochs, lbfgs_epochs, args.seed)
    diag = result.validate(val, x0=x0[B:])
    fit_pct = diag["fit_percent"].reshape(-1)
    rmse = diag["rmse"].reshape(-1)
    r2 = diag["r2"].reshape(-1)
    summary = [
        {
            "trajectories": B,
            "t_train_s": t_train,
            "t_val_s": t_val,
            "hidden": hidden,
            "parameters": sum(p.numel() for p in result.model.parameters()),
            "adam_epochs": adam_epochs,
            "lbfgs_epochs": lbfgs_epochs,
            "train_cpu_s": seconds,
            "final_train_loss": float(losses[-1]),
            "val_fit_x1_pct": float(fit_pct[0]),
            "val_fit_x2_pct": float(fit_pct[1]),
            "val_fit_min_pct": float(fit_pct.min()),
            "val_rmse_x1": float(rmse[0]),
            "val_rmse_x2": float(rmse[1]),
            "val_r2_min": float(r2.min()),
        }
    ]
    markdown = write_table(summary, out / "summary")
    _figure(result.simulate(val, x0=x0[B:])[0], x_val[0], x, losses, adam_epochs, out)
    (out / f"{NAME}.md").write_text(markdown)
    finish(out, markdown)
    return summary


def _figure(y_hat, y_val, x_train, losses, adam_epochs, out) -> None:
    """Phase portrait (training trajectories, validation truth and free run), validation time
    series, and the loss history of both training stages."""
    fig, (ax_phase, ax_time, ax_loss) = plt.subplots(1, 3, figsize=(15, 4.2))
    for k in range(x_train.shape[0]):
        ax_phase.plot(
            x_train[k, :, 1],
            x_train[k, :, 0],
            color="0.75",
            lw=0.8,
            label="training trajectories" if k == 0 else None,
        )
    ax_phase.plot(y_val[:, 1], y_val[:, 0], "k", lw=1.5, label="validation: true")
    ax_phase.plot(y_hat[:, 1], y_hat[:, 0], "r--", lw=1.5, label="validation: neural ODE")
    ax_phase.set_xlabel("position x2")
    ax_phase.set_ylabel("velocity x1")
    ax_phase.set_title("phase portrait")
    ax_phase.legend(fontsize=7)
    t = TS * torch.arange(y_val.shape[0], dtype=torch.float64)
    for j, color in ((0, "C0"), (1, "C1")):
        ax_time.plot(t, y_val[:, j], color=color, lw=1.5, label=f"x{j + 1} true")
        ax_time.plot(t, y_hat[:, j], color=color, ls="--", lw=1.5, label=f"x{j + 1} free run")
    ax_time.set_xlabel("time (s)")
    ax_time.set_ylabel("state")
    ax_time.set_title("free run from the held-out initial state")
    ax_time.legend(fontsize=7, ncol=2)
    epochs = torch.arange(1, losses.shape[0] + 1)
    ax_loss.semilogy(epochs, losses, "k.-")
    ax_loss.axvline(adam_epochs + 0.5, color="0.5", ls="--", label="Adam | L-BFGS")
    ax_loss.set_xlabel("epoch")
    ax_loss.set_ylabel("training loss (mean squared window error)")
    ax_loss.set_title("training loss")
    ax_loss.legend(fontsize=7)
    save_figure(fig, out / f"{NAME}.png")


if __name__ == "__main__":
    main()
