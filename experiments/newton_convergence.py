"""Convergence of Newton iterations: quadratic, linear, and rescued by damping (notes §3).

Three studies, each an error-per-iteration curve on a semi-log plot:

1. Exact Jacobian (notes Fig. 3.3): the error "collapses", e_{k+1} ~ C e_k^2 (Theorem 3).
2. Approximate Jacobian (notes Fig. 3.5): the error follows a straight line,
   e_{k+1} ~ kappa e_k with kappa = rho(I - M^{-1} J(x*)) (Theorem 6, eq. 3.45-3.47). Two
   approximations: M frozen at x0 (simplified Newton) and M = 1.5 J(x) (kappa = 1/3).
3. Damping (notes Fig. 3.2 and 3.4, Theorem 4): full Newton steps on arctan(x) = 0 from
   x0 = 2 oscillate with growing amplitude (Newton diverges for |x0| > 1.3917), while
   Armijo-damped steps converge.

Problems: the scalar x^3 - 2 = 0 (x* = 2^{1/3}) and the vector system
x1^2 + x2^2 = 4, exp(x1) + x2 = 1 (x* from scipy.optimize.fsolve).

Run: ``python -m experiments.newton_convergence [--quick] [--out DIR]``.
"""

from __future__ import annotations

import argparse
import math

from experiments._common import (
    experiment_parser,
    finish,
    output_dir,
    parse_early,
    save_figure,
    write_table,
)

NAME = "newton_convergence"


def build_parser() -> argparse.ArgumentParser:
    """The command line (``--help`` lists it); built without importing torch."""
    parser = experiment_parser(
        NAME, "Quadratic vs linear Newton convergence and damping (notes Fig. 3.2-3.5)."
    )
    return parser


parse_early(__name__, build_parser)

import numpy as np
import torch
from scipy.optimize import fsolve

from experiments._common import plt
from integrators import batch_jacobian, newton

F64 = torch.float64
ERROR_FLOOR = 1e-14


def scalar_phi(x):
    return x**3 - 2.0


def vector_phi(x):
    x1, x2 = x[..., 0], x[..., 1]
    return torch.stack([x1**2 + x2**2 - 4.0, torch.exp(x1) + x2 - 1.0], -1)


def scaled_jacobian(phi):
    """M = 1.5 dphi/dx: I - M^{-1} J = I / 3, a linear rate of exactly 1/3."""

    def jac(x):
        return 1.5 * batch_jacobian(phi, x)[1]

    return jac


def _rates(errors: np.ndarray) -> tuple[float, float]:
    """(median ratio e_{k+1}/e_k while 1e-12 < e_k < 1e-2, observed order from the last three
    errors above the rounding floor)."""
    window = (errors[:-1] > 1e-12) & (errors[:-1] < 1e-2) & (errors[1:] > ERROR_FLOOR)
    ratios = errors[1:][window] / errors[:-1][window]
    ratio = float(np.median(ratios)) if ratios.size else math.nan
    e = errors[errors > ERROR_FLOOR]
    if e.size >= 3:
        order = math.log(e[-1] / e[-2]) / math.log(e[-2] / e[-3])
    else:
        order = math.nan
    return ratio, order


def run_case(problem, phi, x0, x_star, label, max_iter, predicted=math.nan, **options):
    res = newton(phi, x0, return_history=True, max_iter=max_iter, **options)
    errors = (res.x_history - x_star).abs().amax(-1)[:, 0].numpy()
    errors = errors[: int(res.iterations[0]) + 1]
    ratio, order = _rates(errors)
    row = {
        "problem": problem,
        "variant": label,
        "method": options.get("method", "full"),
        "converged": bool(res.converged[0]),
        "iterations": int(res.iterations[0]),
        "final_error": float(errors[-1]),
        "observed_order": order if bool(res.converged[0]) else math.nan,
        "linear_rate": ratio,
        "predicted_ratio": predicted,
        "n_factorizations": res.n_factorizations,
    }
    return row, errors, res


def main(argv=None) -> list[dict]:
    args = build_parser().parse_args(argv)
    out = output_dir(args, NAME)
    max_iter = 100 if args.quick else 200
    tol = 1e-14

    x_s = torch.tensor([[2.0 ** (1 / 3)]], dtype=F64)
    x0_s = torch.tensor([[2.0]], dtype=F64)
    root = fsolve(
        lambda z: [z[0] ** 2 + z[1] ** 2 - 4, math.exp(z[0]) + z[1] - 1], [1.0, -1.0], xtol=1e-15
    )
    x_v = torch.as_tensor(root, dtype=F64)[None]
    x0_v = torch.tensor([[1.0, -1.0]], dtype=F64)
    kappa_scalar = 1.0 - 3.0 * float(x_s) ** 2 / (3.0 * 2.0**2)  # M = phi'(x0) = 12
    j0 = batch_jacobian(vector_phi, x0_v)[1][0]
    js = batch_jacobian(vector_phi, x_v)[1][0]
    kappa_vector = float(
        torch.linalg.eigvals(torch.eye(2, dtype=F64) - torch.linalg.solve(j0, js)).abs().max()
    )

    cases = [
        ("scalar", scalar_phi, x0_s, x_s, "exact Jacobian", dict()),
        (
            "scalar",
            scalar_phi,
            x0_s,
            x_s,
            "M frozen at x0",
            dict(method="simplified", predicted=kappa_scalar),
        ),
        (
            "scalar",
            scalar_phi,
            x0_s,
            x_s,
            "M = 1.5 J",
            dict(jacobian=scaled_jacobian(scalar_phi), predicted=1 / 3),
        ),
        ("vector", vector_phi, x0_v, x_v, "exact Jacobian", dict()),
        (
            "vector",
            vector_phi,
            x0_v,
            x_v,
            "M frozen at x0",
            dict(method="simplified", predicted=kappa_vector),
        ),
        (
            "vector",
            vector_phi,
            x0_v,
            x_v,
            "M = 1.5 J",
            dict(jacobian=scaled_jacobian(vector_phi), predicted=1 / 3),
        ),
        (
            "arctan",
            torch.atan,
            torch.tensor([[2.0]], dtype=F64),
            torch.zeros(1, 1, dtype=F64),
            "full steps",
            dict(method="full"),
        ),
        (
            "arctan",
            torch.atan,
            torch.tensor([[2.0]], dtype=F64),
            torch.zeros(1, 1, dtype=F64),
            "damped (Armijo)",
            dict(method="damped"),
        ),
    ]
    rows, curves = [], {}
    for problem, phi, x0, x_star, label, opts in cases:
        row, errors, _ = run_case(
            problem,
            phi,
            x0,
            x_star,
            label,
            6 if problem == "arctan" else max_iter,
            tol=tol,
            **opts,
        )
        rows.append(row)
        curves[(problem, label)] = errors
    markdown = write_table(rows, out / "newton_convergence")

    fig, axes = plt.subplots(1, 3, figsize=(15, 4))
    for ax, problem in zip(axes[:2], ("scalar", "vector"), strict=True):
        for (prob, label), errors in curves.items():
            if prob == problem:
                ax.semilogy(np.maximum(errors, 1e-17), "o-", label=label)
        ax.set_title(f"{problem} problem (Fig. 3.3 / 3.5)")
        ax.set_xlabel("iteration k")
        ax.set_ylabel("||x_k - x*||_inf")
        ax.legend()
    ax = axes[2]
    for label in ("full steps", "damped (Armijo)"):
        ax.semilogy(np.maximum(curves[("arctan", label)], 1e-17), "o-", label=label)
    ax.set_title("arctan(x) = 0 from x0 = 2 (Fig. 3.2 / 3.4)")
    ax.set_xlabel("iteration k")
    ax.set_ylabel("|x_k - x*|")
    ax.legend()
    save_figure(fig, out / "newton_convergence.png")
    finish(out, markdown)
    return rows


if __name__ == "__main__":
    main()
