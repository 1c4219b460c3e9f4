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
import pandas as pd
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from sysid import ARX, FIR, IOData, fit
from sysid.errors import (
    InputValidationError,
    PoorExcitationWarning,
    RKIdentWarning,
    StudyDeclarationError,
)
from sysid.montecarlo import input_signal, simulate_data
from sysid.studies import WORKER_ENVIRONMENT, Study, local_cluster

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
    return table_of(study.results)


def table_of(frame):
    """``frame`` (results rows) without the timing column, in a canonical row order."""
    keys = ["N", "estimator", "trial", "parameter"]
    frame = frame.drop(columns="time").sort_values(keys).reset_index(drop=True)
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
        "error",
    ]
    assert len(rows) == 2 * 15 * 3
    # one batched fit per chunk gives the same numbers as a fit of each trial alone
    one = rows[(rows["N"] == 80) & (rows["trial"] == 7)]
    data = study.data(1, 1)[2]  # chunk 1 = trials 5..9
    alone = fit(FIR(3, 1), data)
    torch.testing.assert_close(torch.tensor(one["estimate"].to_numpy()), alone.theta)
    torch.testing.assert_close(torch.tensor(one["se"].to_numpy()), alone.standard_errors)
    assert one["loss"].iloc[0] == pytest.approx(float(alone.loss_history[-1]))


def test_in_memory_run_gives_the_checkpointed_table_and_writes_nothing(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    folder = small_study(chunk=5).run(tmp_path / "folder", progress=False)
    memory = small_study(chunk=5).run(progress=False)
    assert table(memory).equals(table(folder))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["folder"]
    with pytest.raises(InputValidationError, match="grid points 0..1 and chunks 0..2"):
        memory.data(2, 0)


def test_same_trial_same_data_for_any_block_aligned_chunk(tmp_path):
    a = small_study(chunk=3).run(tmp_path / "a", progress=False)
    b = small_study(chunk=5).run(tmp_path / "b", progress=False)
    c = small_study(chunk=15).run(tmp_path / "c", progress=False)
    assert table(a).equals(table(b)) and table(a).equals(table(c))
    d = small_study(chunk=10, block=5).run(tmp_path / "d", progress=False)
    e = small_study(chunk=5, block=5).run(tmp_path / "e", progress=False)
    assert table(d).equals(table(e))


def test_a_trial_keeps_its_data_when_trials_is_not_a_multiple_of_block(tmp_path):
    """The last, incomplete block is drawn whole and cut: trial 8 of a 10-trial study sees
    the data of trial 8 of a 12-trial one (block 4), so its estimates are equal."""
    ten = small_study(trials=10, chunk=4, block=4).run(progress=False)
    twelve = small_study(trials=12, chunk=4, block=4).run(progress=False)
    for point in range(2):
        last_10, last_12 = ten.data(point, 2), twelve.data(point, 2)
        assert last_10.batch_shape == (2,)
        torch.testing.assert_close(last_10.u, last_12.u[:2], rtol=0, atol=0)
        torch.testing.assert_close(last_10.y, last_12.y[:2], rtol=0, atol=0)
    keep = twelve.results["trial"] < 10
    assert table(ten).equals(table_of(twelve.results[keep]))


def simulate_two_experiments(point, n, generator):
    """n data sets of two experiments (60 and 40 samples) with first-order-hold inputs."""
    parts = []
    for N in (60, 40):
        u = input_signal("white", N, (n,), generator=generator)
        y = simulate_data(FIR(3, 1), u, theta=FIR_THETA, noise_std=SIGMA, generator=generator).y
        parts.append(IOData(u, y, Ts=0.1, intersample="foh"))
    return IOData.experiments(parts)


def test_chunks_of_several_blocks_keep_experiments_and_intersample(tmp_path):
    """A chunk of several blocks joins them data set by data set (``IOData.cat``): the
    experiments stay apart and the input's intersample behaviour is kept, so a trial's
    estimate does not depend on how many blocks its chunk holds."""
    kw = dict(grid={"N": [100]}, trials=4, seed=1, block=2, truth=FIR_TRUTH)
    one = Study(simulate_two_experiments, {"fir_ls": fir_ls}, chunk=2, **kw)
    two = Study(simulate_two_experiments, {"fir_ls": fir_ls}, chunk=4, **kw)
    data = two.data(0, 0)
    assert data.lengths == [60, 40] and data.intersample == "foh" and data.Ts == 0.1
    second_block = one.data(0, 1).experiment_list
    for joined, block in zip(data.experiment_list, second_block, strict=True):
        assert torch.equal(joined.u[2:], block.u) and torch.equal(joined.y[2:], block.y)
    assert table(one.run(progress=False)).equals(table(two.run(progress=False)))
    one_experiment = simulate_white({"N": 100}, 2, torch.Generator())
    with pytest.raises(InputValidationError, match="lengths = \\[100\\] but part 0 has"):
        IOData.cat([data, IOData(one_experiment.u, one_experiment.y, Ts=0.1, intersample="foh")])


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


def test_a_failed_chunk_write_is_raised_not_lost(tmp_path, monkeypatch):
    """Chunk files are written on a background thread: a write that fails (a full disk)
    still ends the run with its error."""
    import sysid.studies as studies

    def full_disk(frame, path):
        raise OSError("No space left on device")

    monkeypatch.setattr(studies, "_atomic_write_parquet", full_disk)
    with pytest.raises(OSError, match="No space left"):
        small_study().run(tmp_path / "run", progress=False)


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


def test_a_folder_without_results_takes_a_new_declaration_and_changes_are_named(tmp_path):
    """A folder left by a run that failed before its first chunk (manifest only) holds no
    results: a corrected declaration runs there. A grid value 1 against 1.0 (equal in Python,
    another declaration in the stored JSON) is named in the refusal."""

    def broken(point, n, generator):
        raise RuntimeError("simulate failed")

    with pytest.raises(RuntimeError, match="simulate failed"):
        Study(broken, {"fir_ls": fir_ls}, grid={"N": [40]}, trials=4, chunk=2).run(tmp_path)
    assert (tmp_path / "manifest.json").exists()
    small_study().run(tmp_path, progress=False)  # no longer "a different declaration"
    float_grid = Study(simulate_white, {"fir_ls": fir_ls}, {"N": [40.0, 80]}, 15, seed=3, chunk=5)
    with pytest.raises(StudyDeclarationError, match=r"grid: stored \{\"N\": \[40, 80\]\}"):
        float_grid.run(tmp_path, progress=False)


def test_truth_that_names_no_parameter_warns_and_a_non_number_is_refused(tmp_path):
    def declared(truth):
        return Study(simulate_white, {"fir_ls": fir_ls}, {"N": [40]}, 4, chunk=4, truth=truth)

    study = declared({"B1": 1.0, "b2": 0.5, "b3": 0.2}).run(progress=False)
    with pytest.warns(RKIdentWarning, match=r"truth names \['B1'\], which no estimator has"):
        summary = study.summary()
    assert summary[summary["parameter"] == "b1"]["bias"].isna().all()
    wrong = declared({"b1": "a"}).run(progress=False)
    with pytest.raises(InputValidationError, match=r"truth\['b1'\] = 'a'"):
        wrong.summary()


def test_summary_without_truth_and_chunk_files_without_the_error_column(tmp_path):
    """Without a declared truth the summary has NaN bias, RMSE and coverage (it raised a
    TypeError on an object column); chunk files written before the error column read back with
    an empty error (no trial failed), not NaN."""
    study = Study(simulate_white, {"fir_ls": fir_ls}, {"N": [40]}, 4, seed=1, chunk=2)
    summary = study.run(tmp_path, progress=False).summary()
    assert summary[["bias", "rmse", "coverage"]].isna().all().all()
    assert (summary["std"] > 0).all()
    for path in (tmp_path / "chunks").glob("*.parquet"):
        pd.read_parquet(path).drop(columns="error").to_parquet(path)
    again = Study(simulate_white, {"fir_ls": fir_ls}, {"N": [40]}, 4, seed=1, chunk=2)
    assert (again.run(tmp_path, progress=False).results["error"] == "").all()


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


def test_reordered_factors_repeated_values_and_summary_names_are_refused(tmp_path):
    """The order of the grid's factors numbers its points (their seeds and chunk files): a
    study with the same factors in another order is another declaration. A value given twice
    and a factor named like a summary column would be counted twice or overwritten."""
    grid = {"N": [40, 80], "sigma": [0.5, 1.0]}
    Study(simulate_white, {"fir_ls": fir_ls}, grid, trials=4, chunk=4).run(tmp_path)
    swapped = {"sigma": [0.5, 1.0], "N": [40, 80]}
    with pytest.raises(StudyDeclarationError, match=r'factors: stored \["N", "sigma"\]'):
        Study(simulate_white, {"fir_ls": fir_ls}, swapped, trials=4, chunk=4).run(tmp_path)
    with pytest.raises(InputValidationError, match="repeats the values 40"):
        Study(simulate_white, {"fir_ls": fir_ls}, {"N": [40, 40, 80]})
    for name in ("inside", "error2", "points", "mean", "z"):
        with pytest.raises(InputValidationError, match=f"grid factor '{name}'"):
            Study(simulate_white, {"fir_ls": fir_ls}, {"N": [40], name: [1, 2]})


def summary_row(summary, N, estimator, parameter):
    """The summary row of one grid point N, estimator and parameter."""
    at = (summary["N"] == N) & (summary["estimator"] == estimator)
    return summary[at & (summary["parameter"] == parameter)].iloc[0]


def test_failed_trials_leave_every_statistic_but_their_count(tmp_path):
    """Trials whose estimate is NaN (a failed fit) count in trials and converged only; trials
    with a finite estimate but a NaN standard error leave mean_se and coverage. Against
    numpy over the remaining trials."""

    def failing(data):
        result = fit(FIR(3, 1), data)
        bad = data.u[:, 0, 0] > 1.0  # about 16 % of the trials
        result.theta[bad] = math.nan
        result.converged[bad] = False
        return result

    def no_se(data):
        result = fit(FIR(3, 1), data)
        result.standard_errors[::2] = math.nan
        return result

    study = small_study(trials=60, chunk=20, estimators={"failing": failing, "no_se": no_se})
    summary = study.run(tmp_path, progress=False).summary()
    rows = study.results
    z = 1.959963984540054
    for (N, name, parameter), group in rows.groupby(["N", "estimator", "parameter"]):
        row = summary_row(summary, N, name, parameter)
        estimate, se = group["estimate"].to_numpy(), group["se"].to_numpy()
        ok = np.isfinite(estimate)
        both = ok & np.isfinite(se)
        error = estimate - FIR_TRUTH[parameter]
        assert row["trials"] == 60 and row["estimated"] == ok.sum()
        assert row["converged"] == pytest.approx(group["converged"].mean())
        assert row["bias_se"] == pytest.approx(estimate[ok].std(ddof=1) / np.sqrt(ok.sum()))
        assert row["mean_se"] == pytest.approx(se[both].mean())
        assert row["coverage"] == pytest.approx(np.mean(np.abs(error[both]) <= z * se[both]))
        assert row["rmse"] == pytest.approx(np.sqrt(np.mean(error[ok] ** 2)))
    assert (summary[summary["estimator"] == "failing"]["estimated"] < 60).all()


def test_undetermined_and_unconverged_estimates_follow_one_rule_in_every_statistic(tmp_path):
    """A trial with a zero input (its b's are undetermined: estimate 0, SE inf) leaves every
    statistic of those parameters, as a NaN estimate does; converged_only also leaves out
    the fits flagged not converged (wrong by +10 here). summary, covariances and
    normalized_errors against numpy over the same trials."""

    def zero_inputs(point, n, generator):
        data = simulate_white(point, n, generator)
        u = data.u.clone()
        u[::4] = 0.0  # every fourth trial of a block
        return simulate_data(FIR(3, 1), u, theta=FIR_THETA, noise_std=SIGMA, generator=generator)

    def flagged(data):
        result = fit(FIR(3, 1), data)
        bad = data.u[:, 1, 0] > 1.0
        result.theta[bad] += 10.0
        result.converged[bad] = False
        return result

    study = Study(
        zero_inputs,
        {"fir_ls": fir_ls, "flagged": flagged},
        grid={"N": [40, 80]},
        trials=40,
        seed=5,
        chunk=8,
        block=8,
        truth=FIR_TRUTH,
    )
    with pytest.warns(PoorExcitationWarning, match="minimum-norm"):
        study.run(tmp_path, progress=False)
    rows = study.results
    assert np.isposinf(rows[rows["trial"] % 4 == 0]["se"]).all()
    z95 = 1.959963984540054
    for converged_only in (False, True):
        summary = study.summary(converged_only=converged_only)
        errors = study.normalized_errors(converged_only)
        for (N, name, parameter), group in rows.groupby(["N", "estimator", "parameter"]):
            row = summary_row(summary, N, name, parameter)
            estimate, se = group["estimate"].to_numpy(), group["se"].to_numpy()
            use = (group["trial"] % 4 != 0).to_numpy()
            if converged_only:
                use = use & group["converged"].to_numpy()
            error = estimate[use] - FIR_TRUTH[parameter]
            assert row["trials"] == 40 and row["estimated"] == use.sum()
            assert row["mean"] == pytest.approx(estimate[use].mean(), rel=1e-12)
            assert row["std"] == pytest.approx(estimate[use].std(ddof=1), rel=1e-12)
            assert row["mean_se"] == pytest.approx(se[use].mean(), rel=1e-12)
            assert row["coverage"] == pytest.approx(np.mean(np.abs(error) <= z95 * se[use]))
            keep = (errors["N"] == N) & (errors["estimator"] == name)
            mine = errors[keep & (errors["parameter"] == parameter)]
            np.testing.assert_allclose(np.sort(mine["z"]), np.sort(error / se[use]), rtol=1e-12)
        for i, point in enumerate(study.points):
            for name in study.estimators:
                at = rows[(rows["N"] == point["N"]) & (rows["estimator"] == name)]
                theta = at["estimate"].to_numpy().reshape(-1, 3)
                use = at["trial"].to_numpy()[::3] % 4 != 0
                if converged_only:
                    use = use & at["converged"].to_numpy()[::3]
                c = study.covariances(i, name, converged_only)
                assert c["trials"] == use.sum()
                np.testing.assert_allclose(c["empirical"], np.cov(theta[use].T), rtol=1e-10)
                reported = np.stack(at["covariance_row"].to_numpy()).reshape(-1, 3, 3)
                np.testing.assert_allclose(c["reported"], reported[use].mean(0), rtol=1e-12)
    flagged_rows = study.summary(converged_only=True)
    flagged_rows = flagged_rows[flagged_rows["estimator"] == "flagged"]
    assert (flagged_rows["bias"].abs() < 0.3).all()  # the +10 fits are left out


def test_an_estimator_error_is_narrowed_down_to_the_trials_that_cause_it(tmp_path):
    """An estimator that raises a project error for a whole batch when one of its data sets is
    bad (here: a first input sample above 1.5) costs only those trials: NaN, not converged,
    the error's message; the other trials equal the plain fit's estimates. One that fails for
    every trial raises; one that returns no FitResult is named."""
    from sysid.errors import ConvergenceError

    def fragile(data):
        bad = data.u[:, 0, 0] > 1.5
        if bool(bad.any()):
            raise ConvergenceError(f"{int(bad.sum())} bad data sets in the batch")
        return fit(FIR(3, 1), data)

    study = small_study(trials=24, chunk=8, estimators={"fragile": fragile, "fir_ls": fir_ls})
    rows = study.run(tmp_path, progress=False).results
    first = torch.cat([study.data(i, c).u[:, 0, 0] for i in range(2) for c in range(3)])
    bad = np.repeat((first > 1.5).numpy(), 3)  # rows: point, trial, parameter
    assert 0 < bad.sum() < len(bad)
    fragile_rows = rows[rows["estimator"] == "fragile"].sort_values(["N", "trial", "parameter"])
    plain = rows[rows["estimator"] == "fir_ls"].sort_values(["N", "trial", "parameter"])
    assert np.isnan(fragile_rows["estimate"].to_numpy()[bad]).all()
    assert not fragile_rows["converged"].to_numpy()[bad].any()
    assert (
        fragile_rows["error"].to_numpy()[bad] == "ConvergenceError: 1 bad data sets in the batch"
    ).all()
    assert (fragile_rows["error"].to_numpy()[~bad] == "").all()
    np.testing.assert_allclose(
        fragile_rows["estimate"].to_numpy()[~bad], plain["estimate"].to_numpy()[~bad], rtol=1e-12
    )
    summary = study.summary()
    assert summary[summary["estimator"] == "fragile"]["estimated"].sum() == (~bad).sum()
    # chunks of one trial: a chunk the estimator fails for entirely takes the parameter names
    # of the others, so the table is that of chunks of 8 (to rounding of the batched fits)
    single = small_study(trials=24, chunk=1, estimators={"fragile": fragile, "fir_ls": fir_ls})
    single_rows = single.run(progress=False).results.sort_values(["N", "estimator", "trial"])
    eight = rows.sort_values(["N", "estimator", "trial"])
    for column in ("parameter", "converged", "error"):
        assert single_rows[column].tolist() == eight[column].tolist()
    np.testing.assert_allclose(single_rows["estimate"], eight["estimate"], rtol=1e-10)

    def hopeless(data):
        raise ConvergenceError("never")

    with pytest.raises(ConvergenceError, match="never"):
        small_study(trials=4, chunk=4, estimators={"hopeless": hopeless}).run(progress=False)
    with pytest.raises(InputValidationError, match="returned a NoneType without"):
        small_study(trials=4, chunk=4, estimators={"none": lambda data: None}).run(progress=False)


def test_simulate_with_the_wrong_batch_is_named(tmp_path):
    study = Study(
        lambda point, n, g: simulate_white(point, n + 1, g), {"fir_ls": fir_ls}, {"N": [40]}, 4
    )
    with pytest.raises(InputValidationError, match=r"batch shape \(1,\)"):
        study.run(tmp_path, progress=False)


# ---------------------------------------------------------------- seeding and execution order
@pytest.fixture(scope="module")
def table_64(tmp_path_factory):
    """The table of the 64-trial small study run in one chunk per grid point."""
    return table(
        small_study(chunk=64, trials=64).run(tmp_path_factory.mktemp("t64"), progress=False)
    )


def test_chunk_sizes_1_and_7_give_the_table_of_chunk_64(tmp_path, table_64):
    assert len(table_64) == 2 * 64 * 3
    for chunk in (1, 7):
        study = small_study(chunk=chunk, trials=64).run(tmp_path / str(chunk), progress=False)
        assert table(study).equals(table_64)


@settings(max_examples=5, deadline=None)
@given(order=st.permutations(range(2 * 10)), noise_seed=st.integers(0, 2**31))
def test_chunks_computed_in_any_order_give_the_same_table(table_64, order, noise_seed):
    """Each chunk's rows depend only on its coordinates: computed in a shuffled order (chunks
    of 7 trials), with the global generator disturbed between chunks, they make the table of
    the 64-trial run."""
    import pandas as pd

    study = small_study(chunk=7, trials=64)
    coordinates = [(i, c) for i in range(2) for c in range(study.n_chunks)]
    assert len(coordinates) == len(order)
    torch.manual_seed(noise_seed)
    frames = {}
    for k in order:
        torch.rand(int(torch.randint(1, 9, ())))  # disturbs the global generator
        frames[coordinates[k]] = study._compute_chunk(*coordinates[k])
    study._results = pd.concat([frames[key] for key in coordinates], ignore_index=True)
    assert table(study).equals(table_64)


# ---------------------------------------------------------------- a killed run resumes
KILLED_STUDY = """
import os, sys, time
import torch
from sysid import FIR, fit
from sysid.montecarlo import input_signal, simulate_data
from sysid.studies import WORKER_ENVIRONMENT, Study, local_cluster

CALLS = {"n": 0}


def simulate(point, n, generator):
    u = input_signal("white", point["N"], (n,), generator=generator)
    theta = torch.tensor([1.0, 0.5, 0.2], dtype=torch.float64)
    return simulate_data(FIR(3, 1), u, theta=theta, noise_std=0.5, generator=generator)


def estimate(data):
    CALLS["n"] += 1
    if CALLS["n"] > int(os.environ.get("HANG_AFTER", "1000000")):
        time.sleep(600)  # holds the run mid-way until the test kills it
    return fit(FIR(3, 1), data)


def make_study():
    return Study(simulate, {"fir_ls": estimate}, grid={"N": [40, 80]}, trials=20, seed=9,
                 chunk=4)


if __name__ == "__main__":
    make_study().run(sys.argv[1], progress=False)
"""


def test_a_killed_run_resumes_to_the_uninterrupted_table(tmp_path):
    """A subprocess running a study is killed (SIGKILL) after 3 of its 10 chunks are written;
    the rerun computes the other 7 and its table equals that of an uninterrupted run."""
    import os
    import pathlib
    import runpy
    import signal
    import subprocess
    import sys
    import time

    script = tmp_path / "killed_study.py"
    script.write_text(KILLED_STUDY)
    folder = tmp_path / "killed"
    env = {
        **os.environ,
        "HANG_AFTER": "3",
        "PYTHONPATH": str(pathlib.Path(__file__).resolve().parents[1]),
    }
    process = subprocess.Popen([sys.executable, str(script), str(folder)], env=env)
    try:
        while len(list((folder / "chunks").glob("*.parquet"))) < 3 and process.poll() is None:
            time.sleep(0.05)
        assert process.poll() is None, "the study ended before it could be killed"
    finally:
        process.send_signal(signal.SIGKILL)
        process.wait()
    assert process.returncode == -signal.SIGKILL
    assert len(list((folder / "chunks").glob("*.parquet"))) == 3
    declared = runpy.run_path(str(script))
    resumed = declared["make_study"]().run(folder, progress=False)
    assert declared["CALLS"]["n"] == 10 - 3  # only the missing chunks were computed
    clean = declared["make_study"]().run(tmp_path / "clean", progress=False)
    assert table(resumed).equals(table(clean))
    keys = ["N", "estimator", "trial", "parameter"]
    assert not resumed.results.duplicated(keys).any() and len(resumed.results) == 2 * 20 * 3


# ---------------------------------------------------------------- closed form at 20 000 trials
@pytest.mark.slow
def test_fir_empirical_covariance_within_5_percent_of_eq_4_101_at_20000_trials(tmp_path):
    """||C_emp - sigma^2 (U'U)^-1||_F / ||sigma^2 (U'U)^-1||_F < 0.05 (its sampling error
    at 20 000 trials is about 0.014, see the test above)."""
    study = Study(
        simulate_fir,
        {"fir_ls": fir_ls},
        grid={"N": [200]},
        trials=20000,
        seed=2,
        chunk=5000,
        block=5000,
        truth=FIR_TRUTH,
        theory=fir_theory,
    ).run(tmp_path, progress=False)
    row = study.covariance_summary().iloc[0]
    assert row["trials"] == 20000
    assert row["rel_frobenius_theory"] < 0.05
    c = study.covariances(0, "fir_ls")
    torch.testing.assert_close(c["theory"], fir_theory({"N": 200}, "fir_ls"))
    # the same matrix from numpy, independently of the study's own covariance code
    estimates = study.results["estimate"].to_numpy().reshape(-1, 3)
    torch.testing.assert_close(c["empirical"], torch.tensor(np.cov(estimates.T)))


# ---------------------------------------------------------------- consistency: ARX vs OE
def test_arx_bias_under_output_noise_does_not_shrink_while_oe_is_consistent(tmp_path):
    """White output noise on y = B/F u (notes §4.6.2-4.6.4): the ARX equation error F e is
    coloured and correlated with the regressors, so least squares has a bias that does not
    shrink with N (|bias| slope ~ 0, far above its Monte-Carlo error); OE minimises the
    simulation error and is consistent: no significant bias at any N, RMSE and std falling
    like N^(-1/2)."""
    from sysid import OE

    theta = torch.tensor([-1.2, 0.5, 0.5, 0.3], dtype=torch.float64)  # f1 f2 b1 b2

    def simulate(point, n, generator):
        u = input_signal("white", point["N"], (n,), generator=generator)
        return simulate_data(
            ARX(2, 2, 1), u, theta=theta, noise_std=0.5, noise="output", generator=generator
        )

    truth = {"a1": -1.2, "a2": 0.5, "f1": -1.2, "f2": 0.5, "b1": 0.5, "b2": 0.3}
    study = Study(
        simulate,
        {"arx_ls": lambda d: fit(ARX(2, 2, 1), d), "oe": lambda d: fit(OE(2, 2, 1), d)},
        grid={"N": [100, 400, 1600]},
        trials=150,
        seed=4,
        chunk=150,
        block=150,
        truth=truth,
    ).run(tmp_path, progress=False)
    slopes = study.consistency().set_index(["estimator", "parameter"])
    summary = study.summary().set_index(["estimator", "parameter", "N"]).sort_index()
    assert summary["converged"].eq(1).all()
    for parameter in ("a1", "a2"):
        assert abs(slopes.loc[("arx_ls", parameter), "bias_slope"]) < 0.05
        assert abs(slopes.loc[("arx_ls", parameter), "rmse_slope"]) < 0.1
        rows = summary.loc[("arx_ls", parameter)]
        assert (rows["bias"].abs() > 20 * rows["bias_se"]).all()
    oe = slopes.loc["oe"]
    assert ((oe["rmse_slope"] + 0.5).abs() < 0.1).all()
    assert ((oe["std_slope"] + 0.5).abs() < 0.1).all()
    rows = summary.loc["oe"]
    assert (rows["bias"].abs() < 4 * rows["bias_se"]).all()


# ---------------------------------------------------------------- Dask
# Tasks are pickled even on in-process (thread) workers; module-level functions travel by
# reference, so these see the test's state.
DASK_STATE: dict = {}


def fir_ls_recording_worker(data):
    from distributed import get_worker

    DASK_STATE["workers"].add(get_worker().address)
    return fir_ls(data)


def fir_ls_held_after_two_chunks(data):
    """The first two chunks run through; every later one waits until the test has closed a
    worker, so each worker holds a chunk in flight when one is closed."""
    with DASK_STATE["lock"]:
        DASK_STATE["calls"] += 1
        held = DASK_STATE["calls"] > 2
    if held:
        DASK_STATE["release"].wait(timeout=60)
    return fir_ls(data)


class _RecordingClient:
    """Stands in for a ``dask.distributed.Client``: runs each submitted task at once and
    records the size of what it would send to a worker."""

    def __init__(self):
        self.task_bytes = []

    def submit(self, fn, *args, pure=True):
        import concurrent.futures

        import cloudpickle

        self.task_bytes.append(len(cloudpickle.dumps((fn, args))))
        future = concurrent.futures.Future()
        future.set_result(fn(*args))
        return future

    def cancel(self, futures):
        pass


def test_a_rerun_on_a_client_sends_the_declaration_without_the_earlier_results(
    tmp_path, monkeypatch
):
    """Re-running a study object on a client must not ship the results table of its earlier
    run with every task (that table made each task about 1 MB in bench_studies and kept the
    scheduler busy); the table is the same either way."""
    import concurrent.futures

    dask_distributed = pytest.importorskip(
        "dask.distributed",
        reason="dask.distributed is an optional extra: pip install rkident[dask]",
    )
    monkeypatch.setattr(dask_distributed, "as_completed", concurrent.futures.as_completed)
    study = small_study(trials=200, chunk=50)
    local = table(study.run(tmp_path / "local", progress=False))
    client = _RecordingClient()
    study.run(tmp_path / "client", client=client, progress=False)
    assert len(client.task_bytes) == study.n_chunks * 2  # two grid points
    assert max(client.task_bytes) < 20_000, client.task_bytes
    assert table(study).equals(local)


def test_dask_two_workers_give_the_local_table_and_survive_a_killed_worker(tmp_path):
    """A LocalCluster of 2 workers (threads, processes=False) computes the table of the
    in-process runner; a worker closed while chunks are in flight leaves the study to
    finish on the other one, with every row once."""
    import threading

    distributed = pytest.importorskip(
        "distributed", reason="dask.distributed is an optional extra: pip install rkident[dask]"
    )
    local = small_study().run(tmp_path / "local", progress=False)
    chunks = tmp_path / "killed" / "chunks"
    DASK_STATE.update(
        calls=0, workers=set(), release=threading.Event(), lock=threading.Lock(), chunks=chunks
    )
    with (
        distributed.LocalCluster(
            n_workers=2, threads_per_worker=1, processes=False, dashboard_address=None
        ) as cluster,
        distributed.Client(cluster) as client,
    ):
        remote = small_study(estimators={"fir_ls": fir_ls_recording_worker}).run(
            tmp_path / "dask", client=client, progress=False
        )
        assert table(remote).equals(table(local))
        assert len(DASK_STATE["workers"]) == 2

        outcome = {}

        def run():
            try:
                outcome["study"] = small_study(
                    estimators={"fir_ls": fir_ls_held_after_two_chunks}
                ).run(tmp_path / "killed", client=client, progress=False)
            except BaseException as err:  # reported by the assertion below
                outcome["error"] = err

        thread = threading.Thread(target=run)
        thread.start()
        # two chunks written, and both workers inside a held chunk (each has one thread)
        while (
            len(list(chunks.glob("*.parquet"))) < 2 or DASK_STATE["calls"] < 4
        ) and thread.is_alive():
            thread.join(0.05)
        victim = next(iter(cluster.workers.values()))
        cluster.sync(victim.close, executor_wait=False)
        DASK_STATE["release"].set()
        thread.join(120)
        assert "error" not in outcome, outcome.get("error")
        assert len(client.scheduler_info()["workers"]) == 1
    assert table(outcome["study"]).equals(table(local))
    assert len(list(chunks.glob("*.parquet"))) == 6
    assert DASK_STATE["calls"] > 6  # the closed worker's chunk ran again on the other one


# ---------------------------------------------------------------- report
def test_report_figures_against_the_closed_forms(fir_study, tmp_path, saved_figures):
    """The report of the FIR study: normalised errors (t with N - 3 degrees of freedom, close
    to N(0, 1)), QQ points on y = x at scipy's normal quantiles, the binomial band of the
    coverage, the N^(-1/2) reference, and ellipses that are the level sets of the empirical
    (numpy) and theoretical (eq. 4.101) covariances; every figure free of defects."""
    from scipy.stats import chi2, norm

    from experiments._common import figure_defects

    path = fir_study.report(tmp_path, ellipse=("b1", "b3"))
    text = path.read_text()
    for name in ("summary", "covariance", "normalized_errors", "consistency"):
        assert f"## {name}" in text and (tmp_path / f"{name}.csv").exists()
    names = {
        "bias_std_vs_N.png",
        "coverage_vs_N.png",
        "normalized_histograms.png",
        "normalized_qq.png",
        "ellipses_b1_b3.png",
        "se_vs_std.png",
    }
    assert set(saved_figures) == names
    for name in names:
        assert f"]({name})" in text and (tmp_path / name).stat().st_size > 1000
        assert figure_defects(saved_figures[name]) == [], name

    T = fir_study.trials
    z = fir_study.normalized_error_summary()
    assert len(z) == 9 and (z["trials"] == T).all()
    assert (z["mean"].abs() < 4 / math.sqrt(T)).all()
    t_std = np.sqrt((z["N"] - 3) / (z["N"] - 5))  # Student's t, N - 3 degrees of freedom
    assert ((z["std"] - t_std).abs() < 4 / math.sqrt(2 * T)).all()
    assert (z["ks_pvalue"] > 1e-3).all()
    csv = __import__("pandas").read_csv(tmp_path / "normalized_errors.csv")
    np.testing.assert_allclose(csv["std"], z["std"])

    qq = saved_figures["normalized_qq.png"].axes
    assert len(qq) == 3
    for ax in qq:
        points = [line for line in ax.lines if line.get_linestyle() == "None"]
        assert len(points) == 3  # one per N
        for line in points:
            x, y = (np.asarray(v, dtype=float) for v in line.get_data())
            np.testing.assert_allclose(x, norm.ppf((np.arange(200) + 0.5) / 200))
            central = np.abs(x) < 2
            assert np.abs(y - x)[central].max() < 0.15

    (coverage,) = saved_figures["coverage_vs_N.png"].axes
    band = coverage.collections[0].get_paths()[0].vertices[:, 1]
    half = norm.ppf(0.975) * math.sqrt(0.95 * 0.05 / T)
    np.testing.assert_allclose([band.min(), band.max()], [0.95 - half, 0.95 + half])

    std_axes = saved_figures["bias_std_vs_N.png"].axes[1]
    (reference,) = [line for line in std_axes.lines if line.get_linestyle() == ":"]
    x, y = (np.asarray(v, dtype=float) for v in reference.get_data())
    np.testing.assert_allclose(np.diff(np.log(y)) / np.diff(np.log(x)), -0.5)

    radius2 = chi2.ppf(0.95, 2)
    ellipses = saved_figures["ellipses_b1_b3.png"].axes
    assert len(ellipses) == 3
    for point, ax in zip(fir_study.points, ellipses, strict=True):
        rows = fir_study.results[fir_study.results["N"] == point["N"]]
        estimates = rows["estimate"].to_numpy().reshape(-1, 3)[:, [0, 2]]
        mean = estimates.mean(0)
        lines = {line.get_label(): line for line in ax.lines}
        for label, cov in (
            ("empirical 0.95", np.cov(estimates.T)),
            ("theory 0.95", fir_theory(point, "fir_ls").numpy()[np.ix_([0, 2], [0, 2])]),
        ):
            xy = np.stack(lines[label].get_data(), axis=1).astype(float) - mean
            form = np.einsum("ki,ij,kj->k", xy, np.linalg.inv(cov), xy)
            np.testing.assert_allclose(form, radius2, rtol=1e-9)


def test_normalized_errors_reveal_a_wrong_truth(tmp_path):
    """With the truth of b1 off by 3 standard deviations the normalised errors of b1 have
    mean near 3 (the QQ summary is not blind to bias)."""
    shifted = {**FIR_TRUTH, "b1": FIR_TRUTH["b1"] - 3 * SIGMA / math.sqrt(200)}
    study = Study(
        simulate_fir,
        {"fir_ls": fir_ls},
        grid={"N": [200]},
        trials=400,
        seed=1,
        chunk=400,
        block=400,
        truth=shifted,
    ).run(tmp_path, progress=False)
    z = study.normalized_error_summary().set_index("parameter")
    u = fixed_input(200)
    phi, _ = FIR(3, 1).regression(IOData(u, torch.zeros_like(u)))
    expected = (
        3 * SIGMA / math.sqrt(200) / float(SIGMA * torch.linalg.inv(phi.T @ phi)[0, 0].sqrt())
    )
    assert abs(z.loc["b1", "mean"] - expected) < 4 / math.sqrt(400)
    assert abs(z.loc["b2", "mean"]) < 4 / math.sqrt(400)
    assert z.loc["b1", "ks_pvalue"] < 1e-6


def test_report_of_a_single_point_and_a_wrong_ellipse(tmp_path, saved_figures):
    """Without a numeric factor: no curves against N, but the histograms, QQ plots and the
    ellipses of the first two parameters; an unknown parameter is named."""
    from experiments._common import figure_defects

    study = Study(
        simulate_white, {"fir_ls": fir_ls}, {"N": [40]}, 30, seed=2, chunk=10, truth=FIR_TRUTH
    ).run(tmp_path / "study", progress=False)
    path = study.report(tmp_path / "report")
    assert "## consistency" not in path.read_text()
    assert set(saved_figures) == {
        "normalized_histograms.png",
        "normalized_qq.png",
        "ellipses_b1_b2.png",
        "se_vs_std.png",
    }
    for name, fig in saved_figures.items():
        assert figure_defects(fig) == [], name
    with pytest.raises(InputValidationError, match="b7"):
        study.report(tmp_path / "other", ellipse=("b1", "b7"))


def _worker_environment():
    import os

    return {key: os.environ.get(key) for key in WORKER_ENVIRONMENT}


def test_local_cluster_starts_worker_processes_with_the_study_environment(tmp_path):
    """The worker processes of ``local_cluster`` get WORKER_ENVIRONMENT before they start
    (dask's own default trim threshold makes torch re-fault its memory on every operation)
    and compute the in-process table."""
    distributed = pytest.importorskip(
        "distributed", reason="dask.distributed is an optional extra: pip install rkident[dask]"
    )
    local = small_study().run(tmp_path / "local", progress=False)
    with local_cluster(1) as cluster, distributed.Client(cluster) as client:
        seen = client.run(_worker_environment)
        remote = small_study().run(tmp_path / "dask", client=client, progress=False)
    assert list(seen.values()) == [{k: str(v) for k, v in WORKER_ENVIRONMENT.items()}]
    assert table(remote).equals(table(local))
