"""The explicit-solver benchmark in --quick mode: it runs, and the errors it reports are those
of correct solvers (checked against the scipy DOP853 reference inside the benchmark)."""

import csv

from experiments.bench_explicit import main


def test_bench_explicit_quick_reports_small_errors(tmp_path):
    result = main(["--quick", "--out", str(tmp_path)])
    fixed, adaptive = result["fixed"], result["adaptive"]
    solvers = {row["solver"] for row in fixed}
    assert {"ours rk4 eager", "ours rk38 eager", "torchdiffeq rk4 (3/8 rule)"} <= solvers
    for row in fixed:
        # 100 RK4 steps of h = 0.01 on Van der Pol: global error O(h^4) ~ 1e-8
        assert row["max_error"] < 1e-7, row
    by_solver = {(row["batch"], row["solver"]): row for row in fixed}
    for batch in {row["batch"] for row in fixed}:
        ours = by_solver[(batch, "ours rk38 eager")]
        theirs = by_solver[(batch, "torchdiffeq rk4 (3/8 rule)")]
        # the same tableau on the same grid gives the same numbers up to rounding
        assert ours["final_gap_to_tdq_38"] < 1e-12
        assert abs(ours["max_error"] - theirs["max_error"]) < 1e-12
        classic = by_solver[(batch, "ours rk4 eager")]
        assert (
            abs(classic["max_error"] - by_solver[(batch, "torchdiffeq classic rk4")]["max_error"])
            < 1e-12
        )
    for row in adaptive:
        assert row["all_success"], row
        assert row["max_error"] < 1e-3, row  # rtol 1e-6 over a stiffish mu = 20 member
        assert row["sample_f_evals"] > 0
    ours = next(row for row in adaptive if row["solver"].startswith("ours"))
    tdq = next(row for row in adaptive if row["solver"].startswith("torchdiffeq"))
    assert ours["sample_f_evals"] < tdq["sample_f_evals"]  # per-sample steps do less work
    with open(tmp_path / "fixed_step_rk4.csv") as handle:
        assert len(list(csv.DictReader(handle))) == len(fixed)
    assert (tmp_path / "fixed_step_rk4.png").exists()
    assert "dopri5" in (tmp_path / "bench_explicit.md").read_text()
