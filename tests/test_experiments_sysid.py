"""Run each sysid experiment in --quick mode and check the numbers it reports."""

import pytest

from experiments import (
    sysid_bode_residuals,
    sysid_consistency,
    sysid_fat_tails,
    sysid_fir_covariance,
    sysid_fir_inputs,
)
from experiments._common import figure_defects
from sysid.errors import RKIdentWarning, StudyDeclarationError


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
    # a maximum-length sequence and a multisine excite every direction evenly
    for rich in (by(rows, input="mls"), by(rows, input="multisine")):
        assert not rich["poor_excitation_warning"] and rich["cond_UtU"] < 10
        assert rich["param_error_rel"] < 2 * max(white["param_error_rel"], prbs["param_error_rel"])
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


def test_given_trials_and_lengths_win_over_the_quick_defaults(tmp_path, saved_figures):
    """``--quick`` sets defaults only: a given ``--trials`` / ``--n`` is the one run."""
    rows = sysid_fir_covariance.main(
        ["--quick", "--trials", "300", "--n", "120", "--out", str(tmp_path)]
    )
    assert [(r["N"], r["trials"]) for r in rows] == [(120, 300), (120, 300)]


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
    chunks = sorted(tmp_path.glob("study_*/chunks/*.parquet"))
    assert len(chunks) == 2 * 2 * 2  # 2 noise kinds x 2 N x 2 chunks of <= 50 trials
    stamps = [path.stat().st_mtime_ns for path in chunks]
    table = (tmp_path / "consistency_table.csv").read_text()
    assert table.count("\n") == 1 + 8  # header, 4 cases x 2 N
    sysid_consistency.main(["--quick", "--out", str(tmp_path)])  # resumes: nothing recomputed
    assert [path.stat().st_mtime_ns for path in chunks] == stamps
    assert (tmp_path / "consistency_table.csv").read_text() == table
    assert (tmp_path / "report_output" / "report.md").exists()
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


def test_consistency_recovers_from_a_corrupt_chunk_and_refuses_other_options(tmp_path):
    """A damaged checkpoint (a chunk file cut short, another deleted) is recomputed with a
    warning and gives the clean run's numbers; other options in the same folder are refused
    instead of mixing results."""
    clean_dir, dirty_dir = tmp_path / "clean", tmp_path / "dirty"
    sysid_consistency.main(["--quick", "--out", str(clean_dir)])
    clean = (clean_dir / "consistency_table.csv").read_text()
    sysid_consistency.main(["--quick", "--out", str(dirty_dir)])
    first, second = sorted((dirty_dir / "study_output" / "chunks").glob("*.parquet"))[:2]
    first.write_bytes(first.read_bytes()[:200])
    second.unlink()
    with pytest.warns(RKIdentWarning, match="recomputing"):
        sysid_consistency.main(["--quick", "--out", str(dirty_dir)])
    assert (dirty_dir / "consistency_table.csv").read_text() == clean
    assert not list(dirty_dir.glob("study_*/chunks/.*.tmp"))  # no temporary file left behind
    with pytest.raises(StudyDeclarationError, match="sigma"):
        sysid_consistency.main(["--quick", "--sigma", "0.3", "--out", str(dirty_dir)])
