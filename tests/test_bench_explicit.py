"""The explicit-solver benchmark in --quick mode: it runs, and the errors it reports are those
of correct solvers (checked against the scipy DOP853 reference inside the benchmark); the
matched-error comparison of dopri5 is checked against the sweep it is read from and against
runs at the tolerance it picked."""

import csv
import math

import pytest
import torch
from conftest import recorded_figures

from experiments._common import figure_defects
from experiments.bench_explicit import ADAPTIVE_SOLVERS, main, match_error

#: the figures the module's quick run saved, by file name
FIGURES: dict = {}


def _power_law_runs(rtols):
    """Synthetic sweep with err = 3 rtol^0.8, f-evals = 50 err^(-1/5), wall = 1e-4 f-evals."""
    rows = []
    for rtol in rtols:
        err = 3 * rtol**0.8
        f_evals = 50 * err ** (-0.2)
        rows.append(
            {
                "rtol": rtol,
                "max_error": err,
                "sample_f_evals": f_evals,
                "batched_f_calls": f_evals / 16,
                "wall_s": 1e-4 * f_evals,
                "all_success": True,
            }
        )
    return rows


def test_match_error_interpolates_log_log_exactly_on_a_power_law():
    rows = _power_law_runs([1e-7, 1e-4, 1e-6, 1e-5])  # any order
    target = 3 * 3e-6**0.8
    m = match_error(rows, target)
    assert (m["rtol_looser"], m["rtol_tighter"]) == (1e-5, 1e-6)
    assert m["rtol"] == pytest.approx(3e-6, rel=1e-12)
    assert m["sample_f_evals"] == pytest.approx(50 * target**-0.2, rel=1e-12)
    assert m["batched_f_calls"] == pytest.approx(50 * target**-0.2 / 16, rel=1e-12)
    assert m["wall_s"] == pytest.approx(5e-3 * target**-0.2, rel=1e-12)
    # a target equal to one run's error gives that run
    assert match_error(rows, 3 * 1e-6**0.8)["rtol"] == 1e-6


def test_match_error_takes_the_loosest_bracket_and_never_extrapolates():
    rows = _power_law_runs([1e-4, 1e-5, 1e-6, 1e-7])
    # not monotone (1.9e-3, 1e-5, 1e-4, 7.5e-6 from rtol 1e-4 to 1e-7): 4e-5 is crossed twice
    rows[1]["max_error"], rows[2]["max_error"] = 1e-5, 1e-4
    m = match_error(rows, 4e-5)
    assert (m["rtol_looser"], m["rtol_tighter"]) == (1e-4, 1e-5)  # the cheaper crossing
    # a failed run does not count: without the 1e-5 run, only the second crossing is left
    rows[1]["all_success"] = False
    m = match_error(rows, 4e-5)
    assert (m["rtol_looser"], m["rtol_tighter"]) == (1e-6, 1e-7)
    assert match_error(rows, 1e-9) is None  # below the tightest run's error
    assert match_error(rows, 1.0) is None  # above the loosest run's error


@pytest.fixture(scope="module")
def quick(tmp_path_factory):
    """One --quick run shared by the tests below: (result, output folder, torch state kept)."""
    out = tmp_path_factory.mktemp("bench_explicit")
    before = (torch.get_num_threads(), torch.get_default_dtype())
    with recorded_figures() as figures:
        result = main(["--quick", "--out", str(out)])
    FIGURES.update(figures)
    return result, out, before == (torch.get_num_threads(), torch.get_default_dtype())


def test_bench_explicit_quick_reports_small_errors(quick):
    result, tmp_path, state_kept = quick
    assert state_kept  # threads and default dtype restored
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
    assert len(adaptive) == 3
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


def test_bench_explicit_quick_matched_error(quick):
    result, tmp_path, _ = quick
    sweep, matched, equal = result["sweep"], result["matched"], result["adaptive"]
    target = next(r["max_error"] for r in equal if r["solver"] == ADAPTIVE_SOLVERS["ours"])
    rows = {
        name: [r for r in sweep if r["solver"] == label] for name, label in ADAPTIVE_SOLVERS.items()
    }
    match = {
        name: next(r for r in matched if r["solver"] == label)
        for name, label in ADAPTIVE_SOLVERS.items()
    }
    for name, runs in rows.items():
        assert all(r["all_success"] for r in runs), name
        # the equal-rtol row is the sweep's run at rtol 1e-6
        at_base = next(r for r in runs if r["rtol"] == 1e-6)
        eq = next(r for r in equal if r["solver"] == ADAPTIVE_SOLVERS[name])
        assert at_base["max_error"] == eq["max_error"]
        assert at_base["sample_f_evals"] == eq["sample_f_evals"]
        # the grid runs (a decade apart): tighter rtol, smaller error, more work
        grid = sorted((r for r in runs if r["kind"] == "grid"), key=lambda r: -r["rtol"])
        assert [r["rtol"] for r in grid] == [1e-5, 1e-6, 1e-7]
        for loose, tight in zip(grid[:-1], grid[1:], strict=True):
            assert tight["max_error"] < loose["max_error"] / 2, (name, loose, tight)
            assert tight["sample_f_evals"] > loose["sample_f_evals"], name
            assert tight["batched_f_calls"] > loose["batched_f_calls"], name

        m = match[name]
        assert m["bracketed"] and m["target_error"] == target, m
        looser = next(r for r in runs if r["rtol"] == m["rtol_looser"])
        tighter = next(r for r in runs if r["rtol"] == m["rtol_tighter"])
        assert looser["max_error"] >= target >= tighter["max_error"]
        assert m["rtol_tighter"] <= m["rtol"] <= m["rtol_looser"]
        for key in ("sample_f_evals", "batched_f_calls", "wall_s"):
            low, high = sorted((looser[key], tighter[key]))
            assert low <= m[key] <= high, (name, key)
        # a run at the interpolated rtol reaches about the target error and the interpolated
        # work (log-log interpolation of a smooth work-precision curve)
        assert target / 2 <= m["check_max_error"] <= 2 * target, m
        assert m["check_sample_f_evals"] == pytest.approx(m["sample_f_evals"], rel=0.1)

    # ours is placed at its own run at rtol 1e-6
    assert match["ours"]["rtol"] == 1e-6
    assert match["ours"]["check_max_error"] == target
    # per-sample steps beat one step size for the batch at the same error, in both counts
    assert match["ours"]["sample_f_evals"] < match["torchdiffeq"]["sample_f_evals"] / 2
    assert match["ours"]["batched_f_calls"] < match["torchdiffeq"]["batched_f_calls"]
    # the peers need a tighter rtol than 1e-6 to reach our error at 1e-6 here
    assert match["torchdiffeq"]["rtol"] < 1e-6 and match["torchode"]["rtol"] < 1e-6
    for m in match.values():
        for peer in ("torchdiffeq", "torchode"):
            ratio = m["sample_f_evals"] / match[peer]["sample_f_evals"]
            assert m[f"f_evals_vs_{peer}"] == pytest.approx(ratio, rel=1e-12)
            wall = m["wall_s"] / match[peer]["wall_s"]
            assert m[f"wall_vs_{peer}"] == pytest.approx(wall, rel=1e-12)
        assert math.isfinite(m["wall_s"]) and m["wall_s"] > 0
    with open(tmp_path / "adaptive_dopri5_matched.csv") as handle:
        assert len(list(csv.DictReader(handle))) == 3
    with open(tmp_path / "adaptive_dopri5_sweep.csv") as handle:
        assert len(list(csv.DictReader(handle))) == len(sweep)
    assert (tmp_path / "adaptive_dopri5_work_precision.png").stat().st_size > 10_000
    assert "matched error" in (tmp_path / "bench_explicit.md").read_text()


def test_quick_run_figures_are_readable(quick):
    """Every figure of the quick run has labelled axes, finite lines and a legend without
    duplicates (``experiments._common.figure_defects``)."""
    assert FIGURES, "the quick run saved no figure"
    for name, figure in FIGURES.items():
        assert figure_defects(figure) == [], name
