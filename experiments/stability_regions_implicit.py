"""Stability regions |R(z)| <= 1 of the implicit Runge-Kutta methods (notes §7.1.1, §7.3).

R(z) = 1 + z b^T (I - z A)^{-1} 1 is the growth factor of one step on the test equation
x' = lambda x, z = lambda dt (eq. 6.40; eq. 7.11 for implicit Euler: R(z) = 1 / (1 - z)); it comes
from ``ButcherTableau.stability_function``. Methods: implicit Euler, implicit midpoint, Gauss-
Legendre s = 1..3 and Radau IIA s = 1..3 (``integrators.gauss_legendre`` / ``radau_iia``, built
from polynomial roots). For each the table reports

* ``max_R_imag``: max |R(iy)| over y in [-Y, Y] (log-spaced, |y| up to 1e6): A-stability needs
  <= 1 on the imaginary axis (Gauss methods: exactly 1, they are the diagonal Pade
  approximants of e^z);
* ``max_R_left``: max |R(z)| over a polar sample of the closed left half-plane (radii 1e-3 to
  1e6, angles pi/2..3pi/2): <= 1 for an A-stable method (the maximum principle then covers the
  whole half-plane, R being analytic there);
* ``R_inf``: lim |z| -> inf of R (``stability_at_infinity``, 1 - b^T A^{-1} 1): 0 for the
  L-stable Radau IIA (and implicit Euler = Radau IIA s = 1), (-1)^s for Gauss (|R| -> 1: no
  damping of infinitely stiff modes), and ``abs_R_minus_1e8`` = |R(-1e8)| as a direct check;
* ``A_stable``, ``L_stable``: the two facts read off the numbers (tolerance 1e-12).

Run: ``python -m experiments.stability_regions_implicit [--quick] [--out DIR]``.
"""

from __future__ import annotations

import argparse

from experiments._common import (
    experiment_parser,
    finish,
    output_dir,
    parse_early,
    save_figure,
    write_table,
)

NAME = "stability_regions_implicit"


def build_parser() -> argparse.ArgumentParser:
    """The command line (``--help`` lists it); built without importing torch."""
    parser = experiment_parser(
        NAME, "Stability regions, A- and L-stability of the implicit RK methods (notes §7.3)."
    )
    return parser


parse_early(__name__, build_parser)

import numpy as np

from experiments._common import plt
from integrators import ButcherTableau, gauss_legendre, radau_iia, tableau

TOL = 1e-12


def implicit_methods() -> dict[str, ButcherTableau]:
    """name -> tableau of the implicit methods studied."""
    methods = {
        "implicit_euler": tableau("implicit_euler"),
        "implicit_midpoint": tableau("implicit_midpoint"),
    }
    methods.update({f"gauss_legendre_{s}": gauss_legendre(s) for s in (1, 2, 3)})
    methods.update({f"radau_iia_{s}": radau_iia(s) for s in (1, 2, 3)})
    return methods


def sample_points(n: int) -> tuple[np.ndarray, np.ndarray]:
    """(imaginary-axis samples, closed-left-half-plane samples) as complex arrays."""
    radii = np.logspace(-3, 6, n)
    imag = 1j * np.concatenate([-radii[::-1], [0.0], radii])
    angles = np.linspace(np.pi / 2, 3 * np.pi / 2, n // 2 + 1)
    left = (radii[:, None] * np.exp(1j * angles[None, :])).ravel()
    return imag, left


def stability_table(methods: dict[str, ButcherTableau], n: int) -> list[dict]:
    """One row per method with the numbers described in the module docstring."""
    imag, left = sample_points(n)
    rows = []
    for name, tab in methods.items():
        max_imag = float(np.abs(tab.stability_function(imag)).max())
        max_left = float(np.abs(tab.stability_function(left)).max())
        r_inf = tab.stability_at_infinity()
        r_far = float(np.abs(tab.stability_function(np.array(-1e8))))
        rows.append(
            {
                "method": name,
                "stages": tab.stages,
                "order": tab.order,
                "max_R_imag": max_imag,
                "max_R_left": max_left,
                "R_inf": r_inf,
                "abs_R_minus_1e8": r_far,
                "A_stable": max_imag <= 1 + TOL and max_left <= 1 + TOL,
                "L_stable": max_imag <= 1 + TOL and max_left <= 1 + TOL and abs(r_inf) <= TOL,
            }
        )
    return rows


def plot_regions(methods: dict[str, ButcherTableau], n_grid: int):
    """|R(z)| = 1 contours and shaded instability regions (|R| > 1) of every method."""
    x = np.linspace(-8.0, 14.0, n_grid)
    y = np.linspace(-11.0, 11.0, n_grid)
    Z = x[None, :] + 1j * y[:, None]
    cols = 4
    rows = -(-len(methods) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4 * cols, 4 * rows))
    for k, (ax, (name, tab)) in enumerate(zip(axes.ravel(), methods.items(), strict=False)):
        R = np.abs(tab.stability_function(Z))
        R = np.where(np.isfinite(R), R, 1e6)
        ax.contourf(x, y, R, levels=[0.0, 1.0], colors=["0.8"])
        ax.contour(x, y, R, levels=[1.0], colors="k", linewidths=1)
        ax.axhline(0.0, color="0.4", lw=0.5)
        ax.axvline(0.0, color="0.4", lw=0.5)
        ax.set_title(f"{name} (grey: |R| <= 1)", fontsize=9)
        ax.set_aspect("equal")
        ax.set_xlabel("Re(lambda dt)")
        if k % cols == 0:  # one y-label per row: the panels' labels would overlap their neighbours
            ax.set_ylabel("Im(lambda dt)")
    for ax in axes.ravel()[len(methods) :]:
        ax.axis("off")
    return fig


def main(argv=None) -> list[dict]:
    args = build_parser().parse_args(argv)
    out = output_dir(args, NAME)
    methods = implicit_methods()
    rows = stability_table(methods, 400 if args.quick else 2000)
    markdown = write_table(rows, out / "stability")
    save_figure(plot_regions(methods, 151 if args.quick else 501), out / "regions.png")
    finish(out, markdown)
    return rows


if __name__ == "__main__":
    main()
