"""Model only what the scene needs: the ladder linear OE -> grey-box physics -> hybrid ->
neural ODE -> Lagrangian network on one data set, validation error against cost.

Plant: the crane of the course notes (Modelling and Simulation), eq. 2.55-2.70 (cart mass
M, load m on a rope of length L, angle theta), state (x, theta, xdot, thetadot), with viscous
friction ``d`` on the cart and a known centring spring ``k`` (so that the cart stays near
the origin under a random force). The cart force is ``u - d xdot - k x`` (generalised force
(F, 0), eq. 2.115, through W(q)^-1 of eq. 2.60). Measured: cart position and rope angle with
white noise, under a random force held constant over 10 samples (``intersample="zoh"``).
Two scenes:

* ``physics``: exactly that plant: the grey-box model is the true structure;
* ``friction``: the same plant with an unmodelled Coulomb friction ``F_c tanh(xdot / v_s)``
  on the cart, which the grey-box physics lacks.

Each rung is fitted on the estimation record and judged by its free-run simulation on a
separate validation record (from rest, like the data), skipping an initialisation window:

1. linear OE(4, 4, 1), one per output (``sysid.fit``, Gauss-Newton);
2. grey-box physics: the crane with free (M, L, d), m and k known (Levenberg-Marquardt by
   multiple shooting: over a record of dozens of swings the simulation error has local
   minima near the start, e.g. L = 0.98 instead of 0.8 on the full run's data);
3. hybrid: that physics, started at the grey-box estimate, plus a residual network on the
   accelerations (L-BFGS on the free-run error of the whole record from rest);
4. neural ODE: an MLP right-hand side with 4 states, 2 of them measured (Adam on windows
   from estimated initial states, as the next rung);
5. Lagrangian network: learned mass matrix L(q) L(q)^T + eps I, potential and dissipation,
   the force acting on the cart coordinate.

Reported per rung: validation fit % and RMSE per output, training time (wall clock), number
of estimated parameters (network weights plus physical parameters; initial states not
counted), and AIC / FPE of the free-run residuals on the estimation data after the same
window (``sysid.validation``; FPE is infinite where the parameters outnumber the samples;
for the networks the parameter count is the weight count, so
the criteria are the classical formulas applied to an over-parameterised model, not a
statement about its effective degrees of freedom).

Run: ``python -m experiments.model_ladder [--quick] [--out DIR]``.
"""

from __future__ import annotations

import argparse
import math
import time

from experiments._common import (
    experiment_parser,
    finish,
    note,
    output_dir,
    parse_early,
    readable_log_ticks,
    save_figure,
    write_table,
)

NAME = "model_ladder"
SCENES = ("physics", "friction")
RUNGS = ("linear OE", "grey-box", "hybrid", "neural ODE", "Lagrangian network")


def build_parser() -> argparse.ArgumentParser:
    """The command line (``--help`` lists it); built without importing torch."""
    parser = experiment_parser(NAME, __doc__.splitlines()[0])
    parser.add_argument(
        "--samples",
        type=int,
        default=None,
        help="samples of the estimation and of the validation record (default 600, 120 with "
        "--quick)",
    )
    parser.add_argument(
        "--epochs",
        type=int,
        default=None,
        help="training epochs of the networks (default 150, 6 with --quick)",
    )
    parser.add_argument(
        "--hidden",
        type=int,
        default=None,
        help="hidden width of the networks (default 32, 16 with --quick)",
    )
    parser.add_argument(
        "--skip", type=int, default=20, help="initialisation window left out of the errors"
    )
    parser.add_argument("--seed", type=int, default=0, help="seed of the data and trainings")
    return parser


parse_early(__name__, build_parser)

import torch

from experiments._common import plt
from sysid import (
    OE,
    GreyBoxModel,
    HybridODE,
    IOData,
    LagrangianNetwork,
    NeuralODE,
    Param,
    fit,
)
from sysid.montecarlo import input_signal
from sysid.validation import aic, fit_quality, fpe

G = 9.81
TS = 0.05
TRUE = {"M": 2.0, "m": 0.5, "L": 0.8, "d": 0.4, "k": 2.0}
#: grey-box start: M, L, d off by 20 %, 12 %, 25 %; m and k known
START = {"M": 2.4, "L": 0.9, "d": 0.3}
COULOMB = 0.5  # N, friction level F_c of the "friction" scene
V_SLIP = 0.05  # m/s, smoothing velocity v_s of tanh
FORCE = 2.0  # N, standard deviation of the random force
HOLD = 10  # samples the force is held
NOISE = 0.002  # m and rad, measurement noise standard deviation


def crane(t, x, u, p, coulomb: float = 0.0):
    """Crane right-hand side (eq. 2.70) with the cart force ``u - d xdot - k x`` and an
    optional Coulomb friction ``coulomb * tanh(xdot / V_SLIP)``; x (*batch, 4), u (*batch, 1)."""
    s, c = torch.sin(x[..., 1]), torch.cos(x[..., 1])
    M, m, L = p["M"], p["m"], p["L"]
    force = u[..., 0] - p["d"] * x[..., 2] - p["k"] * x[..., 0]
    if coulomb:
        force = force - coulomb * torch.tanh(x[..., 2] / V_SLIP)
    den = M + m - m * c**2
    xdd = (m * s * (L * x[..., 3] ** 2 + G * c) + force) / den
    thdd = -(s * ((M + m) * G + m * L * c * x[..., 3] ** 2) + c * force) / (L * den)
    return torch.stack([x[..., 2], x[..., 3], xdd, thdd], -1)


def scene_data(scene: str, N: int, seed: int) -> IOData:
    """One record of N samples from rest: the force (N, 1), noisy (x, theta) (N, 2)."""
    g = torch.Generator().manual_seed(seed)
    levels = FORCE * input_signal("white", N // HOLD + 1, generator=g)
    u = levels.repeat_interleave(HOLD, 0)[:N]
    coulomb = COULOMB if scene == "friction" else 0.0
    truth = GreyBoxModel(
        lambda t, x, u, p: crane(t, x, u, p, coulomb), dict(TRUE), nx=4, output=[0, 1], substeps=8
    )
    y = truth.simulate(IOData(u, torch.zeros(N, 2, dtype=u.dtype), Ts=TS))
    y = y + NOISE * torch.randn(y.shape, generator=g, dtype=y.dtype)
    return IOData(u, y, Ts=TS)


def state_scales(data: IOData) -> torch.Tensor:
    """(4,) scales of (x, theta, xdot, thetadot): output standard deviations and those of
    their finite-difference rates."""
    y = data.y
    rate = (y[1:] - y[:-1]) / data.Ts
    return torch.cat([y.std(0), rate.std(0)])


def greybox_model(values: dict) -> GreyBoxModel:
    params = {k: Param(v, min=0.0) for k, v in values.items()}
    params.update(m=Param(TRUE["m"], free=False), k=Param(TRUE["k"], free=False))
    return GreyBoxModel(crane, params, nx=4, output=[0, 1])


def _record(name, est, val, yhat_est, yhat_val, n_params, seconds, skip):
    q = fit_quality(val.y, yhat_val, skip=skip)
    e = (est.y - yhat_est)[skip:]
    return {
        "model": name,
        "fit_x_percent": float(q.fit_percent[0]),
        "fit_theta_percent": float(q.fit_percent[1]),
        "rmse_x_m": float(q.rmse[0]),
        "rmse_theta_rad": float(q.rmse[1]),
        "error_percent": float(100 - q.fit_percent.mean()),
        "train_seconds": seconds,
        "n_params": n_params,
        "aic": float(aic(e, n_params)),
        # FPE is undefined (infinite) once the parameters outnumber the samples
        "fpe": float(fpe(e, n_params)) if n_params < e.shape[-2] else math.inf,
    }


def linear_oe(est, val, skip):
    start = time.perf_counter()
    models = []
    for j in range(2):
        res = fit(OE(4, 4, 1, Ts=TS), IOData(est.u, est.y[:, j : j + 1], Ts=TS))
        models.append(res.model)
    seconds = time.perf_counter() - start
    with torch.no_grad():
        y_est = torch.cat([m.simulate(est.u) for m in models], -1)
        y_val = torch.cat([m.simulate(val.u) for m in models], -1)
    n = sum(m.n_params for m in models)
    return _record("linear OE", est, val, y_est, y_val, n, seconds, skip), None


def greybox(est, val, skip):
    model = greybox_model(START)
    start = time.perf_counter()
    res = fit(model, est, x0="zero", criterion="multiple_shooting")
    seconds = time.perf_counter() - start
    values = {n: float(v) for n, v in zip(res.parameter_names, res.theta, strict=True)}
    y_est = model.simulate(est, params=values)
    y_val = model.simulate(val, params=values)
    rec = _record("grey-box", est, val, y_est, y_val, len(values), seconds, skip)
    rec.update({f"{n}_estimate": v for n, v in values.items()})
    return rec, values


def _train(model, est, args, **kw):
    """Adam on windows of ``args.horizon`` intervals from estimated initial states, or the
    options ``kw`` instead."""
    options = dict(
        method="adam",
        horizon=args.horizon,
        batch_size=16,
        epochs=args.epochs,
        steps_per_epoch=args.steps,
        lr=args.lr,
        schedule="cosine",
        x0="estimate",
        seed=args.seed,
        progress=False,
    )
    options.update(kw)
    start = time.perf_counter()
    res = fit(model, est, **options)
    return res, time.perf_counter() - start


def _network_record(name, res, seconds, est, val, skip, extra=0):
    with torch.no_grad():
        y_est = res.simulate(est)
        y_val = res.simulate(val)
    n = sum(p.numel() for p in res.model.parameters() if p.requires_grad) + extra
    return _record(name, est, val, y_est, y_val, n, seconds, skip)


def hybrid(est, val, skip, values, scales, args):
    physics = greybox_model(values)
    model = HybridODE(
        physics,
        hidden=(args.hidden, args.hidden),
        residual_states=[2, 3],
        nu=1,
        Ts=TS,
        x_scale=scales,
        u_scale=FORCE,
        seed=args.seed,
    )
    # the whole record from rest by L-BFGS: the model starts at the grey-box estimate, so the
    # free-run criterion is already near its minimum (no windows needed)
    res, seconds = _train(
        model,
        est,
        args,
        method="lbfgs",
        horizon=est.N - 1,
        epochs=args.lbfgs_epochs,
        lr=1.0,
        x0="zero",
        schedule=None,
        lbfgs_max_iter=args.lbfgs_iter,
    )
    rec = _network_record("hybrid", res, seconds, est, val, skip)
    rec.update({f"{n}_estimate": v for n, v in res.params.items()})
    return rec


def neural_ode(est, val, skip, scales, args):
    model = NeuralODE(
        4,
        1,
        ny=2,
        hidden=(args.hidden, args.hidden),
        Ts=TS,
        x_scale=scales,
        u_scale=FORCE,
        seed=args.seed,
    )
    res, seconds = _train(model, est, args)
    return _network_record("neural ODE", res, seconds, est, val, skip)


def lagrangian(est, val, skip, scales, args):
    model = LagrangianNetwork(
        2,
        1,
        hidden=(args.hidden, args.hidden),
        input_map=torch.tensor([[1.0], [0.0]], dtype=torch.float64),
        q_scale=scales[:2],
        seed=args.seed,
    )
    res, seconds = _train(model, est, args)
    return _network_record("Lagrangian network", res, seconds, est, val, skip)


def run_scene(scene, args):
    est = scene_data(scene, args.samples, 2 * args.seed)
    val = scene_data(scene, args.samples, 2 * args.seed + 1)
    scales = state_scales(est)
    skip = args.skip
    rows = []
    note(f"{scene}: linear OE and grey-box fits")
    rows.append(linear_oe(est, val, skip)[0])
    rec, values = greybox(est, val, skip)
    rows.append(rec)
    note(f"{scene}: hybrid, neural ODE and Lagrangian network, {args.epochs} epochs each")
    rows.append(hybrid(est, val, skip, values, scales, args))
    rows.append(neural_ode(est, val, skip, scales, args))
    rows.append(lagrangian(est, val, skip, scales, args))
    for row in rows:
        row["scene"] = scene
    return rows


def figure(rows):
    fig, axes = plt.subplots(1, 2, figsize=(10, 4), sharey=True)
    markers = dict(zip(RUNGS, "osD^v", strict=True))
    colors = {"physics": "tab:blue", "friction": "tab:red"}
    for scene in SCENES:
        part = [r for r in rows if r["scene"] == scene]
        for ax, cost in zip(axes, ("train_seconds", "n_params"), strict=True):
            ax.plot(
                [r[cost] for r in part],
                [r["error_percent"] for r in part],
                color=colors[scene],
                lw=0.8,
                alpha=0.5,
                label=f"{scene} scene",
            )
            for r in part:
                ax.plot(r[cost], r["error_percent"], markers[r["model"]], color=colors[scene])
    for rung, marker in markers.items():
        axes[1].plot([], [], marker, color="0.3", label=rung)
    for ax, label in zip(axes, ("training time [s]", "number of parameters"), strict=True):
        ax.set_xscale("log")
        ax.set_yscale("log")
        readable_log_ticks(ax.xaxis)
        readable_log_ticks(ax.yaxis)
        ax.set_xlabel(label)
        ax.grid(True, which="both", alpha=0.3)
    axes[0].set_ylabel("validation error, 100 - mean fit [%]")
    axes[0].legend(fontsize=8)
    axes[1].legend(fontsize=7, loc="upper right")
    fig.suptitle("Crane: validation free-run error against cost, per rung of the ladder")
    return fig


def main(argv=None):
    args = build_parser().parse_args(argv)
    out = output_dir(args, NAME)
    torch.set_num_threads(1)
    args.samples = args.samples or (120 if args.quick else 600)
    args.epochs = args.epochs or (6 if args.quick else 150)
    args.hidden = args.hidden or (16 if args.quick else 32)
    args.steps = 3 if args.quick else 10
    args.lbfgs_epochs = 1 if args.quick else 10
    args.lbfgs_iter = 8 if args.quick else 20
    args.horizon = 10 if args.quick else 20
    args.lr = 1e-2 if args.quick else 5e-3
    rows = []
    for scene in SCENES:
        rows.extend(run_scene(scene, args))
    columns = ["scene", "model"] + [k for k in rows[0] if k not in ("scene", "model")]
    columns += [k for r in rows for k in r if k not in columns]
    table = [{k: r.get(k, "") for k in columns} for r in rows]
    markdown = write_table(table, out / NAME)
    fig = figure(rows)
    save_figure(fig, out / f"{NAME}.png")
    finish(out, markdown)
    return rows, fig


if __name__ == "__main__":
    main()
