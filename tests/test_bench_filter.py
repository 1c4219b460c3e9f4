"""experiments/bench_filter.py --quick: the three IIR implementations agree numerically."""

import csv

from experiments._common import figure_defects
from experiments.bench_filter import main


def test_bench_filter_quick_agrees(tmp_path, saved_figures):
    main(["--quick", "--out", str(tmp_path), "--repeats", "1"])
    assert (tmp_path / "bench_filter.png").stat().st_size > 10_000
    assert figure_defects(saved_figures["bench_filter.png"]) == []
    assert (tmp_path / "bench_filter.md").read_text().startswith("| N | data_sets | method")
    with open(tmp_path / "bench_filter.csv") as handle:
        rows = list(csv.DictReader(handle))
    methods = {r["method"] for r in rows}
    assert {"ours", "scipy_autograd", "python_loop"} <= methods
    sizes = {int(r["N"]) for r in rows}
    assert max(sizes) == 2000 and len(sizes) == 3
    batched = [r for r in rows if r["data_sets"] == "50"]
    assert {r["method"] for r in batched} >= {"ours", "scipy_autograd_loop"}
    for row in rows:
        # same loss and gradient as the scipy reference, to rounding
        assert float(row["loss_rel_diff"]) < 1e-12, row
        assert float(row["grad_rel_diff"]) < 1e-10, row
        assert float(row["seconds"]) > 0 and float(row["speedup_of_ours"]) > 0
