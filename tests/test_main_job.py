"""The main job (experiments/identify_mass_spring_damper.py) in its quick mode: the numbers it
reports must show what the notes predict (§4.6): ARX least squares is biased under output
noise, OE by Gauss-Newton and the grey-box ODE fit are not, and their standard errors are
honest."""

import csv
import math

import pytest

from experiments import identify_mass_spring_damper as job


def _rows(path):
    with open(path) as fh:
        return list(csv.DictReader(fh))


def test_main_job_quick(tmp_path):
    job.main(["--quick", "--out", str(tmp_path)])
    rows = _rows(tmp_path / "estimates.csv")
    summary = _rows(tmp_path / "summary.csv")[0]
    trials = int(summary["trials"])
    assert float(summary["oe_converged"]) == 1.0
    assert float(summary["grey_converged"]) == 1.0
    assert float(summary["validation_fit_percent"]) > 80.0
    by = {(r["estimator"], r["parameter"]): r for r in rows}
    for name in ("b1", "b2", "f1", "f2"):
        oe = by[("OE Gauss-Newton", name)]
        # unbiased: the mean is within 4 standard errors of the Monte-Carlo mean
        assert abs(float(oe["bias"])) < 4 * float(oe["std"]) / math.sqrt(trials)
        # the reported standard error matches the empirical spread within a factor 1.6
        assert 1 / 1.6 < float(oe["mean_reported_se"]) / float(oe["std"]) < 1.6
    for name in ("f1", "f2"):
        arx = by[("ARX least squares", name)]
        assert abs(float(arx["bias"])) > 10 * float(arx["std"]) / math.sqrt(trials)
    for name, true in job.TRUE_PHYSICAL.items():
        grey = by[("grey-box (m, xi, K)", name)]
        assert float(grey["true"]) == true
        assert abs(float(grey["mean"]) - true) < 0.05 * true
        assert float(grey["coverage_3se"]) >= 2 / 3


def test_estimates_figure_shows_bias_and_normalised_errors(tmp_path, saved_figures):
    """The story figure: one panel per parameter (mean +- SE of each estimator against the
    truth) and one histogram of (estimate - truth) / SE per unbiased estimator against the
    N(0, 1) density; built from an estimates table like the one ``main`` writes."""
    import numpy as np

    from experiments._common import figure_defects

    rows = [
        {"estimator": est, "parameter": p, "true": 0.5, "mean": mean, "mean_reported_se": 0.01}
        for est, p, mean in [
            ("ARX least squares", "f1", 0.8),
            ("OE Gauss-Newton", "f1", 0.501),
            ("ARX least squares", "f2", 0.2),
            ("OE Gauss-Newton", "f2", 0.499),
            ("grey-box (m, xi, K)", "m", 0.5),
            ("grey-box (m, xi, K)", "K", 0.51),
        ]
    ]
    z = np.random.default_rng(0).standard_normal(200)
    job._estimates_figure(rows, {"OE Gauss-Newton": z, "grey-box (m, xi, K)": z[:30]}, tmp_path)
    assert (tmp_path / "estimates.png").exists()
    fig = saved_figures["estimates.png"]
    assert figure_defects(fig) == []
    panels, histograms = fig.axes[:4], fig.axes[4:]
    assert [ax.get_title() for ax in panels] == ["f1", "f2", "m", "K"]
    assert [t.get_text() for t in panels[0].get_xticklabels()] == ["ARX", "OE"]
    assert panels[0].lines[-1].get_ydata()[0] == 0.5  # the truth line
    assert len(histograms) == 2
    for ax in histograms:
        legend = [t.get_text() for t in ax.get_legend().get_texts()]
        assert "N(0, 1) density" in legend
        assert ax.get_xlabel() == "(estimate - truth) / reported SE"
        density = ax.lines[0].get_ydata()
        assert max(density) == pytest.approx(1 / math.sqrt(2 * math.pi), rel=1e-3)
