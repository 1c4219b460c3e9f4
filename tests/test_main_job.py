"""The main job (experiments/identify_mass_spring_damper.py) in its quick mode: the numbers it
reports must show what the notes predict (§4.6): ARX least squares is biased under output
noise, OE by Gauss-Newton and the grey-box ODE fit are not, and their standard errors are
honest."""

import csv
import math

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
