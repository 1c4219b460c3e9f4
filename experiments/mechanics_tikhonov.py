"""Tikhonov's theorem (notes Theorem 8, Fig. 5.1 and 5.3): fast dynamics -> DAE limit.

(1) Eq. (5.36), x1' = -x1 + x2, eps x2' = x1 - a x2 + u, a = 2, x(0) = (1, 1), for eps from
1e-1 to 4e-3 against its limit (5.37)/(5.38). (2) The two-mass system eq. (5.41) for m1 from
1e-1 to 4e-4 (rho = 1, K = 1e3, m2 = 1, x(0) = (1, 1), xdot(0) = 0) against the reduced model
(5.43) (m1 = 0). Both are linear with a piecewise-constant input, so each family is simulated
exactly in one batched call (Jacobians by sysid.linearize, batched over the parameter, then
the ZOH matrix exponential, eq. 1.55). Reports the largest deviation from the limit and the
fitted slope of log(error) against log(eps) (expected 1: the limit is approached like eps).
"""

from __future__ import annotations

import torch

from experiments._common import experiment_parser, output_dir, plt, save_figure, write_table
from sysid.linearize import linearize, simulate_lti_zoh
from sysid.zoo import SingularlyPerturbedLinear, TwoMassSystem

NAME = "mechanics_tikhonov"
DT = torch.float64


def _input(steps, dt):
    """Piecewise-constant input switching every second between +1 and -1 (as in Fig. 5.1)."""
    t = torch.arange(steps, dtype=DT) * dt
    return torch.where((t.floor() % 2) == 0, 1.0, -1.0)[:, None]


def _simulate(fun, x0, u, dt):
    """Exact samples of a linear model fun(t, x, u) with ZOH input u (T, 1), batched over x0."""
    with torch.no_grad():
        a, b, _, _ = linearize(fun, x0, torch.zeros(*x0.shape[:-1], 1, dtype=DT))
        return simulate_lti_zoh(a, b, x0, u.expand(*x0.shape[:-1], -1, -1), dt)


def _slope(params, errors):
    lx = torch.log(torch.tensor(params, dtype=DT))
    ly = torch.log(torch.tensor(errors, dtype=DT))
    lx, ly = lx - lx.mean(), ly - ly.mean()
    return float((lx * ly).sum() / (lx * lx).sum())


def main(argv=None):
    parser = experiment_parser(NAME, __doc__.splitlines()[0])
    parser.add_argument("--t-end", type=float, default=4.0)
    parser.add_argument("--dt", type=float, default=1e-3)
    args = parser.parse_args(argv)
    if args.quick:
        args.t_end, args.dt = 2.0, 5e-3
    out = output_dir(args, NAME)
    steps = round(args.t_end / args.dt)
    u = _input(steps, args.dt)
    t = torch.arange(steps + 1, dtype=DT) * args.dt
    rows = []

    # (1) eq. (5.36) against (5.38): x1' = (1/a - 1) x1 + u / a
    eps = [1e-1, 3e-2, 1e-2, 4e-3]
    family = SingularlyPerturbedLinear(eps=torch.tensor(eps, dtype=DT)[:, None], a=2.0)
    x = _simulate(family, torch.ones(len(eps), 2, dtype=DT), u, args.dt)
    limit_model = SingularlyPerturbedLinear(a=2.0)
    x1_limit = _simulate(
        lambda tt, s, uu: limit_model.reduced(tt, s, uu), torch.ones(1, 1, dtype=DT), u, args.dt
    )[0, :, 0]
    err_536 = [float((x[i, :, 0] - x1_limit).abs().max()) for i in range(len(eps))]
    slope_536 = _slope(eps, err_536)
    rows += [
        {
            "system": "eq. 5.36",
            "parameter": "eps",
            "value": e,
            "max_error_x1": err,
            "fitted_slope": round(slope_536, 3),
        }
        for e, err in zip(eps, err_536, strict=True)
    ]

    # (2) two-mass system eq. (5.41) against (5.43)
    m1 = [1e-1, 1e-2, 1e-3, 4e-4]
    masses = TwoMassSystem(m1=torch.tensor(m1, dtype=DT)[:, None])
    x0 = torch.tensor([[1.0, 1.0, 0.0, 0.0]], dtype=DT).expand(len(m1), -1)
    s = _simulate(masses, x0, u, args.dt)
    reduced = TwoMassSystem()
    s_red = _simulate(reduced.ode_543, torch.tensor([[1.0, 1.0, 0.0]], dtype=DT), u, args.dt)[0]
    err_541 = [float((s[i, :, 1] - s_red[:, 1]).abs().max()) for i in range(len(m1))]
    slope_541 = _slope(m1[1:], err_541[1:])
    rows += [
        {
            "system": "eq. 5.41 -> 5.43",
            "parameter": "m1",
            "value": m,
            "max_error_x2": err,
            "fitted_slope": round(slope_541, 3),
        }
        for m, err in zip(m1, err_541, strict=True)
    ]

    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8))
    for i in range(len(eps)):
        axes[0].plot(t, x[i, :, 0], color="0.6", lw=0.8, label="ODE (5.36)" if i == 0 else None)
    axes[0].plot(t, x1_limit, "k", label="DAE limit (5.37)")
    axes[0].set_title(f"x1, eps = {eps[0]:g} ... {eps[-1]:g}")
    for i in range(len(m1)):
        axes[1].plot(t, s[i, :, 1], color="0.6", lw=0.8, label="ODE (5.41)" if i == 0 else None)
    axes[1].plot(t, s_red[:, 1], "k", label="reduced (5.43)")
    axes[1].set_title(f"x2, m1 = {m1[0]:g} ... {m1[-1]:g}")
    for ax in axes:
        ax.set_xlabel("t [s]")
        ax.legend(fontsize=8)
    save_figure(fig, out / "tikhonov.png")
    write_table(rows, out / "tikhonov")
    return rows


if __name__ == "__main__":
    for row in main():
        print(row)
