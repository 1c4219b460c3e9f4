"""Each implicit-method experiment (issue 3, item 7) runs with --quick into tmp_path; numbers
from its CSV are checked against independent truth: closed-form stability functions (eq. 7.11,
diagonal Pade), the classical orders 2s / 2s-1 of collocation methods, numpy eigenvalues of
eq. 6.42, and agreement between independent ways of computing sensitivities (notes §7-8).

Typo note (eq. 6.42): the fast block must be scaled by 1/eps, not eps (see
``sysid.zoo.StiffLinear``); the eigenvalue check below uses that reading.
"""

from __future__ import annotations

import csv
import math

import numpy as np

from experiments._common import figure_defects


def read_csv(path) -> list[dict]:
    with open(path, newline="") as handle:
        return list(csv.DictReader(handle))


def by_key(rows: list[dict], key: str) -> dict[str, dict]:
    return {row[key]: row for row in rows}


# ----------------------------------------------------------- implicit Euler, Fig. 7.1
def stiff_linear_eigenvalues(eps: float = 5e-4) -> np.ndarray:
    """Eigenvalues of eq. 6.42 with the fast block scaled by 1/eps, built here with numpy."""
    e = 1.0 / eps
    a = np.array(
        [[0, 5, 1, 0], [-5, 0, 0, 0.5], [0, 0, -0.1 * e, e], [0, e, -e, -0.1 * e]], dtype=float
    )
    return np.linalg.eigvals(a)


def test_implicit_euler_stays_bounded_and_converges_linearly(tmp_path, saved_figures):
    from experiments import implicit_euler_stiff

    implicit_euler_stiff.main(["--quick", "--out", str(tmp_path)])
    assert saved_figures
    for name, fig in saved_figures.items():
        assert figure_defects(fig) == [], name  # labelled axes, legible ticks
    assert (tmp_path / "trajectories.png").exists() and (tmp_path / "implicit_euler.md").exists()
    rows = read_csv(tmp_path / "implicit_euler.csv")
    implicit = {float(r["dt"]): r for r in rows if r["method"] == "implicit_euler"}
    explicit = next(r for r in rows if r["method"] == "euler")
    fast = stiff_linear_eigenvalues()
    fast = fast[np.abs(fast) > 100]
    for dt in (2e-2, 1e-3):
        row = implicit[dt]
        assert int(row["status"]) == 0
        # |R| of implicit Euler at the fast modes, eq. 7.11: 1 / |1 - lambda dt| < 1
        assert math.isclose(
            float(row["abs_R"]), float(np.max(1 / np.abs(1 - fast * dt))), rel_tol=1e-9
        )
        assert float(row["abs_R"]) < 1
        assert float(row["max_abs_x"]) < 1.5  # bounded (exact solution stays below ~1.1)
    # global error O(dt) (eq. 7.7): slope of log error between dt = 2e-2 and 1e-3
    e_coarse, e_fine = float(implicit[2e-2]["error_final"]), float(implicit[1e-3]["error_final"])
    assert e_fine < e_coarse < 0.2
    slope = float(read_csv(tmp_path / "slope.csv")[0]["slope"])
    assert math.isclose(slope, math.log(e_coarse / e_fine) / math.log(20.0), rel_tol=1e-12)
    assert 0.8 < slope < 1.2
    # explicit Euler at dt = 2e-2: |1 + lambda dt| ~ 40 > 1 (eq. 7.9), the state explodes
    assert math.isclose(
        float(explicit["abs_R"]), float(np.max(np.abs(1 + fast * 2e-2))), rel_tol=1e-9
    )
    assert float(explicit["abs_R"]) > 30
    assert float(explicit["max_abs_x"]) > 1e10


# ------------------------------------------------------- convergence orders, Fig. 7.2
def test_collocation_orders_and_fig72(tmp_path, saved_figures, reference_slope_mismatches):
    from experiments import convergence_implicit

    convergence_implicit.main(["--quick", "--out", str(tmp_path)])
    fig = saved_figures["convergence.png"]
    assert figure_defects(fig) == []  # includes: no overlapping tick labels on the dt axis
    ax72, ax_ord = fig.axes
    assert len([line for line in ax72.lines if "(p = " in line.get_label()]) == 2
    assert len([line for line in ax_ord.lines if "(p = " in line.get_label()]) == 6
    assert reference_slope_mismatches(ax72) == [] and reference_slope_mismatches(ax_ord) == []
    assert (tmp_path / "convergence.png").exists()
    rows = read_csv(tmp_path / "orders.csv")
    seen = set()
    for row in rows:
        s = int(row["stages"])
        expected = 2 * s if row["family"] == "gauss_legendre" else 2 * s - 1
        assert int(row["order"]) == expected
        assert int(row["points_fitted"]) >= 3, row
        assert abs(float(row["fitted_slope"]) - expected) <= 0.2, row
        seen.add((row["family"], s))
    assert {(f, s) for f in ("gauss_legendre", "radau_iia") for s in (1, 2, 3)} <= seen

    fig72 = read_csv(tmp_path / "fig72.csv")

    def finest_slope(label: str) -> float:
        pts = sorted(
            (float(r["dt"]), float(r["error"]))
            for r in fig72
            if r["method"] == label and int(r["status"]) == 0 and float(r["error"]) > 1e-12
        )[:3]
        d, e = np.log(np.array(pts)).T
        return float(np.polyfit(d, e, 1)[0])

    assert abs(finest_slope("midpoint (ERK2)") - 2.0) < 0.2
    assert abs(finest_slope("gauss_2") - 4.0) < 0.2
    finest = {
        r["method"]: float(r["error"]) for r in fig72 if int(r["n_steps"]) == 256
    }  # same 2 stages: IRK4 is ~5 orders of magnitude more accurate (Fig. 7.2)
    assert finest["gauss_2"] < 1e-4 * finest["midpoint (ERK2)"]

    tol_rows = {float(r["rtol"]): r for r in read_csv(tmp_path / "newton_tolerance.csv")}
    assert all(int(r["status"]) == 0 for r in tol_rows.values())
    assert float(tol_rows[1e-10]["error"]) < 1e-12  # converged Newton: truncation error only
    assert float(tol_rows[1e-6]["error"]) > float(tol_rows[1e-10]["error"])


# ------------------------------------------------------ work precision, Fig. 7.3
def test_stiff_work_precision(tmp_path):
    from experiments import stiff_work_precision

    stiff_work_precision.main(["--quick", "--out", str(tmp_path)])
    assert (tmp_path / "work_precision.png").exists()
    stiff = by_key(read_csv(tmp_path / "stiff_vanderpol.csv"), "method")
    dopri, radau = stiff["dopri5"], stiff["radau_iia"]
    for row in (dopri, radau):
        assert int(row["status"]) == 0
        assert float(row["error"]) < 1e-4  # both accurate against scipy Radau (1e-12)
    # explicit steps are bounded by stability (|lambda| dt <~ 3.3, lambda ~ -(y1^2 - 1)/eps):
    # at eps = 1e-3 over [0, 0.5] that is hundreds of steps whatever the tolerance
    assert int(dopri["n_steps"]) > 200
    assert int(dopri["n_steps"]) > 5 * int(radau["n_steps"])
    assert int(dopri["n_f_evals"]) > 5 * int(radau["n_f_evals"])

    fixed = read_csv(tmp_path / "vanderpol_fixed_step.csv")
    err = {(r["method"], float(r["dt"])): float(r["error"]) for r in fixed}
    assert all(int(r["status"]) == 0 for r in fixed)
    for label, order in (("rk4 (ERK4)", 4), ("gauss_2 (IRK4)", 4), ("radau_3 (IRK5)", 5)):
        slope = math.log(err[(label, 0.1)] / err[(label, 0.02)]) / math.log(5.0)
        assert abs(slope - order) < 0.5, (label, slope)
    # at equal step the 2-stage IRK4 beats the 2-stage ERK2 by orders of magnitude
    assert err[("gauss_2 (IRK4)", 0.02)] < 1e-3 * err[("midpoint (ERK2)", 0.02)]


# ---------------------------------------------------------- stability regions, §7.3
def test_stability_regions_implicit(tmp_path, saved_figures):
    from experiments import stability_regions_implicit

    stability_regions_implicit.main(["--quick", "--out", str(tmp_path)])
    assert figure_defects(saved_figures["regions.png"]) == []
    assert (tmp_path / "regions.png").exists()
    rows = by_key(read_csv(tmp_path / "stability.csv"), "method")
    assert len(rows) == 8
    for name, row in rows.items():
        assert row["A_stable"] == "True", name
        assert float(row["max_R_imag"]) <= 1 + 1e-12
        assert float(row["max_R_left"]) <= 1 + 1e-12
    for s in (1, 2, 3):
        gauss, radau = rows[f"gauss_legendre_{s}"], rows[f"radau_iia_{s}"]
        # Gauss = diagonal Pade: |R(iy)| = 1 exactly, R(inf) = (-1)^s, not L-stable
        assert abs(float(gauss["max_R_imag"]) - 1) < 1e-12
        assert abs(float(gauss["R_inf"]) - (-1) ** s) < 1e-12
        assert gauss["L_stable"] == "False"
        # Radau IIA: R(inf) = 0 (L-stable), |R(-1e8)| = O(1e-8)
        assert abs(float(radau["R_inf"])) < 1e-12
        assert float(radau["abs_R_minus_1e8"]) < 1e-7
        assert radau["L_stable"] == "True"
    # implicit Euler, eq. 7.11: R(z) = 1/(1 - z); implicit midpoint R = (1 + z/2)/(1 - z/2)
    # (R = 1 + z b^T (I - z A)^-1 1 cancels at |z| = 1e8: relative accuracy ~1e-8 only)
    r_euler = float(rows["implicit_euler"]["abs_R_minus_1e8"])
    assert math.isclose(r_euler, 1 / (1 + 1e8), rel_tol=1e-6)
    r_mid = float(rows["implicit_midpoint"]["abs_R_minus_1e8"])
    assert math.isclose(r_mid, abs((1 - 5e7) / (1 + 5e7)), rel_tol=1e-12)
    assert rows["implicit_euler"]["L_stable"] == "True"
    assert float(rows["implicit_midpoint"]["R_inf"]) == -1.0


# ------------------------------------------------------------ sensitivities, §8
def test_sensitivities_agree(tmp_path, saved_figures):
    from experiments import sensitivities_compare

    sensitivities_compare.main(["--quick", "--out", str(tmp_path)])
    assert figure_defects(saved_figures["sensitivities.png"]) == []  # e.g. no bars on log axis
    assert (tmp_path / "sensitivities.png").exists()
    rows = {(r["method"], r["way"]): r for r in read_csv(tmp_path / "sensitivities.csv")}

    def worst(method: str, way: str) -> float:
        row = rows[(method, way)]
        return max(float(row["rel_diff_dx_dx0"]), float(row["rel_diff_dx_dp"]))

    assert worst("rk4", "reverse") < 1e-10  # eq. 8.18 vs autograd through odeint
    assert worst("gauss_legendre_2", "reverse") < 1e-7  # eq. 8.28 vs IFT backward
    # eq. 8.8 with the same method and grid: the same discrete derivatives (§8.2)
    assert worst("rk4", "variational") < 1e-10
    assert worst("gauss_legendre_2", "variational") < 1e-9
    for method in ("rk4", "gauss_legendre_2"):
        assert worst(method, "fd") < 1e-6  # central differences
        # ODE sensitivities differ from the discrete ones by the discretisation error only
        assert 1e-12 < worst(method, "variational_exact") < 1e-4
    values = {(r["method"], r["way"]): r for r in read_csv(tmp_path / "values.csv")}
    # dx(T)/dx0 is not trivial (not the identity) and the parameter sensitivity is nonzero
    fwd = values[("rk4", "forward")]
    assert abs(float(fwd["A00"]) - 1) > 1e-2 and abs(float(fwd["B00"])) > 1e-2
