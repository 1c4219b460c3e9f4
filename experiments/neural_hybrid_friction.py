"""A hybrid model learns an unmodelled friction while its physical parameters stay unbiased.

Run with no arguments (``python -m experiments.neural_hybrid_friction``); ``--quick`` is the
seconds-long variant the tests use.

1. Plant: the spring-mass-damper of the course notes (Modelling and Simulation), eq. 1.26 /
   1.28, ``m x'' + c x' + k x + F(x') = u``, with an unmodelled smooth Stribeck friction

       F(v) = (F_c + (F_s - F_c) exp(-(v / v_s)^2)) tanh(v / v_eps)

   (Coulomb level F_c, breakaway level F_s at low speed, Stribeck velocity v_s, smoothing
   velocity v_eps; of the order of the input force, so far from negligible). Data:
   ``records`` training experiments and one held-out validation experiment, each from rest
   under its own random-phase multisine force (``intersample="foh"``), simulated by RK4 at
   Ts / 20 (Ts = 0.1 s); position and velocity measured with white noise.
2. Models, both fitted through ``sysid.fit``:
   - grey-box physics without friction, ``m x'' + c x' + k x = u`` with m, c, k free
     (Gauss-Newton on the free-run error, known initial state at rest);
   - hybrid: ``x'' = (u - k x) / m + r(x')``, the physics with m, k free plus a residual
     network on the acceleration that sees the velocity only (a small module passed as the
     ``network`` of :class:`sysid.continuous.HybridODE`, which selects the velocity from the
     normalised state). The viscous term is left to the network: a linear ``c x'`` is
     indistinguishable from the linear part of ``r(x')`` (only ``c / m + r`` enters the
     model), so a free c would not be identifiable; m and k are, through the input and the
     spring. Trained by L-BFGS on windows of 10 intervals (initial states estimated),
     started at the grey-box estimate of (m, k); RK4 at Ts = 0.1 s.
3. Reported: the physical parameters with their standard errors (grey-box: ``sigma^2
   (J'J)^-1``, eq. 4.101; hybrid: the same form with the network weights and the initial
   states as nuisance parameters, see :mod:`sysid.continuous.training`) and their errors in
   standard-error units; the learned velocity-dependent force ``D(v) = -m r(v)`` against the
   true one ``c v + F(v)`` on the velocity range of the training data (relative RMS); the
   validation free run from rest: fit % and RMSE per state. "Within 3 SE" fails where the
   network has not converged or where the residual cannot represent the friction.

Writes ``neural_hybrid_friction.csv/.md`` (one row per model) and ``neural_hybrid_friction.png``
(learned and true velocity-dependent force, validation free runs of both models).
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

NAME = "neural_hybrid_friction"


def build_parser() -> argparse.ArgumentParser:
    """The command line (``--help`` lists it); built without importing torch."""
    parser = experiment_parser(NAME, __doc__.splitlines()[0])
    parser.add_argument(
        "--records",
        type=int,
        default=None,
        help="training experiments (default 6, 2 with --quick)",
    )
    parser.add_argument(
        "--t-record",
        type=float,
        default=None,
        help="length of every experiment in s (default 40, 10 with --quick)",
    )
    parser.add_argument(
        "--hidden",
        type=int,
        default=None,
        help="width of both hidden layers of the residual (default 32, 16 with --quick)",
    )
    parser.add_argument(
        "--epochs",
        type=int,
        default=None,
        help="L-BFGS epochs of the hybrid (default 10, 5 with --quick)",
    )
    parser.add_argument("--seed", type=int, default=0, help="seed of data and training")
    return parser


parse_early(__name__, build_parser)

import time

import torch
from torch import nn

from experiments._common import plt
from sysid import GreyBoxModel, HybridODE, IOData, Param, fit
from sysid.validation import fit_quality

TS = 0.1
TRUE = {"m": 1.0, "c": 0.4, "k": 4.0}
#: Stribeck friction (N, N, m/s, m/s): Coulomb level, breakaway level, Stribeck velocity,
#: smoothing velocity of the sign
F_C, F_S, V_S, V_EPS = 1.0, 1.5, 0.3, 0.1
FORCE = 3.0  # N, standard deviation of the multisine force
BAND = (0.05, 1.0)  # Hz, frequency band of the multisine
NOISE = (0.01, 0.04)  # m, m/s: measurement noise standard deviations
SUBSTEPS_TRUE = 20


def friction(v: torch.Tensor) -> torch.Tensor:
    """The Stribeck friction force F(v) (N) at velocities v (m/s), any shape."""
    return (F_C + (F_S - F_C) * torch.exp(-((v / V_S) ** 2))) * torch.tanh(v / V_EPS)


def msd(t, x, u, p, with_friction: bool = False):
    """Spring-mass-damper (notes eq. 1.28) ``x = (position, velocity)`` (*batch, 2), force u
    (*batch, 1), parameters p["m"], p["c"], p["k"]; plus the friction F(v) when asked."""
    force = u[..., 0] - p["c"] * x[..., 1] - p["k"] * x[..., 0]
    if with_friction:
        force = force - friction(x[..., 1])
    return torch.stack([x[..., 1], force / p["m"]], -1)


def multisine(N: int, generator: torch.Generator) -> torch.Tensor:
    """(N, 1) random-phase multisine force: every DFT frequency of the record in ``BAND``,
    equal amplitudes, scaled to the standard deviation ``FORCE``."""
    t = TS * torch.arange(N, dtype=torch.float64)
    f0 = 1.0 / (N * TS)
    freqs = f0 * torch.arange(max(1, round(BAND[0] / f0)), round(BAND[1] / f0) + 1)
    phase = 2 * torch.pi * torch.rand(freqs.numel(), generator=generator, dtype=torch.float64)
    u = torch.sin(2 * torch.pi * freqs[:, None] * t + phase[:, None]).sum(0)
    return (FORCE * u / u.std())[:, None]


def record(N: int, generator: torch.Generator) -> tuple[IOData, torch.Tensor]:
    """One experiment from rest: (noisy data, true states (N, 2))."""
    u = multisine(N, generator)
    truth = GreyBoxModel(
        lambda t, x, u, p: msd(t, x, u, p, with_friction=True),
        {n: Param(v, free=False) for n, v in TRUE.items()},
        nx=2,
        substeps=SUBSTEPS_TRUE,
    )
    with torch.no_grad():
        x = truth.simulate(IOData(u, u.new_zeros(N, 2), Ts=TS, intersample="foh"))
    noise = torch.tensor(NOISE, dtype=x.dtype)
    y = x + noise * torch.randn(x.shape, generator=generator, dtype=x.dtype)
    return IOData(u, y, Ts=TS, intersample="foh"), x


class VelocityResidual(nn.Module):
    """Residual network of the hybrid on the velocity only: ``z (*batch, nx + nu) ->
    (*batch, 1)``, a tanh MLP of the normalised velocity ``z[..., 1]`` whose last layer
    starts at zero (the initial hybrid model is exactly the physics)."""

    def __init__(self, hidden: int, generator: torch.Generator):
        super().__init__()
        self.mlp = nn.Sequential(
            nn.Linear(1, hidden),
            nn.Tanh(),
            nn.Linear(hidden, hidden),
            nn.Tanh(),
            nn.Linear(hidden, 1),
        ).double()
        gain = nn.init.calculate_gain("tanh")
        with torch.no_grad():
            for layer in self.mlp[::2]:
                nn.init.xavier_uniform_(layer.weight, gain=gain, generator=generator)
                layer.bias.zero_()
            self.mlp[-1].weight.zero_()

    def forward(self, z):
        return self.mlp(z[..., 1:2])


def greybox(data: IOData):
    """Grey-box fit without friction, m, c, k free (started at the truth, bounded below by
    0). Returns (fit result, the GreyBoxModel, CPU seconds)."""
    model = GreyBoxModel(msd, {n: Param(v, min=0.0) for n, v in TRUE.items()}, nx=2, compile=False)
    start = time.process_time()
    res = fit(model, data, x0="zero")
    return res, model, time.process_time() - start


def hybrid(data: IOData, start: dict, hidden: int, epochs: int, seed: int, horizon: int = 10):
    """The hybrid model started at ``start`` (m, k; c fixed at 0, the viscous term left to
    the residual), trained by L-BFGS (20 iterations per epoch) on the windows of ``horizon``
    intervals tiling the records, initial states of the windows estimated. Returns
    (training result, CPU seconds)."""
    physics = GreyBoxModel(
        msd,
        {
            "m": Param(start["m"], min=0.0),
            "c": Param(0.0, free=False),
            "k": Param(start["k"], min=0.0),
        },
        nx=2,
        compile=False,
    )
    x_scale = torch.cat([e.y for e in data.experiment_list]).std(0)
    network = VelocityResidual(hidden, torch.Generator().manual_seed(seed))
    model = HybridODE(physics, network, residual_states=[1], nu=1, x_scale=x_scale, u_scale=FORCE)
    began = time.process_time()
    res = fit(
        model,
        data,
        method="lbfgs",
        horizon=horizon,
        epochs=epochs,
        lr=1.0,
        lbfgs_max_iter=20,
        x0="estimate",
        seed=seed,
        progress=False,
    )
    return res, time.process_time() - began


def learned_force(model, v: torch.Tensor) -> torch.Tensor:
    """The hybrid's velocity-dependent force ``-m r(v)`` (N) at velocities v (n,)."""
    x = torch.stack([torch.zeros_like(v), v], -1)
    with torch.no_grad():
        r = model.residual(x, v.new_zeros(v.shape[0], 1))[..., 0]
        return -model.physical_values()["m"] * r


def main(argv=None):
    args = build_parser().parse_args(argv)
    out = output_dir(args, NAME)
    torch.set_num_threads(1)
    B = args.records or (2 if args.quick else 6)
    t_record = args.t_record or (10.0 if args.quick else 40.0)
    hidden = args.hidden or (16 if args.quick else 32)
    epochs = args.epochs or (5 if args.quick else 10)
    gen = torch.Generator().manual_seed(args.seed)
    N = round(t_record / TS) + 1

    note(f"simulating {B + 1} experiments of {t_record:g} s (the last one for validation)")
    records = [record(N, gen) for _ in range(B + 1)]
    data = IOData.experiments([d for d, _ in records[:B]])
    val, x_val = records[B]

    note("grey-box fit without friction (m, c, k free)")
    gb, gb_model, gb_seconds = greybox(data)
    gb_values = {n: float(v) for n, v in zip(gb.parameter_names, gb.theta, strict=True)}
    y_gb = gb_model.simulate(val, params=gb_values)
    note(f"hybrid: physics (m, k free) + velocity residual, L-BFGS {epochs} epochs")
    hy, hy_seconds = hybrid(data, gb_values, hidden, epochs, args.seed)
    y_hy = hy.simulate(val, x0=torch.zeros(2, dtype=torch.float64))

    v_train = torch.cat([e.y[:, 1] for e in data.experiment_list])
    lo, hi = float(v_train.quantile(0.01)), float(v_train.quantile(0.99))
    v = torch.linspace(lo, hi, 201, dtype=torch.float64)
    true_force = TRUE["c"] * v + friction(v)
    force_hat = learned_force(hy.model, v)
    force_rel_rms = float(
        (force_hat - true_force).pow(2).mean().sqrt() / true_force.pow(2).mean().sqrt()
    )

    rows = []
    for name, res, yhat, seconds in (
        ("grey-box (no friction)", gb, y_gb, gb_seconds),
        ("hybrid", hy, y_hy, hy_seconds),
    ):
        q = fit_quality(val.y, yhat)
        row = {"model": name}
        for n in ("m", "c", "k"):
            if n in res.parameter_names:
                i = res.parameter_names.index(n)
                est, se = float(res.theta[i]), float(res.standard_errors[i])
                row.update(
                    {f"{n}_hat": est, f"{n}_se": se, f"{n}_error_in_se": (est - TRUE[n]) / se}
                )
            else:
                row.update({f"{n}_hat": "", f"{n}_se": "", f"{n}_error_in_se": ""})
        row.update(
            {
                "max_abs_error_in_se": max(
                    abs(row[f"{n}_error_in_se"])
                    for n in ("m", "c", "k")
                    if row[f"{n}_error_in_se"] != ""
                ),
                "val_fit_position_pct": float(q.fit_percent[0]),
                "val_fit_velocity_pct": float(q.fit_percent[1]),
                "val_rmse_position_m": float(q.rmse[0]),
                "val_rmse_velocity_m_s": float(q.rmse[1]),
                "force_rel_rms": force_rel_rms if name == "hybrid" else "",
                "cpu_s": seconds,
            }
        )
        rows.append(row)
    markdown = write_table(rows, out / NAME)
    fig = _figure(v, true_force, force_hat, gb_values, val, x_val, y_gb, y_hy)
    save_figure(fig, out / f"{NAME}.png")
    finish(out, markdown)
    return rows, {"v": v, "true_force": true_force, "learned_force": force_hat}


def _figure(v, true_force, force_hat, gb_values, val, x_val, y_gb, y_hy):
    """Learned vs true velocity-dependent force; validation free runs (position, velocity)."""
    fig, (ax_f, ax_x, ax_v) = plt.subplots(1, 3, figsize=(15, 4.2))
    ax_f.plot(v, true_force, "k", lw=2, label="true: c v + F(v)")
    ax_f.plot(v, force_hat, "r--", lw=1.5, label="hybrid: -m r(v)")
    ax_f.plot(v, gb_values["c"] * v, "b:", lw=1.5, label="grey-box: c v")
    ax_f.set_xlabel("velocity (m/s)")
    ax_f.set_ylabel("velocity-dependent force (N)")
    ax_f.set_title("friction on the training velocity range")
    ax_f.legend(fontsize=7)
    t = TS * torch.arange(val.N, dtype=torch.float64)
    for ax, j, unit in ((ax_x, 0, "position (m)"), (ax_v, 1, "velocity (m/s)")):
        ax.plot(t, x_val[:, j], "k", lw=1.5, label="true")
        ax.plot(t, y_gb[:, j], "b:", lw=1.2, label="grey-box (no friction)")
        ax.plot(t, y_hy[:, j], "r--", lw=1.2, label="hybrid")
        ax.set_xlabel("time (s)")
        ax.set_ylabel(unit)
        ax.set_title(f"validation free run: {unit.split()[0]}")
        ax.legend(fontsize=7)
    return fig


if __name__ == "__main__":
    main()
