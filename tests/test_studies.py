"""sysid.studies.Study: declared, batched, resumable Monte-Carlo studies.

Independent truths: FIR least squares with a fixed input has the exact covariance
sigma^2 (Phi'Phi)^-1 (the course notes (Modelling and Simulation) eq. 4.92-4.93, 4.101),
computed here from the regressor matrix; its standard deviation falls like N^(-1/2); the
95 % intervals of a Gaussian model cover the truth 95 % of the time (binomial spread). The
seeding contract (a trial's data depend only on the seed, grid point and trial index) is
checked by comparing per-trial estimates across chunk sizes, interruptions and Dask.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from sysid import ARX, FIR, IOData, fit
from sysid.errors import InputValidationError, RKIdentWarning, StudyDeclarationError
from sysid.montecarlo import input_signal, simulate_data
from sysid.studies import Study

SIGMA = 0.5
FIR_TRUTH = {"b1": 1.0, "b2": 0.5, "b3": 0.2}
FIR_THETA = torch.tensor(list(FIR_TRUTH.values()), dtype=torch.float64)
ARX_TRUTH = {"a1": -0.7, "a2": 0.1, "b1": 1.0, "b2": 0.4}


def fixed_input(N: int) -> torch.Tensor:
    """One input record per N, the same in every trial (deterministic regressors)."""
    return input_signal("white", N, generator=torch.Generator().manual_seed(N))


def simulate_fir(point, n, generator):
    """n data sets of the FIR system on the fixed input; only the noise varies."""
    u = fixed_input(point["N"]).expand(n, -1, -1)
    return simulate_data(FIR(3, 1), u, theta=FIR_THETA, noise_std=SIGMA, generator=generator)


def simulate_white(point, n, generator):
    """n data sets of the FIR system, input and noise both drawn per trial."""
    u = input_signal("white", point["N"], (n,), generator=generator)
    return simulate_data(FIR(3, 1), u, theta=FIR_THETA, noise_std=SIGMA, generator=generator)


def fir_theory(point, estimator):
    """sigma^2 (Phi'Phi)^-1 with Phi the regressor that fit(FIR(3, 1)) uses (eq. 4.101)."""
    u = fixed_input(point["N"])
    phi, _ = FIR(3, 1).regression(IOData(u, torch.zeros_like(u)))
    return SIGMA**2 * torch.linalg.inv(phi.T @ phi)


def fir_ls(data):
    return fit(FIR(3, 1), data)


def small_study(chunk=5, trials=15, block=1, estimators=None, **options):
    return Study(
        simulate_white,
        estimators or {"fir_ls": fir_ls},
        grid={"N": [40, 80]},
        trials=trials,
        seed=3,
        chunk=chunk,
        block=block,
        truth=FIR_TRUTH,
        **options,
    )


def table(study):
    """The results without the timing column, in a canonical row order."""
    keys = ["N", "estimator", "trial", "parameter"]
    frame = study.results.drop(columns="time").sort_values(keys).reset_index(drop=True)
    frame["covariance_row"] = frame["covariance_row"].map(tuple)
    return frame


@pytest.fixture(scope="module")
def fir_study(tmp_path_factory):
    study = Study(
        simulate_fir,
        {"fir_ls": fir_ls},
        grid={"N": [100, 400, 1600]},
        trials=2000,
        seed=11,
        chunk=1000,
        block=500,
        truth=FIR_TRUTH,
        theory=fir_theory,
    )
    return study.run(tmp_path_factory.mktemp("fir"), progress=False)


def test_fir_covariance_matches_eq_4_101_within_the_sampling_error(fir_study):
    """||C_emp - Sigma||_F / ||Sigma||_F of a sample covariance of T Gaussian vectors has
    mean square (tr(Sigma^2) + tr(Sigma)^2) / (T - 1) / ||Sigma||_F^2; allow 4 times its root."""
    cov = fir_study.covariance_summary()
    assert len(cov) == 3
    for i, point in enumerate(fir_study.points):
        row = cov.iloc[i]
        sigma = fir_theory(point, "fir_ls")
        T = fir_study.trials
        scale = math.sqrt(
            (torch.trace(sigma @ sigma) + torch.trace(sigma) ** 2) / (T - 1)
        ) / torch.linalg.matrix_norm(sigma)
        assert row["trials"] == T
        assert row["rel_frobenius_theory"] < 4 * float(scale)
        assert row["rel_frobenius_reported"] < 4 * float(scale)
        # reported covariance: sigma2_hat (Phi'Phi)^-1, E sigma2_hat = sigma^2 exactly
        assert row["rel_frobenius_reported_vs_theory"] < 0.02
        matrices = fir_study.covariances(i, "fir_ls")
        torch.testing.assert_close(matrices["theory"], sigma)


def test_fir_summary_bias_coverage_and_standard_errors(fir_study):
    summary = fir_study.summary()
    assert len(summary) == 9 and (summary["trials"] == 2000).all()
    assert list(summary.columns[:3]) == ["N", "estimator", "parameter"]
    # unbiased: |bias| within 4 standard errors of the mean
    assert (summary["bias"].abs() < 4 * summary["bias_se"]).all()
    # 95 % intervals (normal quantile, estimated sigma): binomial spread sqrt(.05 .95 / T)
    spread = math.sqrt(0.05 * 0.95 / 2000)
    assert (summary["coverage"] - 0.95).abs().max() < 4 * spread + 0.005
    assert (summary["se_over_std"] - 1).abs().max() < 0.1
    assert np.allclose(summary["rmse"] ** 2, summary["bias"] ** 2 + summary["std"] ** 2, rtol=1e-2)
    assert summary["converged"].eq(1).all()


def test_fir_consistency_slope_of_std_is_minus_one_half(fir_study):
    slopes = fir_study.consistency("N")
    assert len(slopes) == 3 and (slopes["points"] == 3).all()
    assert (slopes["std_slope"] + 0.5).abs().max() < 0.1


def test_arx_reported_covariance_and_coverage(tmp_path):
    """ARX least squares on equation-error data: the reported covariance sigma2 (Phi'Phi)^-1
    (eq. 4.92-4.93) matches the spread of the estimates; intervals cover 95 %."""
    theta = torch.tensor(list(ARX_TRUTH.values()), dtype=torch.float64)

    def simulate(point, n, generator):
        u = input_signal("white", point["N"], (n,), generator=generator)
        return simulate_data(
            ARX(2, 2, 1), u, theta=theta, noise_std=SIGMA, noise="model", generator=generator
        )

    study = Study(
        simulate,
        {"arx_ls": lambda d: fit(ARX(2, 2, 1), d)},
        grid={"N": [200, 800]},
        trials=1500,
        seed=5,
        chunk=1500,
        block=1500,
        truth=ARX_TRUTH,
    ).run(tmp_path, progress=False)
    summary = study.summary()
    assert (summary["bias"].abs() < 4 * summary["bias_se"]).all()
    assert (summary["coverage"] - 0.95).abs().max() < 4 * math.sqrt(0.05 * 0.95 / 1500) + 0.01
    assert (study.covariance_summary()["rel_frobenius_reported"] < 0.15).all()
    assert (study.consistency()["std_slope"] + 0.5).abs().max() < 0.1


def test_results_table_is_tidy(tmp_path):
    study = small_study().run(tmp_path, progress=False)
    rows = study.results
    assert list(rows.columns) == [
        "N",
        "estimator",
        "trial",
        "parameter",
        "estimate",
        "se",
        "converged",
        "loss",
        "time",
        "covariance_row",
    ]
    assert len(rows) == 2 * 15 * 3
    # one batched fit per chunk gives the same numbers as a fit of each trial alone
    one = rows[(rows["N"] == 80) & (rows["trial"] == 7)]
    data = study._simulate_chunk(1, 1)[2]  # chunk 1 = trials 5..9
    alone = fit(FIR(3, 1), data)
    torch.testing.assert_close(torch.tensor(one["estimate"].to_numpy()), alone.theta)
    torch.testing.assert_close(torch.tensor(one["se"].to_numpy()), alone.standard_errors)
    assert one["loss"].iloc[0] == pytest.approx(float(alone.loss_history[-1]))


def test_same_trial_same_data_for_any_block_aligned_chunk(tmp_path):
    a = small_study(chunk=3).run(tmp_path / "a", progress=False)
    b = small_study(chunk=5).run(tmp_path / "b", progress=False)
    c = small_study(chunk=15).run(tmp_path / "c", progress=False)
    assert table(a).equals(table(b)) and table(a).equals(table(c))
    d = small_study(chunk=10, block=5).run(tmp_path / "d", progress=False)
    e = small_study(chunk=5, block=5).run(tmp_path / "e", progress=False)
    assert table(d).equals(table(e))


@settings(
    max_examples=8, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(chunk=st.integers(1, 12))
def test_chunk_size_never_changes_a_trial(tmp_path_factory, chunk):
    reference = small_study(chunk=12, trials=12)
    reference.run(tmp_path_factory.mktemp("ref"), progress=False)
    study = small_study(chunk=chunk, trials=12).run(tmp_path_factory.mktemp("s"), progress=False)
    assert table(study).equals(table(reference))


def test_resume_after_an_interruption_gives_the_uninterrupted_table(tmp_path):
    calls = {"n": 0}

    def failing(data):
        calls["n"] += 1
        if calls["n"] == 3:
            raise RuntimeError("interrupted")
        return fir_ls(data)

    with pytest.raises(RuntimeError, match="interrupted"):
        small_study(estimators={"fir_ls": failing}).run(tmp_path / "run", progress=False)
    assert len(list((tmp_path / "run" / "chunks").glob("*.parquet"))) == 2
    assert not list((tmp_path / "run" / "chunks").glob(".*.tmp"))
    calls["n"] = 10
    resumed = small_study(estimators={"fir_ls": failing}).run(tmp_path / "run", progress=False)
    assert calls["n"] == 10 + 6 - 2  # the two finished chunks are not recomputed
    clean = small_study().run(tmp_path / "clean", progress=False)
    assert table(resumed).equals(table(clean))


def test_an_unreadable_chunk_file_is_recomputed(tmp_path):
    clean = small_study().run(tmp_path, progress=False)
    expected = table(clean)
    path = sorted((tmp_path / "chunks").glob("*.parquet"))[1]
    path.write_bytes(path.read_bytes()[:100])
    with pytest.warns(RKIdentWarning, match="recomputing"):
        again = small_study().run(tmp_path, progress=False)
    assert table(again).equals(expected)


@pytest.mark.parametrize(
    ("change", "word"),
    [
        ({"trials": 20}, "trials"),
        ({"chunk": 3}, "chunk"),
        ({"version": "2"}, "version"),
        ({"estimators": {"other": fir_ls}}, "estimators"),
    ],
)
def test_a_changed_declaration_is_refused(tmp_path, change, word):
    small_study().run(tmp_path, progress=False)
    with pytest.raises(StudyDeclarationError, match=word) as info:
        small_study(**change).run(tmp_path, progress=False)
    assert "new folder" in str(info.value)
    assert isinstance(info.value, InputValidationError)


def test_changed_grid_or_seed_is_refused(tmp_path):
    small_study().run(tmp_path, progress=False)
    other = Study(simulate_white, {"fir_ls": fir_ls}, grid={"N": [40]}, trials=15, seed=3, chunk=5)
    with pytest.raises(StudyDeclarationError, match="grid"):
        other.run(tmp_path, progress=False)
    reseeded = Study(simulate_white, {"fir_ls": fir_ls}, {"N": [40, 80]}, 15, seed=4, chunk=5)
    with pytest.raises(StudyDeclarationError, match="seed"):
        reseeded.run(tmp_path, progress=False)


def test_invalid_declarations_are_refused():
    with pytest.raises(InputValidationError, match="multiple of block"):
        small_study(chunk=5, block=2)
    with pytest.raises(InputValidationError, match="trials"):
        small_study(trials=1)
    with pytest.raises(InputValidationError, match="grid"):
        Study(simulate_white, {"fir_ls": fir_ls}, grid={"N": [object()]})
    with pytest.raises(InputValidationError, match="estimator"):
        Study(simulate_white, {}, grid={"N": [40]})
    with pytest.raises(InputValidationError, match="results yet"):
        _ = small_study().results


def test_simulate_with_the_wrong_batch_is_named(tmp_path):
    study = Study(
        lambda point, n, g: simulate_white(point, n + 1, g), {"fir_ls": fir_ls}, {"N": [40]}, 4
    )
    with pytest.raises(InputValidationError, match=r"batch shape \(1,\)"):
        study.run(tmp_path, progress=False)


def test_report_writes_tables_and_figures(tmp_path):
    study = small_study().run(tmp_path / "study", progress=False)
    path = study.report(tmp_path / "report")
    text = path.read_text()
    assert "## summary" in text and "## consistency" in text and "| N | estimator |" in text
    for name in ("summary.csv", "covariance.csv", "consistency.csv"):
        assert (tmp_path / "report" / name).exists()
    assert (tmp_path / "report" / "bias_std_vs_N.png").stat().st_size > 1000
    assert (tmp_path / "report" / "se_vs_std.png").stat().st_size > 1000


def test_dask_client_gives_the_local_table(tmp_path):
    distributed = pytest.importorskip(
        "distributed", reason="dask.distributed is an optional extra: pip install rkident[dask]"
    )
    local = small_study().run(tmp_path / "local", progress=False)
    with distributed.Client(
        processes=False, n_workers=1, threads_per_worker=2, dashboard_address=None
    ) as client:
        remote = small_study().run(tmp_path / "dask", client=client, progress=False)
    assert table(remote).equals(table(local))
    assert len(list((tmp_path / "dask" / "chunks").glob("*.parquet"))) == 6
