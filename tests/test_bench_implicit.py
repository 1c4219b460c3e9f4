"""The implicit benchmark runs in --quick mode and reports errors that are checked here."""

import csv

from experiments.bench_implicit import main


def test_bench_implicit_quick_reports_consistent_errors(tmp_path):
    rows = main(["--quick", "--out", str(tmp_path)])
    assert (tmp_path / "bench_implicit.png").exists()
    with open(tmp_path / "bench_implicit.csv") as fh:
        table = list(csv.DictReader(fh))
    assert len(table) == len(rows) == 6
    for row in rows:
        assert row["ours_s"] > 0 and row["peer_s"] > 0
        if row["rtol"] is not None:
            # adaptive Radau IIA meets the tolerance about as well as scipy's Radau
            assert row["ours_error"] < 20 * row["rtol"]
            assert row["ours_error"] < 10 * row["peer_error"] + row["rtol"]
        else:
            # at dt = 0.05, order 4 (Gauss s=2) and 5 (Radau s=3) beat Adams-Moulton
            assert row["ours_error"] < row["peer_error"]
            assert row["ours_error"] < 1e-6
