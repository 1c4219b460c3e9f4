"""The grey-box training scripts in their quick modes: the numbers they report must show
what theory predicts. The crane's batched Monte-Carlo estimates are unbiased and their
reported standard errors honest (coverage of the 95 % intervals, empirical std against the
mean reported SE); the constrained crane's parameters are recovered within 3 SE through its
index-1 KKT DAE and its index-3 form is refused; multiple shooting reaches the truth from
poor starts where single shooting stops in local minima."""

import math

from experiments import greybox_constrained, greybox_crane, greybox_shooting


def test_greybox_crane_quick_coverage_and_bias(tmp_path):
    summary, rows, corr = greybox_crane.main(["--quick", "--out", str(tmp_path)])
    trials = summary["trials"]
    assert summary["converged"] == 1.0
    # every parameter identifiable: no pair collinear
    assert summary["max_abs_correlation"] < 0.99
    assert [r["parameter"] for r in rows] == ["M", "m", "L", "d"]
    for r in rows:
        # unbiased: |bias| within 4 Monte-Carlo standard errors of the mean, and small
        # against one reported SE
        assert abs(r["bias"]) < 4 * r["empirical_std"] / math.sqrt(trials), r
        assert abs(r["bias_over_se"]) < 0.35, r
        # honest SEs: the empirical std matches the mean reported SE (sampling error of a
        # std over 128 trials about 6 %), 95 % coverage within 4 binomial sigmas
        assert 0.7 < r["se_over_std"] < 1.3, r
        assert 0.86 <= r["coverage_95"] <= 1.0, r
    assert (tmp_path / "normalised_errors.png").stat().st_size > 0


def test_greybox_constrained_quick_within_3se_and_index3_refused(tmp_path):
    summary, rows = greybox_constrained.main(
        ["--quick", "--trials", "2", "--samples", "40", "--out", str(tmp_path)]
    )
    assert summary["converged"] == 1.0
    assert summary["index3_form"].startswith("HighIndexError")
    assert [r["parameter"] for r in rows] == ["M", "m", "L"]
    for r in rows:
        assert r["within_3se"] == 1.0, r
        assert r["mean_se"] < 0.05 * r["true"], r


def test_greybox_shooting_quick_multiple_beats_single(tmp_path):
    summary, rows = greybox_shooting.main(["--quick", "--out", str(tmp_path)])
    assert summary["starts"] == 16
    assert summary["success_multiple_shooting"] >= 0.9
    assert summary["success_simulation"] <= summary["success_multiple_shooting"] - 0.25
    assert sum(r["starts"] for r in rows) == 16
    assert (tmp_path / "success_vs_distance.png").stat().st_size > 0
