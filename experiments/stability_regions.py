"""Stability regions |R(z)| <= 1 of the explicit Runge-Kutta methods (notes Fig. 6.7, 6.14).

R(z) is the growth factor of one step on the test equation x' = lambda x, z = lambda dt
(eq. 6.40); it comes from ``ButcherTableau.stability_function``. For explicit methods with
s = o <= 4 stages it is the truncated exponential series of eq. (6.41); Dormand-Prince adds
z^6 / 600. The table lists, for each method, the stability interval on the negative real
axis [real_min, 0] (e.g. explicit Euler [-2, 0], RK4 about [-2.785, 0]) and on the
imaginary axis [-imag_max, imag_max], measured by :func:`stability_radius`.

Run: ``python -m experiments.stability_regions [--quick] [--out DIR]``.
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

NAME = "stability_regions"


def build_parser() -> argparse.ArgumentParser:
    """The command line (``--help`` lists it); built without importing torch."""
    parser = experiment_parser(
        NAME, "Stability regions of the explicit Runge-Kutta methods (notes Fig. 6.7, 6.14)."
    )
    return parser


parse_early(__name__, build_parser)

import numpy as np
from scipy.optimize import brentq

from experiments._common import plt
from integrators import TABLEAU_NAMES, ButcherTableau, tableau

EXPLICIT_METHODS = tuple(n for n in TABLEAU_NAMES if tableau(n).is_explicit)


def stability_radius(
    tab: ButcherTableau, angle: float, r_max: float = 10.0, step: float = 1e-2
) -> float:
    """Length of the stable segment of the ray z = r exp(i angle), r >= 0, that starts at 0.

    ``|R(z)| <= 1`` is scanned on r = step, 2 step, ..., r_max; the first crossing of
    ``|R| = 1`` is refined with Brent's method. A method already unstable at r = step (explicit
    Euler and the 2-stage methods on the imaginary axis) gets 0. Returns ``r_max`` when no
    crossing is found.

    Args:
        tab: the method.
        angle: direction of the ray in radians (pi: negative real axis, pi/2: imaginary axis).
        r_max: largest radius scanned.
        step: scan resolution.

    Returns:
        r* such that lambda dt = r e^(i angle) is stable for 0 < r <= r* (to ~1e-12).
    """
    direction = np.exp(1j * angle)

    def excess(r: float) -> float:
        return float(np.abs(tab.stability_function(r * direction))) - 1.0

    radii = np.arange(1, int(round(r_max / step)) + 1) * step
    values = np.abs(tab.stability_function(radii * direction)) - 1.0
    unstable = np.flatnonzero(values > 1e-12)
    if unstable.size == 0:
        return float(r_max)
    first = int(unstable[0])
    if first == 0:
        return 0.0
    return float(brentq(excess, radii[first - 1], radii[first], xtol=1e-14, rtol=1e-14))


def stability_table(methods=EXPLICIT_METHODS) -> list[dict]:
    """One row per method: stages, order, real-axis and imaginary-axis stability limits."""
    rows = []
    for name in methods:
        tab = tableau(name)
        rows.append(
            {
                "method": name,
                "stages": tab.stages,
                "order": tab.order,
                "real_min": -stability_radius(tab, np.pi),
                "imag_max": stability_radius(tab, np.pi / 2),
            }
        )
    return rows


def same_region_groups(methods, Z) -> list[tuple[list[str], np.ndarray]]:
    """The methods grouped by their stability function on the grid ``Z`` (complex array):
    methods whose |R| agree at every point of ``Z`` (e.g. the two-stage second-order methods,
    which all have R(z) = 1 + z + z^2/2) share one |R(z)| = 1 curve.

    Returns:
        ``[(names, |R| on Z), ...]`` in the order of ``methods``' first members.
    """
    groups: list[tuple[list[str], np.ndarray]] = []
    for name in methods:
        R = np.abs(tableau(name).stability_function(Z))
        for names, R_group in groups:
            if np.allclose(R, R_group, rtol=1e-10, atol=1e-12):
                names.append(name)
                break
        else:
            groups.append(([name], R))
    return groups


def plot_regions(methods, n_grid: int):
    """Figure: Euler's disc (Fig. 6.7) and the |R| = 1 contours of all methods (Fig. 6.14)."""
    x = np.linspace(-4.0, 1.5, n_grid)
    y = np.linspace(-3.5, 3.5, n_grid)
    Z = x[None, :] + 1j * y[:, None]
    fig, (ax_euler, ax_all) = plt.subplots(1, 2, figsize=(11, 5))
    euler = np.abs(tableau("euler").stability_function(Z))
    ax_euler.contourf(x, y, euler, levels=[0.0, 1.0], colors=["0.75"])
    ax_euler.contour(x, y, euler, levels=[1.0], colors="k")
    ax_euler.set_title("explicit Euler: |1 + z| <= 1 (Fig. 6.7)")
    styles = ["-", "--", "-.", ":"]
    groups = same_region_groups(methods, Z)
    for k, (names, R) in enumerate(groups):
        color, style = f"C{k}", styles[k % len(styles)]
        ax_all.contour(x, y, R, levels=[1.0], colors=[color], linestyles=[style], linewidths=1.8)
        ax_all.plot([], [], color=color, ls=style, lw=1.8, label=" = ".join(names))
    ax_all.set_title("|R(z)| = 1 of the explicit methods (Fig. 6.14)")
    ax_all.legend(
        loc="upper left",
        bbox_to_anchor=(1.02, 1.0),
        fontsize=8,
        title="one curve per R(z)",
        title_fontsize=8,
    )
    for ax in (ax_euler, ax_all):
        ax.axhline(0.0, color="0.5", lw=0.5)
        ax.axvline(0.0, color="0.5", lw=0.5)
        ax.set_aspect("equal")
        ax.set_xlabel("Re(lambda dt)")
        ax.set_ylabel("Im(lambda dt)")
    return fig


def main(argv=None) -> list[dict]:
    args = build_parser().parse_args(argv)
    out = output_dir(args, NAME)
    rows = stability_table()
    markdown = write_table(rows, out / "stability_intervals")
    save_figure(plot_regions(EXPLICIT_METHODS, 151 if args.quick else 601), out / "regions.png")
    finish(out, markdown)
    return rows


if __name__ == "__main__":
    main()
