"""The mechanics experiments run in --quick mode and show what they claim (numbers checked)."""

import csv

from experiments import (
    mechanics_constraint_drift,
    mechanics_energy_drift,
    mechanics_two_pendulum,
)
from experiments._common import figure_defects


def test_constraint_drift_baumgarte_vs_none(tmp_path, saved_figures):
    rows = mechanics_constraint_drift.main(["--quick", "--out", str(tmp_path)])
    assert saved_figures
    for name, fig in saved_figures.items():
        assert figure_defects(fig) == [], name  # labelled axes, legible ticks
    for plant in ("bowl", "crane"):
        runs = {r["alpha"]: r for r in rows if r["plant"] == plant}
        free = runs[0.0]
        # eq. (2.185): without stabilisation the drift keeps growing
        assert free["max_c_second_half"] > 2 * free["max_c_first_half"]
        stabilised = [r for a, r in runs.items() if a > 0]
        # eq. (2.186): with Baumgarte it stays bounded ...
        for r in stabilised:
            assert r["max_c_second_half"] < 1.5 * r["max_c_first_half"]
        # ... and the best gain keeps it at least 10x smaller
        assert min(r["max_c_second_half"] for r in stabilised) < free["max_c_second_half"] / 10
    with open(tmp_path / "constraint_drift.csv") as fh:
        assert len(list(csv.DictReader(fh))) == 6
    assert (tmp_path / "constraint_drift.png").stat().st_size > 0


def test_energy_drift_rk4_vs_gauss_legendre(tmp_path, saved_figures):
    rows = mechanics_energy_drift.main(["--quick", "--out", str(tmp_path)])
    assert saved_figures
    for name, fig in saved_figures.items():
        assert figure_defects(fig) == [], name  # labelled axes, legible ticks
    by = {(r["plant"], r["method"]): r for r in rows}
    rk4, gl = by[("chain", "rk4")], by[("chain", "gauss_legendre")]
    # Gauss-Legendre conserves the quadratic energy of the linear chain to round-off
    assert gl["max_err_second_half"] < 1e-10 * gl["energy"]
    # RK4 drifts, and the drift grows with time
    assert rk4["max_err_second_half"] > 1e-3 * rk4["energy"]
    assert rk4["max_err_second_half"] > rk4["max_err_first_half"]
    assert (tmp_path / "energy_drift.png").stat().st_size > 0


def test_two_pendulum_polar_and_cartesian_models_agree(tmp_path):
    """Eq. (2.98)-(2.109) vs (2.150)-(2.158): the same motion; both RK4 errors shrink fast
    with dt (order 4 ideally: ratio 16 per halving, > 4 required here), and the Cartesian
    model keeps its constraints small with Baumgarte stabilisation."""
    rows = mechanics_two_pendulum.main(["--quick", "--out", str(tmp_path)])
    for model in ("polar", "cartesian"):
        sel = sorted((r for r in rows if r["model"] == model), key=lambda r: -r["dt"])
        assert sel[0]["position_error"] > 4 * sel[-1]["position_error"]
        assert sel[-1]["position_error"] < 1e-4
    cart = [r for r in rows if r["model"] == "cartesian"]
    assert max(r["max_constraint"] for r in cart) < 1e-3
