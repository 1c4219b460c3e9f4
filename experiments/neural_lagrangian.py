"""Plain neural ODE vs Lagrangian network vs grey-box on a conservative pendulum: long rollouts.

Run with no arguments (``python -m experiments.neural_lagrangian``); ``--quick`` is the
seconds-long variant the tests use.

1. Plant: a frictionless pendulum (point mass m = 1 kg on a massless rod of length L = 1 m,
   g = 9.81 m/s²) built as a :class:`sysid.mechanics.LagrangianSystem` (T = m |p'|²/2 with
   p = (L sin θ, -L cos θ), V from gravity; notes eq. 2.3, 2.21, 2.40). Energy
   E = m L² θ'²/2 + m g L (1 - cos θ) (zero at the bottom) is conserved.
   The data and the reference rollouts come from its closed-form equation
   θ'' = -(g / L) sin θ (RK4 at Ts / 10); the grey-box row, which simulates the Lagrangian
   build, checks that the two agree.
2. Data: ``trajectories`` released from rest at angles drawn uniformly in ±2 rad (strongly
   nonlinear swings), Ts = 0.1 s, both states measured, noise-free.
3. Models, trained through ``sysid.fit``:
   - ``NeuralODE(2, 0)``: a tanh MLP right-hand side (no structure);
   - ``LagrangianNetwork(1, dissipation=False)``: learned M(θ) = L Lᵀ + εI and V(θ), so the
     learned flow conserves the learned energy by construction;
   - the grey-box pendulum with its length L free (Gauss-Newton on the simulation error).
   Equal training loss: both networks are trained by L-BFGS (``--round-iters`` iterations per
   epoch) until the common training loss (mean squared error of the windows of ``horizon``
   intervals tiling the records, every window started at the measured state, the same
   function for every model) falls below ``--target``; each stops at the first epoch below
   it, so the two end within one epoch's progress of the same loss.
4. Long rollouts from a held-out initial state over ``t_roll`` seconds (RK4 at Ts,
   ``sysid.rollout_diagnostics``): the state error against the truth and against a floor (the
   true system run from the initial state perturbed by 1e-4), and the energy drift: the true
   plant's energy evaluated on the rollout, max_t |E(t) - E(0)| / E(0).

Writes ``summary.csv/.md`` (per model: training loss, iterations, CPU time, parameters, rollout
error, energy drift) and ``neural_lagrangian.png`` (rollout error with its floor, relative
energy against time, phase portraits).
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

NAME = "neural_lagrangian"


def build_parser() -> argparse.ArgumentParser:
    """The command line (``--help`` lists it); built without importing torch."""
    parser = experiment_parser(NAME, __doc__.splitlines()[0])
    parser.add_argument(
        "--trajectories", type=int, default=8, help="training trajectories (6 s each)"
    )
    parser.add_argument(
        "--t-roll",
        type=float,
        default=None,
        help="rollout horizon in s (default 200, 60 with --quick)",
    )
    parser.add_argument(
        "--target", type=float, default=2e-4, help="common training loss both networks reach"
    )
    parser.add_argument("--horizon", type=int, default=5, help="training window (intervals)")
    parser.add_argument("--hidden", type=int, default=12, help="width of the hidden layers")
    parser.add_argument("--round-iters", type=int, default=5, help="L-BFGS iterations per epoch")
    parser.add_argument(
        "--max-epochs",
        type=int,
        default=None,
        help="L-BFGS epochs at most (default 200, 60 with --quick)",
    )
    parser.add_argument("--seed", type=int, default=0, help="seed of data and training")
    return parser


parse_early(__name__, build_parser)

import time

import torch
from torch import nn

from experiments._common import plt
from integrators import odeint
from sysid import IOData, fit, rollout_diagnostics
from sysid.continuous import GreyBoxModel, LagrangianNetwork, NeuralODE, Param
from sysid.mechanics import LagrangianSystem

TS = 0.1
G = 9.81
LENGTH = 1.0
MASS = 1.0
PERTURBATION = 1e-4


class Pendulum(LagrangianSystem):
    """Frictionless pendulum, state (theta, thetadot): a point mass ``MASS`` at
    p = (L sin θ, -L cos θ), gravity (0, -g); the length ``L`` is an ``nn.Parameter``."""

    def __init__(self, L: float = LENGTH):
        super().__init__(nq=1, coordinate_names=("theta",))
        self.L = nn.Parameter(torch.tensor(float(L), dtype=torch.float64))
        self.register_buffer("mass", torch.tensor([MASS], dtype=torch.float64))
        self.register_buffer("g_field", torch.tensor([0.0, -G], dtype=torch.float64))

    def point_masses(self):
        return self.mass

    def positions(self, q):
        th, length = q[..., 0], self.L.to(q)
        length = length[..., 0] if length.dim() > 0 else length  # (*batch, 1) in a batched fit
        return torch.stack([length * torch.sin(th), -length * torch.cos(th)], -1).unsqueeze(-2)

    def gravity(self):
        return self.g_field


def true_pendulum(t, x: torch.Tensor) -> torch.Tensor:
    """The plant's closed-form right-hand side (θ', -(g / L) sin θ) of states (*batch, 2)."""
    return torch.stack([x[..., 1], -(G / LENGTH) * torch.sin(x[..., 0])], -1)


def true_energy(x: torch.Tensor) -> torch.Tensor:
    """E = m L² θ'²/2 + m g L (1 - cos θ) (*batch,) of states x = (θ, θ') (*batch, 2)."""
    return MASS * LENGTH * (0.5 * LENGTH * x[..., 1] ** 2 + G * (1 - torch.cos(x[..., 0])))


def rollout(f, x0: torch.Tensor, steps: int, substeps: int = 1) -> torch.Tensor:
    """States (*batch, steps + 1, 2) of x' = f(t, x) from x0 by RK4 at Ts / substeps."""
    t = TS * torch.arange(steps + 1, dtype=torch.float64)
    return odeint(f, x0, t, method="rk4", substeps=substeps).x.detach()


def window_loss(model, x: torch.Tensor, horizon: int) -> float:
    """The common training loss: mean squared state error of the windows of ``horizon``
    intervals tiling every record of x (B, N, 2), each started at the measured state."""
    k = torch.arange(0, x.shape[1] - horizon, horizon)
    idx = k[:, None] + torch.arange(horizon + 1)
    starts = x[:, k].reshape(-1, 2)
    sim = rollout(model, starts, horizon).reshape(x.shape[0], k.numel(), horizon + 1, 2)
    return float(((sim - x[:, idx]) ** 2).mean())


def train_to_target(model, data: IOData, x, args, max_epochs: int):
    """L-BFGS (windows of ``args.horizon``, ``args.round_iters`` iterations per epoch) until
    :func:`window_loss` of the model being trained falls below ``args.target`` (checked
    after every epoch by the trainer's callback).

    Returns:
        (trained model, common loss, iterations, CPU seconds).
    """
    start = time.process_time()
    history = []

    def reached(epoch, state):
        history.append(window_loss(state["model"], x, args.horizon))
        return history[-1] < args.target

    result = fit(
        model,
        data,
        method="lbfgs",
        horizon=args.horizon,
        epochs=max_epochs,
        lr=1.0,
        lbfgs_max_iter=args.round_iters,
        seed=args.seed,
        callback=reached,
    )
    seconds = time.process_time() - start
    return result.model, history[-1], len(history) * args.round_iters, seconds


def main(argv=None):
    args = build_parser().parse_args(argv)
    out = output_dir(args, NAME)
    t_roll = args.t_roll or (60.0 if args.quick else 200.0)
    max_epochs = args.max_epochs or (60 if args.quick else 200)
    B, N = args.trajectories, 61
    torch.manual_seed(args.seed)
    gen = torch.Generator().manual_seed(args.seed)

    note(f"simulating {B} training swings of {(N - 1) * TS:g} s")
    theta0 = 2.0 * (2 * torch.rand(B + 1, generator=gen, dtype=torch.float64) - 1)
    x0 = torch.stack([theta0, torch.zeros_like(theta0)], -1)
    x = rollout(true_pendulum, x0[:B], N - 1, substeps=10)
    data = IOData(x.new_zeros(B, N, 0), x, Ts=TS)
    scale = x.reshape(-1, 2).std(0)
    hidden = (args.hidden, args.hidden)

    networks = {
        "neural ODE (MLP)": NeuralODE(2, 0, hidden=hidden, Ts=TS, x_scale=scale, seed=args.seed),
        "Lagrangian network": LagrangianNetwork(
            1, 0, hidden=hidden, dissipation=False, ny=2, q_scale=scale[:1], seed=args.seed
        ),
    }
    trained, rows = {}, []
    for name, model in networks.items():
        note(f"training the {name} to a common training loss < {args.target:g}")
        model, loss, iters, seconds = train_to_target(model, data, x, args, max_epochs)
        trained[name] = model
        rows.append(
            {
                "model": name,
                "train_loss": loss,
                "reached_target": loss < args.target,
                "lbfgs_iterations": iters,
                "train_cpu_s": seconds,
                "parameters": sum(p.numel() for p in model.parameters()),
            }
        )

    note("fitting the grey-box pendulum (length L free)")
    start = time.process_time()
    # the first 3 s of the widest swing from its known state: one parameter needs no more
    widest, n_grey = int(x[:, 0, 0].abs().argmax()), 31
    grey = fit(
        GreyBoxModel(Pendulum(0.8), {"L": Param(0.8, min=0.0)}, x0=x[widest, 0]),
        IOData(x.new_zeros(n_grey, 0), x[widest, :n_grey], Ts=TS),
    )
    L_hat = grey.params["L"]
    grey_model = Pendulum(L_hat)
    trained["grey-box"] = grey_model
    rows.append(
        {
            "model": "grey-box",
            "train_loss": window_loss(grey_model, x, args.horizon),
            "train_cpu_s": time.process_time() - start,
            "parameters": 1,
            "L_hat": L_hat,
        }
    )

    note(f"rollouts over {t_roll:g} s")
    steps = round(t_roll / TS)
    x_start = x0[B:]
    t_grid = TS * torch.arange(steps + 1, dtype=torch.float64)
    curves = {}
    for row in rows:
        d = rollout_diagnostics(
            trained[row["model"]],
            true_pendulum,
            x_start[0],
            t_grid,
            energy=true_energy,
            perturbation=PERTURBATION,
        )
        curves[row["model"]] = (d.x, d.error, d.energy)
        summary = d.summary()
        row["rollout_rms_error"] = float(summary["rms_error"])
        row["rollout_final_error"] = float(summary["final_error"])
        row["floor_rms_error"] = float(summary["rms_floor"])
        row["energy_drift"] = float(summary["energy_drift"])
    truth, floor = d.x_true, d.floor
    mlp, lnn = rows[0], rows[1]
    ratio = [
        {
            "t_roll_s": t_roll,
            "train_loss_ratio_mlp_over_lnn": mlp["train_loss"] / lnn["train_loss"],
            "energy_drift_ratio_mlp_over_lnn": mlp["energy_drift"] / lnn["energy_drift"],
        }
    ]
    markdown = write_table(rows, out / "summary")
    markdown += "\n" + write_table(ratio, out / "ratios")
    _figure(curves, truth, floor, out)
    (out / f"{NAME}.md").write_text(markdown)
    finish(out, markdown)
    return rows, ratio[0]


_STYLE = {"neural ODE (MLP)": "C3", "Lagrangian network": "C0", "grey-box": "C2"}


def _figure(curves, truth, floor, out) -> None:
    """Rollout error with its floor, relative energy error, phase portraits."""
    t = TS * torch.arange(truth.shape[0], dtype=torch.float64)
    fig, (ax_err, ax_energy, ax_phase) = plt.subplots(1, 3, figsize=(15, 4.2))
    for name, (xr, err, rel) in curves.items():
        ax_err.semilogy(t[1:], err[1:], color=_STYLE[name], label=name)
        ax_energy.plot(t, rel, color=_STYLE[name], label=name)
        ax_phase.plot(xr[:, 0], xr[:, 1], color=_STYLE[name], lw=0.8, label=name)
    ax_err.semilogy(t[1:], floor[1:], "k:", label="floor: truth from x0 + 1e-4")
    ax_phase.plot(truth[:, 0], truth[:, 1], "k--", lw=1.2, label="truth")
    ax_err.set_xlabel("time (s)")
    ax_err.set_ylabel("state error |x - x_true|")
    ax_err.set_title("rollout error")
    ax_energy.set_xlabel("time (s)")
    ax_energy.set_ylabel("(E(t) - E(0)) / E(0), true energy")
    ax_energy.set_title("energy drift")
    ax_phase.set_xlabel("theta (rad)")
    ax_phase.set_ylabel("theta' (rad/s)")
    ax_phase.set_title("phase portraits of the rollouts")
    for ax in (ax_err, ax_energy, ax_phase):
        ax.legend(fontsize=7)
    save_figure(fig, out / f"{NAME}.png")


if __name__ == "__main__":
    main()
