"""The grey-box consistency study (experiments/greybox_consistency.py) in its quick mode: the
grey-box fit of the pendulum's (a, c, b) is unbiased, its standard deviation falls with N
close to N^(-1/2), and the reported standard errors give 95 % intervals that cover the truth;
the study is a declaration kind of ``python -m experiments.study``."""

import csv
import math

import torch

from experiments import greybox_consistency as gc
from experiments import study as cli


def _rows(path):
    with open(path) as fh:
        return list(csv.DictReader(fh))


def test_quick_study_is_consistent_with_honest_standard_errors(tmp_path):
    study, rows = gc.main(["--quick", "--out", str(tmp_path)])
    trials = gc.QUICK["trials"]
    assert len(study.results) == len(gc.QUICK["N"]) * trials * 3
    for row in rows:
        assert row["converged"] == 1.0
        # std against N: -1/2 asymptotically; the quick grid (N = 40, 160) sits a little
        # steeper (the response from rest carries less information at first)
        assert -0.85 < row["std_slope"] < -0.45, row
        # coverage of the 95 % intervals: binomial spread sqrt(0.95 0.05 / 48) = 0.031
        assert 0.85 <= row["min_coverage_95"] and row["max_coverage_95"] <= 1.0, row
        # unbiased: every mean within 3.5 Monte-Carlo standard errors of the truth
        assert row["max_bias_over_bias_se"] < 3.5, row
        assert 0.7 < row["se_over_std_mean"] < 1.4, row
    summary = _rows(tmp_path / "report" / "summary.csv")
    assert {float(r["truth"]) for r in summary} == set(gc.TRUTH.values())
    for name in ("bias_std_vs_N.png", "coverage_vs_N.png", "normalized_qq.png"):
        assert (tmp_path / "report" / name).exists()


def test_cli_declares_the_greybox_study():
    """The CLI's kind builds the study with the file's grid; its data are the model's own
    simulation plus white noise of the declared std."""
    study = cli.declare({"kind": "greybox_consistency", "grid": {"N": [200], "sigma": [0.1]}}, 8)
    assert study.grid == {"N": [200], "sigma": [0.1]}
    assert (study.trials, study.seed) == (8, gc.SEED)
    data = study.simulate({"N": 200, "sigma": 0.1}, 2, torch.Generator().manual_seed(0))
    noise = data.y - gc.model(gc.TRUTH).simulate(data)
    # 400 samples: the sample std is within 12 % (3.4 of its standard errors) of 0.1
    assert abs(float(noise.std()) / 0.1 - 1.0) < 0.12
    assert abs(float(noise.mean())) < 4 * 0.1 / math.sqrt(400)
