"""Constrained crane in index-1 KKT form: (M, m, L) recovered through the DAE grey-box path.

Plant: the rigid-rod crane in Cartesian coordinates of the zoo (``RigidCraneCartesian``,
the course notes (Modelling and Simulation), eq. 2.138-2.149): q = (x, p1, p2), constraint
c(q) = (|p - (x, 0)|^2 - L^2) / 2, a horizontal force on the cart. Its index-1 form is the
KKT system of eq. 2.168 with Baumgarte stabilisation c'' + 2 alpha c' + alpha^2 c = 0
(eq. 2.186): a semi-explicit DAE x' = f(x, z, u), 0 = g(x, z, u) with the multiplier z.

Data: ``trials`` records simulated by ``integrators.daeint`` of the index-1 DAE at the true
parameters (Radau IIA, 4 steps per sample), cart position x and load position p1 measured
with white noise. Fit: ONE batched ``sysid.fit`` of a ``GreyBoxModel`` over the same DAE (the
multiplier eliminated by Newton at every RK4 stage, its derivatives by the implicit function
theorem). Reported: the estimates, their standard errors and the errors in SE units. The
index-3 form (g = c(q), dg/dz = 0) is given to the same fit and refused with
``HighIndexError``.

Run: ``python -m experiments.greybox_constrained [--quick] [--out DIR]``.
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

NAME = "greybox_constrained"


def build_parser() -> argparse.ArgumentParser:
    """The command line (``--help`` lists it); built without importing torch."""
    parser = experiment_parser(NAME, __doc__.splitlines()[0])
    parser.add_argument(
        "--trials", type=int, default=None, help="data sets (default 20, 4 with --quick)"
    )
    parser.add_argument(
        "--samples",
        type=int,
        default=None,
        help="samples per data set (default 300, 100 with --quick)",
    )
    parser.add_argument("--baumgarte", type=float, default=5.0, help="Baumgarte alpha in 1/s")
    parser.add_argument("--seed", type=int, default=0, help="seed of inputs and noise")
    return parser


parse_early(__name__, build_parser)

import torch
from torch import nn

from experiments._common import plt
from integrators import SemiExplicitDAE, daeint
from integrators.errors import HighIndexError
from sysid import GreyBoxModel, IOData, Param, fit
from sysid.montecarlo import input_signal
from sysid.zoo import RigidCraneCartesian

TRUE = {"M": 2.0, "m": 0.5, "L": 0.8}
START = {"M": 2.5, "m": 0.4, "L": 0.9}
TS, NOISE = 0.05, 0.002


class CraneDAE(nn.Module):
    """The rigid crane as a semi-explicit DAE module with the multiplier z: ``f`` and ``g`` of
    its index-1 KKT form (eq. 2.168, Baumgarte eq. 2.186), or with ``index=3`` the position
    constraint itself as the algebraic equation (eq. 2.126, dg/dz = 0). The parameters are
    the plant's, named ``crane.M``, ``crane.m``, ``crane.L``."""

    nz = 1

    def __init__(self, baumgarte: float, index: int = 1):
        super().__init__()
        self.crane = RigidCraneCartesian(**TRUE, baumgarte=baumgarte)
        self.form = self.crane.index1_dae if index == 1 else self.crane.index3_dae

    def f(self, t, x, z, u=None):
        return self.form()[0](t, x, z, u)

    def g(self, t, x, z, u=None):
        return self.form()[1](t, x, z, u)


def at_rest(L: float) -> torch.Tensor:
    """The consistent state with the load hanging still below the cart at x = 0."""
    return torch.tensor([0.0, 0.0, L, 0.0, 0.0, 0.0], dtype=torch.float64)


def crane_data(trials: int, N: int, alpha: float, seed: int) -> IOData:
    """Cart and load positions (x, p1) from daeint of the index-1 DAE, plus white noise."""
    g = torch.Generator().manual_seed(seed)
    u = 2.0 * input_signal("prbs", N, (trials,), hold=5, generator=g)
    plant = RigidCraneCartesian(**TRUE, baumgarte=alpha)
    problem = SemiExplicitDAE(*plant.index1_dae())
    t = TS * torch.arange(N, dtype=torch.float64)
    x0 = at_rest(TRUE["L"]).expand(trials, 6)
    with torch.no_grad():
        sol = daeint(
            problem,
            x0,
            torch.zeros(trials, 1, dtype=torch.float64),
            t,
            u=u,
            adaptive=False,
            substeps=4,
        )
    y = sol.x[..., :2]
    return IOData(u, y + NOISE * torch.randn(y.shape, generator=g, dtype=y.dtype), Ts=TS)


def main(argv=None):
    args = build_parser().parse_args(argv)
    out = output_dir(args, NAME)
    trials = args.trials or (4 if args.quick else 20)
    N = args.samples or (100 if args.quick else 300)
    note(f"daeint: {trials} records of {N} samples of the index-1 KKT crane")
    data = crane_data(trials, N, args.baumgarte, args.seed)
    start = {f"crane.{n}": Param(v, min=0.0) for n, v in START.items()}
    names = RigidCraneCartesian().state_names
    kw = dict(nx=6, state_names=names, output=["x", "p1"], x0=at_rest(TRUE["L"]), substeps=2)
    note(f"fit: one batched DAE grey-box fit of {trials} data sets")
    res = fit(GreyBoxModel(CraneDAE(args.baumgarte), start, **kw), data)
    rows = []
    for j, n in enumerate(res.parameter_names):
        est, se = res.theta[:, j], res.standard_errors[:, j]
        name = n.removeprefix("crane.")
        err = (est - TRUE[name]) / se
        rows.append(
            {
                "parameter": name,
                "true": TRUE[name],
                "mean_estimate": float(est.mean()),
                "mean_se": float(se.mean()),
                "max_abs_error_in_se": float(err.abs().max()),
                "within_3se": float((err.abs() <= 3).double().mean()),
            }
        )
    try:
        fit(GreyBoxModel(CraneDAE(args.baumgarte, index=3), start, **kw), data[:1])
        refused = "accepted"
    except HighIndexError as exc:
        refused = f"HighIndexError: {str(exc).split(':')[0]}"
    summary = [
        {
            "trials": trials,
            "samples": N,
            "baumgarte": args.baumgarte,
            "converged": float(res.converged.double().mean()),
            "index3_form": refused,
        }
    ]
    fig, axes = plt.subplots(1, len(rows), figsize=(3.2 * len(rows), 3.0))
    for j, (ax, r) in enumerate(zip(axes, rows, strict=True)):
        ax.errorbar(
            range(trials), res.theta[:, j], yerr=3 * res.standard_errors[:, j], fmt="o", ms=3
        )
        ax.axhline(r["true"], color="k", lw=1)
        ax.set_title(f"{r['parameter']}: estimate +- 3 SE")
        ax.set_xlabel("data set")
    save_figure(fig, out / "estimates.png")
    tables = [write_table(summary, out / "summary"), write_table(rows, out / "estimates")]
    finish(out, *tables)
    return summary[0], rows


if __name__ == "__main__":
    main()
