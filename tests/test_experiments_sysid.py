"""Run each sysid experiment in --quick mode and check the numbers it reports."""

import csv

import pytest

from experiments import (
    sysid_bode_residuals,
    sysid_consistency,
    sysid_fat_tails,
    sysid_fir_covariance,
    sysid_fir_inputs,
)
from experiments._common import figure_defects


def by(rows, **keys):
    return next(r for r in rows if all(r[k] == v for k, v in keys.items()))


def test_fir_inputs_fig_4_1(tmp_path, saved_figures):
    rows = sysid_fir_inputs.main(["--quick", "--out", str(tmp_path)])
    assert saved_figures
    for name, fig in saved_figures.items():
        assert figure_defects(fig) == [], name  # labelled axes, legible ticks
    white, prbs = by(rows, input="white"), by(rows, input="prbs")
    step, sine = by(rows, input="step"), by(rows, input="sinusoid")
    # sinusoid and step excite few directions: U'U near singular, flagged, poor estimates
    for poor in (step, sine):
        assert poor["cond_UtU"] > 1e3 * max(white["cond_UtU"], prbs["cond_UtU"])
        assert poor["poor_excitation_warning"]
        assert poor["param_error_rel"] > 5 * max(white["param_error_rel"], prbs["param_error_rel"])
    assert not white["poor_excitation_warning"] and not prbs["poor_excitation_warning"]
    # ... while the sinusoid's output fit on its own data stays excellent (notes' remark)
    assert sine["fit_estimation_pct"] > 95
    assert sine["fit_validation_pct"] < white["fit_validation_pct"]
    assert (tmp_path / "fir_inputs.png").exists() and (tmp_path / "fir_inputs.csv").exists()


def test_fir_covariance_eq_4_101(tmp_path, saved_figures):
    rows = sysid_fir_covariance.main(["--quick", "--out", str(tmp_path)])
    assert saved_figures
    for name, fig in saved_figures.items():
        assert figure_defects(fig) == [], name  # labelled axes, legible ticks
    for row in rows:
        assert row["trials"] >= 2000
        assert row["rel_frobenius_emp_vs_4.101"] < 0.15  # sampling error ~ sqrt(21/2000)
        assert row["rel_frobenius_reported_vs_4.101"] < 0.02
        assert row["coverage_95_per_tap"] == pytest.approx(0.95, abs=0.01)
        assert row["sigma2_hat_mean"] == pytest.approx(0.25, rel=0.02)
    assert (tmp_path / "fir_covariance.png").exists()


def test_consistency_arx_biased_oe_consistent_and_resumes(tmp_path, saved_figures):
    summary = sysid_consistency.main(["--quick", "--out", str(tmp_path)])
    fig = saved_figures["consistency.png"]
    assert figure_defects(fig) == []
    for ax in fig.axes:  # N labelled at the data lengths only, no minor-tick labels
        assert [t.get_text() for t in ax.get_xticklabels()] == ["200", "800"]
        assert [t.get_text() for t in ax.get_xticklabels(minor=True)] == []
    ls_out = by(summary, estimator="arx_ls", noise="output")
    ls_eq = by(summary, estimator="arx_ls", noise="equation")
    oe = by(summary, estimator="oe_gn", noise="output")
    assert ls_out["bias_over_se_at_max_N"] > 20  # biased ...
    assert abs(ls_out["bias_f1_at_max_N"]) > 0.8 * abs(ls_out["bias_f1_at_min_N"])  # ... for all N
    assert ls_eq["bias_over_se_at_max_N"] < 4
    assert oe["bias_over_se_at_max_N"] < 4
    assert -0.8 < oe["std_slope"] < -0.25  # std ~ 1/sqrt(N)
    with open(tmp_path / "consistency.csv") as handle:
        n_rows = len(list(csv.DictReader(handle)))
    sysid_consistency.main(["--quick", "--out", str(tmp_path)])  # resumes: nothing recomputed
    with open(tmp_path / "consistency.csv") as handle:
        assert len(list(csv.DictReader(handle))) == n_rows == 8
    assert (tmp_path / "consistency.png").exists()


def test_fat_tails_fair_beats_least_squares(tmp_path, saved_figures):
    rows = sysid_fat_tails.main(["--quick", "--out", str(tmp_path)])
    assert figure_defects(saved_figures["fat_tails.png"]) == []  # points, not bars, on log axis
    assert by(rows, noise="student_t(df=2)")["fair_over_ls"] < 0.3
    assert by(rows, noise="contaminated")["fair_over_ls"] < 0.5
    assert by(rows, noise="gaussian")["fair_over_ls"] < 1.3  # little loss when LS is optimal
    assert (tmp_path / "fat_tails.png").exists()


def test_bode_and_residual_tests(tmp_path, saved_figures):
    rows = sysid_bode_residuals.main(["--quick", "--out", str(tmp_path)])
    assert figure_defects(saved_figures["bode.png"]) == []
    assert figure_defects(saved_figures["residuals.png"]) == []
    arx = by(rows, model="ARX(2,2) LS", data="OE data")
    oe = by(rows, model="OE(2,2) GN", data="OE data")
    oe_bj = by(rows, model="OE(2,2) GN", data="BJ data")
    bj = by(rows, model="BJ(2,1,1,2) GN", data="BJ data")
    assert oe["white"] and oe["independent"] and oe["max_rel_error_G"] < 0.2
    assert bj["white"] and bj["independent"] and bj["max_rel_error_G"] < 0.2
    assert not arx["white"] and arx["max_rel_error_G"] > 2 * oe["max_rel_error_G"]
    # OE on Box-Jenkins data: G still consistent, but the residuals are coloured
    assert not oe_bj["white"] and oe_bj["max_rel_error_G"] < 0.2
    assert all(r["stable"] for r in rows)
    assert (tmp_path / "bode.png").exists() and (tmp_path / "residuals.png").exists()


def test_consistency_recovers_from_a_corrupt_partial_file(tmp_path, capsys):
    """A half-written last line used to crash every rerun (TypeError) and a partly written N
    counted as done. Truncate the file mid-line, and separately drop rows of one N: the
    rerun drops what is incomplete, says so, recomputes it and gives the clean run's numbers.
    """
    clean_dir, dirty_dir = tmp_path / "clean", tmp_path / "dirty"
    sysid_consistency.main(["--quick", "--out", str(clean_dir)])
    text = (clean_dir / "consistency.csv").read_text()
    clean = (clean_dir / "consistency_table.csv").read_text()
    lines = text.splitlines(keepends=True)
    assert len(lines) == 9 and not list(dirty_dir.glob("*"))
    dirty_dir.mkdir()
    for corrupt in (
        text[: len(text) - len(lines[-1]) // 2],  # last row cut mid-line
        "".join(lines[:2] + lines[3:6] + lines[7:]),  # one row of each N missing
        "".join(lines[:-1]) + lines[-1][:-1] + ",1.0,2.0\n",  # a row with extra fields
    ):
        (dirty_dir / "consistency.csv").write_text(corrupt)
        capsys.readouterr()
        sysid_consistency.main(["--quick", "--out", str(dirty_dir)])
        assert "recomputing" in capsys.readouterr().out
        assert (dirty_dir / "consistency_table.csv").read_text() == clean
        assert (dirty_dir / "consistency.csv").read_text().count("\n") == 9
    assert not list(dirty_dir.glob(".*.tmp"))  # no temporary file left behind
