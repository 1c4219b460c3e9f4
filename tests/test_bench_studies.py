"""experiments/bench_studies.py --quick: the study's batched least-squares estimates (and its
batched fit alone) are the per-data-set numpy lstsq and statsmodels OLS estimates on the same
data, the hand-written end-to-end loops estimate the same parameters, the checkpoint and Dask
tables cover every data set."""

import pytest

from experiments.bench_studies import main


@pytest.fixture(scope="module")
def quick(tmp_path_factory):
    out = tmp_path_factory.mktemp("bench_studies")
    return out, *main(["--quick", "--out", str(out), "--repeats", "1"])


def test_study_estimates_are_the_loops_estimates(quick):
    out, rows, _, _ = quick
    by = {row["method"]: row for row in rows}
    end_to_end = [
        "Python loop end to end: numpy draws, scipy lfilter, numpy lstsq",
        "Python loop end to end: numpy draws, scipy lfilter, statsmodels OLS",
    ]
    assert set(by) == {
        "Study, batched fit(method='lls'), checkpointed",
        "Python loop, numpy lstsq",
        "Python loop, statsmodels OLS",
        "batched fit(method='lls') alone, one chunk of ready data",
        *end_to_end,
    }
    for row in rows:
        if row["method"] not in end_to_end:  # the same data sets
            assert row["max_abs_estimate_difference"] < 1e-10, row
        assert row["seconds_per_data_set"] > 0
    # the hand-written loops simulate the same ARX model (from the same seed): unbiased
    # estimates of the same parameters (mean of 50 data sets of 500 samples: SE about 0.01)
    for method in end_to_end:
        assert by[method]["max_abs_mean_estimate_error"] < 0.05
    assert by["batched fit(method='lls') alone, one chunk of ready data"]["data_sets"] == 2000
    assert (
        by["Study, batched fit(method='lls'), checkpointed"]["max_abs_mean_estimate_error"] < 0.01
    )
    assert by["Python loop, numpy lstsq"]["data_sets"] == 50
    assert (out / "throughput.md").exists() and (out / "README.md").exists()


def test_checkpoint_and_dask_tables(quick):
    _, _, checkpoint, dask = quick
    (row,) = checkpoint
    assert row["data_sets"] == 2000 and row["seconds_in_memory"] > 0
    assert [r["workers"] for r in dask] == [1, 2]
    assert all(r["data_sets"] == 64 and r["chunks"] == 16 for r in dask)
    assert dask[0]["speedup_vs_1_worker"] == 1.0
