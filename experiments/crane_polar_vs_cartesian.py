"""The two-pendulum crane in polar vs Cartesian constrained coordinates: which model for which
question (notes §2.3 example 6, eq. 2.98-2.109, and §2.4 example 3, eq. 2.150-2.158).

Models (``sysid.zoo``; cart and both masses of mass m = 1 kg, rods L = 1 m, g = 9.81 m/s^2):

- polar ``TwoPendulumCranePolar``: q = (x, theta1, theta2), an ODE with 6 states; W(q) depends on
  q (eq. 2.105), the accelerations need a 3x3 solve (eq. 2.109);
- Cartesian ``TwoPendulumCraneCartesian``: q = (x, p1, p2) in R^5 (vertical axis pointing
  down), 10 differential states plus 2 multipliers, W = m I; simulated in its index-1 form
  (KKT system eq. 2.168, here a 2x2 Schur complement since W is diagonal), without and with
  Baumgarte stabilisation cddot + 2 alpha cdot + alpha^2 c = 0 (eq. 2.186).

Both are evaluated twice: by the autograd builder (``forward``) and by the notes' closed forms
transcribed in the zoo (``closed_form_acceleration``). Corresponding states: the polar state is
mapped to Cartesian positions p1 = (x + L sin theta1, L cos theta1), p2 = p1 + (L sin theta2,
L cos theta2) and their time derivatives (chain rule, eq. 2.2), which satisfy c = 0 and
cdot = 0 exactly (consistent initial conditions, eq. 2.182).

Measured:

1. consistency of the two models: at random states the Cartesian accelerations equal the
   second time derivatives of the mapped polar positions (chain rule applied to the polar
   qddot), to rounding;
2. cost of one right-hand-side evaluation for batch 1 and 1024 (median wall time);
3. simulations of ``--t-end`` seconds from the same initial condition with dopri5 at several
   rtol: max error of the pendulum positions p1, p2 against a reference (polar model, dopri5,
   rtol = atol = 1e-12), wall time, right-hand-side evaluations, and for the Cartesian model
   the constraint drift max |c(q(t))| and max |cdot| (eq. 2.185).

Writes ``rhs_cost.csv/.md``, ``simulation.csv/.md``, ``consistency.csv/.md``,
``conclusions.md`` and ``crane_polar_vs_cartesian.png``. Everything runs on one intra-op thread
(restored afterwards): on a shared machine, thread hand-offs of tiny tensor operations measure
the scheduler, not the model. Wall times depend on the machine and its load (the CPU time of
each simulation is reported too); ratios measured in the same process are the meaningful
numbers.

Run: ``python -m experiments.crane_polar_vs_cartesian [--quick] [--out DIR]``.
"""

from __future__ import annotations

import time

import numpy as np
import torch
from torch import nn

from experiments._common import experiment_parser, output_dir, plt, save_figure, write_table
from integrators import odeint
from sysid.zoo import TwoPendulumCraneCartesian, TwoPendulumCranePolar

NAME = "crane_polar_vs_cartesian"
DT = torch.float64
M, L, G = 1.0, 1.0, 9.81
ALPHA = 10.0  # Baumgarte gain [1/s]
X0_POLAR = (0.0, 0.6, -0.4, 0.3, 0.0, 0.5)  # (x, theta1, theta2, xdot, theta1dot, theta2dot)
REFERENCE_TOL = 1e-12


def polar_to_cartesian(x: torch.Tensor, length: float = L) -> torch.Tensor:
    """Map polar states (*batch, 6) to Cartesian states (*batch, 10) of the same motion.

    q = (x, theta1, theta2) -> (x, p1, p2), vertical axis down (eq. 2.99-2.102 with the y axis
    flipped to the Cartesian model's convention); velocities by the chain rule (eq. 2.2).
    """
    cart, t1, t2 = x[..., 0], x[..., 1], x[..., 2]
    v, w1, w2 = x[..., 3], x[..., 4], x[..., 5]
    s1, c1, s2, c2 = torch.sin(t1), torch.cos(t1), torch.sin(t2), torch.cos(t2)
    p1x, p1y = cart + length * s1, length * c1
    p2x, p2y = p1x + length * s2, p1y + length * c2
    v1x, v1y = v + length * c1 * w1, -length * s1 * w1
    v2x, v2y = v1x + length * c2 * w2, v1y - length * s2 * w2
    return torch.stack([cart, p1x, p1y, p2x, p2y, v, v1x, v1y, v2x, v2y], -1)


def polar_point_accelerations(x: torch.Tensor, qddot: torch.Tensor, length: float = L):
    """Accelerations (*batch, 5) of (x, p1, p2) implied by polar states and qddot (the second
    time derivative of the map of :func:`polar_to_cartesian`)."""
    t1, t2, w1, w2 = x[..., 1], x[..., 2], x[..., 4], x[..., 5]
    a, b1, b2 = qddot[..., 0], qddot[..., 1], qddot[..., 2]
    s1, c1, s2, c2 = torch.sin(t1), torch.cos(t1), torch.sin(t2), torch.cos(t2)
    a1x = a + length * (c1 * b1 - s1 * w1**2)
    a1y = -length * (s1 * b1 + c1 * w1**2)
    a2x = a1x + length * (c2 * b2 - s2 * w2**2)
    a2y = a1y - length * (s2 * b2 + c2 * w2**2)
    return torch.stack([a, a1x, a1y, a2x, a2y], -1)


def positions_of(model_name: str, x: torch.Tensor) -> torch.Tensor:
    """Pendulum positions (p1x, p1y, p2x, p2y) (*batch, T, 4) of a trajectory."""
    if model_name == "polar":
        return polar_to_cartesian(x)[..., 1:5]
    return x[..., 1:5]


def random_polar_states(n: int, seed: int) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed)
    scale = torch.tensor([1.0, np.pi, np.pi, 1.0, 2.0, 2.0], dtype=DT)
    return (2 * torch.rand(n, 6, generator=gen, dtype=DT) - 1) * scale


def consistency_rows(n: int = 256, seed: int = 0) -> list[dict]:
    """Cartesian accelerations vs the mapped polar ones at random states (both evaluations)."""
    polar, cart = TwoPendulumCranePolar(M, L, G), TwoPendulumCraneCartesian(M, L, G)
    for model in (polar, cart):
        model.requires_grad_(False)
    xp = random_polar_states(n, seed)
    xc = polar_to_cartesian(xp)
    with torch.no_grad():
        c, cdot = cart.drift(xc)
        qdd_builder = polar(0.0, xp)[..., 3:]
        qdd_closed = polar.closed_form_acceleration(xp[..., :3], xp[..., 3:])
        expected = polar_point_accelerations(xp, qdd_builder)
        cart_builder = cart(0.0, xc)[..., 5:]
        cart_closed, _ = cart.closed_form_acceleration(xc[..., :5], xc[..., 5:])
    return [
        {"check": "mapped state: max |c|", "value": float(c.abs().max())},
        {"check": "mapped state: max |cdot|", "value": float(cdot.abs().max())},
        {
            "check": "polar builder vs closed form eq. 2.105-2.109: max |qddot diff|",
            "value": float((qdd_builder - qdd_closed).abs().max()),
        },
        {
            "check": "Cartesian builder vs closed form eq. 2.157: max |qddot diff|",
            "value": float((cart_builder - cart_closed).abs().max()),
        },
        {
            "check": "Cartesian accelerations vs mapped polar: max |diff|",
            "value": float((cart_builder - expected).abs().max()),
        },
    ]


def median_time(fn, args: tuple, repeats: int) -> float:
    """Median wall time of ``fn(*args)`` over ``repeats`` calls after two warm-up calls [s]."""
    fn(*args), fn(*args)
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn(*args)
        times.append(time.perf_counter() - start)
    return float(np.median(times))


def rhs_cost_rows(batches, repeats: int) -> list[dict]:
    polar, cart = TwoPendulumCranePolar(M, L, G), TwoPendulumCraneCartesian(M, L, G, ALPHA)
    for model in (polar, cart):
        model.requires_grad_(False)
    rows = []
    for batch in batches:
        xp = random_polar_states(batch, seed=1)
        xc = polar_to_cartesian(xp)
        qp, vp, qc, vc = xp[..., :3], xp[..., 3:], xc[..., :5], xc[..., 5:]
        cases = {
            ("polar", "autograd builder"): (polar, (0.0, xp)),
            ("polar", "closed form (2.105-2.109)"): (polar.closed_form_acceleration, (qp, vp)),
            ("Cartesian", "autograd builder"): (cart, (0.0, xc)),
            ("Cartesian", "closed form KKT (2.157)"): (cart.closed_form_acceleration, (qc, vc)),
        }
        with torch.no_grad():
            base = None
            for (model_name, form), (fn, fn_args) in cases.items():
                seconds = median_time(fn, fn_args, repeats)
                base = base or seconds
                rows.append(
                    {
                        "model": model_name,
                        "form": form,
                        "batch": batch,
                        "n_states": 6 if model_name == "polar" else 10,
                        "us_per_call": 1e6 * seconds,
                        "us_per_state_vector": 1e6 * seconds / batch,
                        "ratio_to_polar_builder": seconds / base,
                    }
                )
    return rows


class ClosedFormPolar(nn.Module):
    """xdot = [qdot, qddot] of the polar crane from the notes' closed form (eq. 2.105-2.109,
    typos fixed in the zoo)."""

    def __init__(self, plant: TwoPendulumCranePolar):
        super().__init__()
        self.plant = plant

    def forward(self, t, x, u=None):
        q, qdot = x[..., :3], x[..., 3:]
        return torch.cat([qdot, self.plant.closed_form_acceleration(q, qdot, u)], -1)


class ClosedFormCartesian(nn.Module):
    """xdot = [qdot, qddot] of the Cartesian crane from the KKT system of eq. (2.156)-(2.158)
    transcribed in the zoo, with the constraint rows of the right-hand side shifted by
    -2 alpha cdot - alpha^2 c (Baumgarte, eq. 2.186) when ``alpha`` is given."""

    def __init__(self, plant: TwoPendulumCraneCartesian, alpha: float | None):
        super().__init__()
        self.plant, self.alpha = plant, alpha

    def forward(self, t, x, u=None):
        q, qdot = x[..., :5], x[..., 5:]
        kkt, rhs = self.plant.closed_form_kkt(q, qdot, u)
        if self.alpha is not None:
            a = kkt[..., 5:, :5]  # dc/dq
            c = self.plant.constraints(q)
            cdot = (a @ qdot.unsqueeze(-1)).squeeze(-1)
            shift = 2 * self.alpha * cdot + self.alpha**2 * c
            rhs = torch.cat([rhs[..., :5], rhs[..., 5:] - shift], -1)
        qddot = torch.linalg.solve(kkt, rhs.unsqueeze(-1))[..., :5, 0]
        return torch.cat([qdot, qddot], -1)


def make_rhs(model_name: str, form: str, alpha):
    """(rhs module, plant) for ``model_name`` in {"polar", "Cartesian"} and ``form`` in
    {"closed form", "builder"}; the builder is the plant itself (``forward``)."""
    if model_name == "polar":
        plant = TwoPendulumCranePolar(M, L, G).requires_grad_(False)
        return (ClosedFormPolar(plant) if form == "closed form" else plant), plant
    plant = TwoPendulumCraneCartesian(M, L, G, alpha).requires_grad_(False)
    return (ClosedFormCartesian(plant, alpha) if form == "closed form" else plant), plant


def simulate(model_name: str, form: str, alpha, x0_polar, t, rtol):
    """One dopri5 simulation (rtol = atol); returns (solution, (wall, CPU) time [s], plant)."""
    rhs, plant = make_rhs(model_name, form, alpha)
    x0 = x0_polar if model_name == "polar" else polar_to_cartesian(x0_polar)
    start, cpu = time.perf_counter(), time.process_time()
    with torch.no_grad():
        sol = odeint(rhs, x0, t, method="dopri5", rtol=rtol, atol=rtol)
    return sol, (time.perf_counter() - start, time.process_time() - cpu), plant


def simulation_rows(variants, t_end: float, n_out: int):
    """Simulate every (model, form, alpha, rtol) of ``variants`` and compare the pendulum
    positions with the reference; returns (rows, t, reference positions, curves)."""
    t = torch.linspace(0.0, t_end, n_out, dtype=DT)
    x0 = torch.tensor([X0_POLAR], dtype=DT)
    ref, (ref_time, ref_cpu), _ = simulate("polar", "closed form", None, x0, t, REFERENCE_TOL)
    ref_pos = positions_of("polar", ref.x)
    rows, curves = [], {}
    for model_name, form, alpha, rtol in variants:
        sol, (seconds, cpu), plant = simulate(model_name, form, alpha, x0, t, rtol)
        err = (positions_of(model_name, sol.x) - ref_pos).abs().amax(-1)[0]
        row = {
            "model": model_name,
            "form": form,
            "baumgarte_alpha": "none" if alpha is None else alpha,
            "rtol": rtol,
            "max_position_error": float(err.max()),
            "wall_time_s": seconds,
            "cpu_time_s": cpu,
            "f_evals": int(torch.as_tensor(sol.stats.n_f_evals).max()),
            "steps": int(torch.as_tensor(sol.stats.n_steps).max()),
            "status": int(sol.status.max()),
        }
        if model_name == "Cartesian":
            with torch.no_grad():
                c, cdot = plant.drift(sol.x)
            row["max_abs_c"] = float(c.abs().max())
            row["max_abs_cdot"] = float(cdot.abs().max())
            row["final_abs_c"] = float(c[0, -1].abs().max())
            curves[("drift", form, rtol, alpha)] = c[0].abs().amax(-1)
        rows.append(row)
        curves[(model_name, form, rtol, alpha)] = err
    rows.append(
        {
            "model": "polar (reference)",
            "form": "closed form",
            "baumgarte_alpha": "none",
            "rtol": REFERENCE_TOL,
            "wall_time_s": ref_time,
            "cpu_time_s": ref_cpu,
            "f_evals": int(torch.as_tensor(ref.stats.n_f_evals).max()),
            "steps": int(torch.as_tensor(ref.stats.n_steps).max()),
            "status": int(ref.status.max()),
        }
    )
    return rows, t, ref_pos[0], curves


def variants_for(quick: bool) -> list[tuple]:
    """(model, form, alpha, rtol) of the simulations: closed forms at every tolerance, the
    builders at every tolerance (full run) or at the loosest one (quick run)."""
    tolerances = (1e-5, 1e-8) if quick else (1e-4, 1e-6, 1e-8, 1e-10)
    closed = [("polar", None), ("Cartesian", None), ("Cartesian", ALPHA)]
    builder = [("polar", None), ("Cartesian", ALPHA)]
    out = [(m, "closed form", a, r) for r in tolerances for m, a in closed]
    builder_tols = tolerances[:1] if quick else tolerances
    return out + [(m, "builder", a, r) for r in builder_tols for m, a in builder]


def conclusions(cost_rows, sim_rows, consistency) -> str:
    """The Markdown conclusion, with the measured numbers filled in."""

    def cost(model, form, batch):
        return next(
            r["us_per_call"]
            for r in cost_rows
            if r["model"] == model and r["form"].startswith(form) and r["batch"] == batch
        )

    small, big = min(r["batch"] for r in cost_rows), max(r["batch"] for r in cost_rows)
    tight = min(r["rtol"] for r in sim_rows if r["model"] == "polar")
    tight_builder = min(r["rtol"] for r in sim_rows if r["form"] == "builder")

    def sim(model, alpha, form="closed form", rtol=tight):
        return next(
            r
            for r in sim_rows
            if r["model"] == model
            and r["form"] == form
            and r["baumgarte_alpha"] == alpha
            and r["rtol"] == rtol
        )

    pol, free, stab = sim("polar", "none"), sim("Cartesian", "none"), sim("Cartesian", ALPHA)
    pol_b = sim("polar", "none", "builder", tight_builder)
    stab_b = sim("Cartesian", ALPHA, "builder", tight_builder)
    err_ratio = stab["max_position_error"] / pol["max_position_error"]
    eval_ratio = stab["f_evals"] / pol["f_evals"]
    builder_ratio = cost("polar", "autograd", small) / cost("Cartesian", "autograd", small)
    mismatch = consistency[-1]["value"]
    return f"""# Two-pendulum crane: polar vs Cartesian constrained coordinates

Both models describe the same motion: at 256 random states the Cartesian accelerations equal
the mapped polar ones to {mismatch:.1e}. Simulations: dopri5, rtol = atol, from the same
initial state; errors are the max over time of the pendulum positions against the reference.

| question | polar | Cartesian |
|---|---|---|
| states | 6 (ODE) | 10 differential + 2 multipliers (index-1 DAE) |
| one rhs, closed form, batch {small} / {big} [us] | {cost("polar", "closed", small):.0f} / \
{cost("polar", "closed", big):.0f} | {cost("Cartesian", "closed", small):.0f} / \
{cost("Cartesian", "closed", big):.0f} |
| one rhs, autograd builder, batch {small} / {big} [us] | \
{cost("polar", "autograd", small):.0f} / {cost("polar", "autograd", big):.0f} | \
{cost("Cartesian", "autograd", small):.0f} / {cost("Cartesian", "autograd", big):.0f} |
| position error at rtol {tight:g} | {pol["max_position_error"]:.1e} | \
{free["max_position_error"]:.1e} (no stab.), {stab["max_position_error"]:.1e} \
(alpha = {ALPHA:g}) |
| rhs evaluations / CPU time at rtol {tight:g}, closed forms | {pol["f_evals"]} / \
{pol["cpu_time_s"]:.2f} s | {stab["f_evals"]} / {stab["cpu_time_s"]:.2f} s (alpha = {ALPHA:g}) |
| same with the builders at rtol {tight_builder:g} | {pol_b["f_evals"]} / \
{pol_b["cpu_time_s"]:.2f} s | {stab_b["f_evals"]} / {stab_b["cpu_time_s"]:.2f} s |
| constraint drift max abs c at rtol {tight:g} | none by construction | \
{free["max_abs_c"]:.1e} (no stab.), {stab["max_abs_c"]:.1e} (alpha = {ALPHA:g}) |

Which model for which question:

- Simulation of this crane (prediction, control design, identification of its physical
  parameters): the polar model. At the same tolerance the stabilised Cartesian model needs
  {eval_ratio:.1f}x the right-hand-side evaluations (the Baumgarte term adds a fast mode
  of rate {ALPHA:g}/s) and is {err_ratio:.1f}x less accurate on the positions; without
  stabilisation its constraints drift (|c| grows like the integration error). The polar model
  has the minimal number of states, no consistency conditions on the initial state and no
  drift. The price of the polar model is its derivation (the notes stop at eq. 2.109); the
  autograd builder removes it, but it is the more expensive builder path: a q-dependent W
  costs {builder_ratio:.1f}x the Cartesian builder per evaluation at batch {small}.
- Deriving a model quickly, adding pendulums or changing the geometry, closed kinematic
  loops where no minimal coordinates exist: the Cartesian model. W = m I is constant, every
  term is bilinear (eq. 2.157), N pendulums only add rows, and per evaluation it costs about
  the same as the polar closed form. It needs consistent initial conditions (eq. 2.182), a
  KKT (Schur complement) solve per evaluation, and stabilisation of the drift (eq. 2.186).
"""


def main(argv=None) -> list[dict]:
    parser = experiment_parser(NAME, "Two-pendulum crane: polar vs Cartesian coordinates.")
    parser.add_argument("--t-end", type=float, default=5.0, help="simulated horizon [s]")
    args = parser.parse_args(argv)
    out = output_dir(args, NAME)
    t_end = min(args.t_end, 2.0) if args.quick else args.t_end
    batches, repeats = ((1, 256), 5) if args.quick else ((1, 1024), 30)

    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # on a shared machine, intra-op threads measure the scheduler
    try:
        consistency = consistency_rows()
        cost_rows = rhs_cost_rows(batches, repeats)
        sim_rows, t, ref_pos, curves = simulation_rows(variants_for(args.quick), t_end, 201)
    finally:
        torch.set_num_threads(threads)
    markdown = write_table(consistency, out / "consistency")
    markdown += "\n" + write_table(cost_rows, out / "rhs_cost")
    markdown += "\n" + write_table(sim_rows, out / "simulation")
    text = conclusions(cost_rows, sim_rows, consistency)
    (out / "conclusions.md").write_text(text)

    fig, axes = plt.subplots(1, 3, figsize=(16, 4.2))
    for k, label in enumerate(("p1x", "p1y", "p2x", "p2y")):
        axes[0].plot(t, ref_pos[:, k], label=label)
    axes[0].set_title("reference positions (polar, dopri5, rtol 1e-12), y axis down")
    axes[0].set_xlabel("t [s]")
    axes[0].legend(fontsize=8)
    for key, err in curves.items():
        name, form, rtol, alpha = key
        if form == "builder":  # same trajectories as the closed forms (see simulation.csv)
            continue
        tag = "no stab." if alpha is None else f"alpha = {alpha:g}"
        if name == "drift":
            axes[2].semilogy(t, err.clamp_min(1e-17), label=f"{tag}, rtol {rtol:g}")
        else:
            style = "-" if name == "polar" else ("--" if alpha is None else ":")
            label = f"{name}{'' if name == 'polar' else ' ' + tag}, rtol {rtol:g}"
            axes[1].semilogy(t, err.clamp_min(1e-17), style, label=label)
    axes[1].set_title("max position error vs reference (closed forms; builders coincide)")
    axes[2].set_title("Cartesian constraint drift max |c(q(t))|")
    for ax in axes[1:]:
        ax.set_xlabel("t [s]")
        ax.legend(fontsize=6)
    save_figure(fig, out / "crane_polar_vs_cartesian.png")
    print(markdown + "\n" + text)
    return sim_rows


if __name__ == "__main__":
    main()
