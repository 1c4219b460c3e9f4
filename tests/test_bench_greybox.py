"""experiments/bench_greybox.py --quick: both crane fits reach the truth, the Jacobian's size
and memory grow linearly with the record."""

import pytest

from experiments.bench_greybox import main


@pytest.fixture(scope="module")
def quick(tmp_path_factory):
    out = tmp_path_factory.mktemp("bench_greybox")
    return out, *main(["--quick", "--out", str(out)])


def test_crane_fits_reach_the_truth_on_both_sides(quick):
    out, rows, _ = quick
    by = {row["method"]: row for row in rows}
    assert set(by) == {
        "ours, one batched fit",
        "ours, one data set",
        "scipy least_squares + solve_ivp, loop",
    }
    # 100 samples of 2 mrad / 2 mm noise: parameters within a few per cent of the truth
    for row in rows:
        assert row["relative_parameter_error"] < 0.05, row
        assert row["seconds_per_data_set"] > 0
        assert row["converged"] == 1.0, row  # ours: stationary; scipy: success
    ours, scipy = by["ours, one batched fit"], by["scipy least_squares + solve_ivp, loop"]
    # the same data sets: both estimators reach errors of the same size
    assert ours["error_on_scipy_sets"] < 3 * scipy["error_on_scipy_sets"] + 1e-3
    assert (out / "crane.md").exists() and (out / "jacobian.md").exists()


def test_jacobian_grows_linearly_with_the_record(quick):
    _, _, jac = quick
    short, long = jac
    assert short["columns"] == long["columns"] == 8  # 6 parameters and 2 initial states
    assert long["jacobian_mb"] == pytest.approx(2 * short["jacobian_mb"])
