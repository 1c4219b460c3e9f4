"""Tests of sysid.validation against hand computations, scipy and statsmodels."""

import math

import numpy as np
import pytest
import scipy.linalg
import scipy.signal
import scipy.stats
import statsmodels.api as sm
import torch
from _shared_models import LinearRHS
from statsmodels.stats.diagnostic import acorr_ljungbox
from statsmodels.tsa.stattools import acf, ccf

from integrators.errors import InputValidationError
from sysid.data import IOData
from sysid.estimation import fit
from sysid.filters import iir_filter
from sysid.models import ARX, OE
from sysid.montecarlo import input_signal, simulate_data
from sysid.validation import aic, fit_percent, fit_quality, fpe, residual_test, select_order

DT = torch.float64


def gen(seed):
    return torch.Generator().manual_seed(seed)


def test_fit_percent_hand_computation():
    rng = np.random.default_rng(0)
    y = rng.standard_normal((3, 50, 2))
    yhat = y + 0.3 * rng.standard_normal((3, 50, 2))
    got = fit_percent(torch.tensor(y), torch.tensor(yhat)).numpy()
    for b in range(3):
        for c in range(2):
            ref = 100 * (
                1
                - np.linalg.norm(y[b, :, c] - yhat[b, :, c])
                / np.linalg.norm(y[b, :, c] - y[b, :, c].mean())
            )
            assert got[b, c] == pytest.approx(ref, rel=1e-12)
    yt = torch.tensor(y)
    assert torch.allclose(fit_percent(yt, yt), torch.full((3, 2), 100.0, dtype=DT))
    mean_model = yt.mean(dim=-2, keepdim=True).expand_as(yt)
    assert torch.allclose(fit_percent(yt, mean_model), torch.zeros(3, 2, dtype=DT), atol=1e-12)
    with pytest.raises(InputValidationError, match="constant"):
        fit_percent(torch.ones(10), torch.zeros(10))


def test_fit_percent_needs_the_samples_and_channels_of_y():
    """yhat with another number of samples or channels broadcast along time: a (1,) yhat
    against 50 samples gave a fit, (1, 50) against (50, 1) gave 50 fits. Batch dimensions
    still broadcast: one yhat (50, 2) against three batch members equals the loop."""
    rng = np.random.default_rng(2)
    y = torch.tensor(rng.standard_normal((3, 50, 2)))
    y1 = y[0, :, 0]
    pairs = [(y1, torch.zeros(1)), (y1[:, None], y1[None, :]), (y1, y1[:49]), (y[0], y[0, :, :1])]
    for call in (fit_percent, fit_quality):
        for measured, yhat in pairs:
            with pytest.raises(InputValidationError, match="same number of samples N"):
                call(measured, yhat)
    yhat = torch.tensor(rng.standard_normal((50, 2)))
    got = fit_percent(y, yhat)
    for b in range(3):
        ref = 100 * (
            1 - np.linalg.norm(y[b] - yhat, axis=0) / np.linalg.norm(y[b] - y[b].mean(0), axis=0)
        )
        np.testing.assert_allclose(got[b].numpy(), ref, rtol=1e-12)


def test_aic_fpe_hand_computation():
    rng = np.random.default_rng(1)
    e = rng.normal(0, 0.7, size=(4, 200))
    d = 5
    got_aic = aic(torch.tensor(e).unsqueeze(-1), d).numpy()
    got_fpe = fpe(torch.tensor(e).unsqueeze(-1), d).numpy()
    for b in range(4):
        V = np.mean(e[b] ** 2)
        loglik = scipy.stats.norm.logpdf(e[b], scale=math.sqrt(V)).sum()  # maximised Gaussian
        assert got_aic[b] == pytest.approx(-2 * loglik + 2 * d, rel=1e-12)
        assert got_fpe[b] == pytest.approx(V * (1 + d / 200) / (1 - d / 200), rel=1e-12)


def test_residual_test_matches_statsmodels():
    e = torch.randn(2, 300, 1, generator=gen(2), dtype=DT)
    u = torch.randn(2, 300, 1, generator=gen(3), dtype=DT)
    r = residual_test(e, u, max_lag=12)
    for b in range(2):
        x = e[b, :, 0].numpy()
        np.testing.assert_allclose(r.autocorrelation[b].numpy(), acf(x, nlags=12), atol=1e-12)
        lb = acorr_ljungbox(x, lags=[12])
        assert r.whiteness_statistic[b].item() == pytest.approx(lb["lb_stat"].iloc[0], rel=1e-10)
        assert r.whiteness_pvalue[b].item() == pytest.approx(lb["lb_pvalue"].iloc[0], rel=1e-8)
        ref = ccf(x, u[b, :, 0].numpy(), adjusted=False)[:13]  # corr(e_{k+tau}, u_k), tau >= 0
        np.testing.assert_allclose(r.cross_correlation[b, 0, 12:].numpy(), ref, atol=1e-12)
    assert r.bound == pytest.approx(scipy.stats.norm.ppf(0.995) / math.sqrt(300))


def test_residual_test_flags_coloured_and_passes_white():
    T, N = 400, 400
    white = torch.randn(T, N, generator=gen(4), dtype=DT)
    u = torch.randn(T, N, 1, generator=gen(5), dtype=DT)
    res_white = residual_test(white.unsqueeze(-1), u, max_lag=20, alpha=0.01)
    # false alarm rates near alpha = 1 % (the Ljung-Box chi^2 law is slightly liberal at
    # N = 400, m = 20: statsmodels' acorr_ljungbox rejects the same 3.5 % of these series)
    assert res_white.white.float().mean() > 0.95
    assert res_white.independent.float().mean() > 0.95
    coloured = iir_filter(torch.ones(1, dtype=DT), torch.tensor([-0.5], dtype=DT), white)
    res_col = residual_test(coloured.unsqueeze(-1), max_lag=20)
    assert res_col.white.float().mean() < 0.01
    # residuals that still contain the input two samples back: not independent of past inputs
    leak = white[:, 2:] + 0.5 * u[:, :-2, 0]
    res_leak = residual_test(leak.unsqueeze(-1), u[:, 2:], max_lag=10)
    assert res_leak.independent.float().mean() < 0.01
    assert res_leak.cross_correlation[:, 0, 12].mean() > 3 * res_leak.bound  # lag +2


def test_select_order_picks_true_arx_order():
    u = input_signal("white", 600, (20,), generator=gen(6))
    true = torch.tensor([-1.2, 0.5, 0.5, 0.3], dtype=DT)
    data = simulate_data(
        ARX(2, 2, 1), u, theta=true, noise_std=0.1, noise="model", generator=gen(7)
    )
    val = select_order(data, "arx", criterion="validation")
    assert val.best == (2, 2)
    assert (val.best_index == val.orders.index((2, 2))).float().mean() >= 0.9
    for criterion in ("aic", "fpe"):
        sel = select_order(data, "arx", criterion=criterion)
        chosen = [sel.orders[i] for i in sel.best_index.tolist()]
        assert all(na >= 2 and nb >= 2 for na, nb in chosen)  # never under-fits
        counts = {o: chosen.count(o) for o in set(chosen)}
        assert max(counts, key=counts.get) == (2, 2)  # the most frequent choice is the truth
    # table rows carry the criteria; AIC of the true order beats the under-fitted ones
    rows = {(r["na"], r["nb"]): r for r in sel.table}
    assert rows[(2, 2)]["aic"] < rows[(1, 2)]["aic"] and rows[(2, 2)]["aic"] < rows[(2, 1)]["aic"]


# ---------------------------------------------------------------- model form f(model, data)
def _fitted_oe():
    """An OE(2, 2) fit to noisy data of a known OE system, plus fresh validation data."""
    truth = OE(2, 2)
    theta = torch.tensor([0.5, 0.3, -1.2, 0.5], dtype=DT)
    u = input_signal("white", 300, (), generator=gen(10))
    data = simulate_data(truth, u, theta=theta, noise_std=0.1, generator=gen(11))
    u_val = input_signal("white", 300, (), generator=gen(12))
    val = simulate_data(truth, u_val, theta=theta, noise_std=0.1, generator=gen(13))
    return fit(OE(2, 2), data), data, val


def test_model_forms_equal_array_forms():
    result, data, val = _fitted_oe()
    model = result.model
    with torch.no_grad():
        y_sim = model.simulate(val.u)
        e_est = data.y - model.predict(data)
    for obj in (model, result):
        # fit % of the free-run simulation (MATLAB's compare), not of the one-step prediction
        got = fit_percent(obj, val)
        assert torch.equal(got, fit_percent(val.y, y_sim))
        assert not got.requires_grad
        assert torch.equal(aic(obj, data), aic(e_est, model.n_params))
        assert torch.equal(fpe(obj, data), fpe(e_est, model.n_params))
        r = residual_test(obj, data, max_lag=15)
        ref = residual_test(e_est, data.u, max_lag=15)
        assert torch.equal(r.autocorrelation, ref.autocorrelation)
        assert torch.equal(r.cross_correlation, ref.cross_correlation)
        assert torch.equal(r.passed, ref.passed)
    assert 90.0 < fit_percent(model, val).item() < 100.0  # OE of the true order fits well


@pytest.mark.parametrize("d", [3, 5, -1])
def test_criteria_refuse_n_params_outside_their_range(d):
    """FPE needs 0 <= d < N (its denominator 1 - d/N vanishes at d = N); AIC only d >= 0
    (N log V + 2 d stays defined, e.g. for a network's weights: the hand formula)."""
    e = torch.randn(3, 1, generator=gen(16), dtype=torch.float64)
    with pytest.raises(InputValidationError, match=rf"fpe: .*d = {d}"):
        fpe(e, d)
    if d < 0:
        with pytest.raises(InputValidationError, match="aic: n_params must be >= 0"):
            aic(e, d)
    else:
        V = float((e**2).mean())
        expected = 3 * math.log(V) + 2 * d + 3 * (math.log(2 * math.pi) + 1)
        assert float(aic(e, d)) == pytest.approx(expected, rel=1e-12)


@pytest.mark.parametrize(
    ("call", "words"),
    [
        (lambda m, d, y: fit_percent(d, m), "fit_percent(model, data)"),  # swapped
        (lambda m, d, y: fit_percent(m, y), "fit_percent(model, data)"),  # tensor, not IOData
        (lambda m, d, y: fit_percent(d, y), "fit_percent(y, yhat)"),
        (lambda m, d, y: fit_percent("y", y), "fit_percent(y, yhat)"),
        (lambda m, d, y: aic(m, 4), "aic(model, data)"),
        (lambda m, d, y: aic(y, 4.5), "aic(residuals, n_params)"),
        (lambda m, d, y: fpe(d, m), "fpe(model, data)"),
        (lambda m, d, y: residual_test(m, y), "residual_test(model, data, ...)"),
        (lambda m, d, y: residual_test(y, d), "residual_test(residuals, u=None, ...)"),
        (lambda m, d, y: residual_test({"e": 1}), "residual_test(residuals, u=None, ...)"),
    ],
)
def test_wrong_argument_types_name_the_signature(call, words):
    model = OE(1, 1)
    data = IOData(torch.randn(50, generator=gen(14)), torch.randn(50, generator=gen(15)))
    with pytest.raises(InputValidationError, match="expected") as info:
        call(model, data, data.y)
    assert words in str(info.value)


def test_result_without_model_is_refused():
    result, data, _ = _fitted_oe()
    result.model = None
    with pytest.raises(InputValidationError, match=r"got \(FitResult, IOData\)"):
        fit_percent(result, data)


def test_fit_result_validate_leaves_out_the_start_of_every_experiment():
    """Two validation experiments cut from one record (the second starts away from rest):
    ``validate(data, skip)`` and ``fit_percent(result, data, skip)`` leave out the first
    ``skip`` samples of each, as an independent per-experiment simulation from rest by scipy's
    lfilter does; they left out only the first experiment's (550 samples, fit 88.8 % instead
    of 95.6 %)."""
    import scipy.signal

    rng = np.random.default_rng(0)
    u = rng.standard_normal(600)
    y = scipy.signal.lfilter([0, 0.1], [1, -0.9], u) + 0.01 * rng.standard_normal(600)
    parts = [IOData(u[:300], y[:300]), IOData(u[300:], y[300:])]
    data = IOData.experiments(parts)
    res = fit(OE(1, 1, 1), data)
    quality = res.validate(data, skip=50)
    b1, f1 = res.theta.tolist()
    ys, yhat = [], []
    for part in parts:
        ys.append(part.y.numpy()[50:, 0])
        yhat.append(scipy.signal.lfilter([0, b1], [1, f1], part.u.numpy()[:, 0])[50:])
    ys, yhat = np.concatenate(ys), np.concatenate(yhat)
    percent = 100 * (1 - np.linalg.norm(ys - yhat) / np.linalg.norm(ys - ys.mean()))
    assert quality.n_samples == 500 and quality.skip == 50
    np.testing.assert_allclose(float(quality.fit_percent), percent, rtol=1e-10)
    np.testing.assert_allclose(float(quality.rmse), np.sqrt(np.mean((ys - yhat) ** 2)), rtol=1e-10)
    np.testing.assert_allclose(float(fit_percent(res, data, skip=50)), percent, rtol=1e-10)
    for call in (res.validate, lambda d, skip: fit_percent(res, d, skip=skip)):
        with pytest.raises(InputValidationError, match="skip"):
            call(data, skip=299)


@pytest.mark.parametrize("structure", ["fir", "arx"])
def test_select_order_criteria_equal_statsmodels_ols_on_the_scored_rows(structure):
    # every FIR / ARX candidate is the least-squares fit on the scored samples (the first
    # max lag + nk of each experiment serve only as regressors): its AIC and FPE are those of
    # statsmodels' OLS on the same rows, whichever its own lags (two experiments, 3 data sets)
    lengths = (70, 55)
    parts = []
    for e, n in enumerate(lengths):
        u = input_signal("white", n, (3,), generator=gen(30 + e))
        parts.append(
            simulate_data(
                ARX(2, 2, 1),
                u,
                theta=torch.tensor([-1.2, 0.5, 0.5, 0.3], dtype=DT),
                noise_std=0.1,
                noise="model",
                generator=gen(40 + e),
            )
        )
    data = IOData.experiments(parts)
    nk = 2
    sel = select_order(data, structure, nk=nk)
    assert not sel.aic.requires_grad  # plain numbers to compare (and .numpy() works)
    skip = max(max(o) for o in sel.orders) + nk
    for i, order in enumerate(sel.orders):
        na, nb = (0, order[0]) if structure == "fir" else order
        for b in range(3):
            X, target = [], []
            for part in parts:
                y, u = part.y[b, :, 0].numpy(), part.u[b, :, 0].numpy()
                k = np.arange(skip, part.N)
                lagged_y = [-y[k - j] for j in range(1, na + 1)]
                X.append(np.column_stack(lagged_y + [u[k - nk - j] for j in range(nb)]))
                target.append(y[k])
            ols = sm.OLS(np.concatenate(target), np.concatenate(X)).fit()
            assert sel.aic[i, b].item() == pytest.approx(ols.aic, rel=1e-10, abs=1e-9)
            d, n = ols.df_model, ols.nobs
            assert sel.fpe[i, b].item() == pytest.approx(
                ols.ssr / n * (1 + d / n) / (1 - d / n), rel=1e-10
            )


def test_select_order_refuses_orders_that_are_not_integers():
    """orders=[(1.7, 2.9)] ran the (1, 2) candidate and reported it as the choice; numpy
    integers are orders like any other (the same AIC as the Python ints, and as the one
    candidate given, the choice)."""
    u = input_signal("white", 200, generator=gen(31))
    true = torch.tensor([-0.5, 1.0, 0.3], dtype=DT)
    data = simulate_data(ARX(1, 2, 1), u, theta=true, noise_std=0.1, generator=gen(32))
    for orders in ([(1.7, 2.9)], [(1, 2.0)], [(True, 2)], [1]):
        with pytest.raises(InputValidationError, match="orders"):
            select_order(data, "arx", orders=orders)
    plain = select_order(data, "arx", orders=[(1, 2)])
    numpy = select_order(data, "arx", orders=[(np.int64(1), np.int32(2))])
    assert numpy.best == (1, 2) and type(numpy.best[0]) is int
    assert numpy.table[0]["aic"] == plain.table[0]["aic"]


def test_select_order_scores_every_experiment_after_its_own_start():
    """AIC/FPE of select_order on two experiments (the second far from rest at its start)
    equal those of the one-step ARX prediction errors computed per experiment by numpy with the
    first max-lag samples of each left out, for the least-squares fit on those same rows; only
    the first experiment's were left out."""
    rng = np.random.default_rng(3)
    parts = []
    for y0 in (0.0, 8.0):
        u = rng.standard_normal(200)
        y = scipy.signal.lfilter([0, 0.5], [1, -0.8], u) + y0 * 0.8 ** np.arange(200)
        parts.append(IOData(u, y + 0.05 * rng.standard_normal(200)))
    data = IOData.experiments(parts)
    orders = [(1, 1), (2, 2)]
    selection = select_order(data, "arx", orders=orders)
    skip = 2 + 1  # the largest candidate's lag and the delay
    for k, (na, nb) in enumerate(orders):
        rows, targets = [], []
        for part in parts:
            u, y = part.u.numpy()[:, 0], part.y.numpy()[:, 0]
            for t in range(skip, len(y)):
                rows.append(
                    [-y[t - i] for i in range(1, na + 1)] + [u[t - i] for i in range(1, nb + 1)]
                )
                targets.append(y[t])
        theta = np.linalg.lstsq(np.array(rows), np.array(targets), rcond=None)[0]
        errors = []
        for part in parts:
            u, y = part.u.numpy()[:, 0], part.y.numpy()[:, 0]
            pred = np.zeros_like(y)
            for t in range(skip, len(y)):
                past_y = [-y[t - i] for i in range(1, na + 1)]
                past_u = [u[t - i] for i in range(1, nb + 1)]
                pred[t] = np.dot(theta, past_y + past_u)
            errors.append((y - pred)[skip:])
        e = torch.tensor(np.concatenate(errors)).unsqueeze(-1)
        d = na + nb
        torch.testing.assert_close(selection.aic[k], aic(e, d), rtol=1e-10, atol=0)
        torch.testing.assert_close(selection.fpe[k], fpe(e, d), rtol=1e-10, atol=0)


def test_independence_test_holds_its_level_with_a_coloured_input():
    """White residuals independent of an AR(1) input (pole 0.95): the independence test must
    reject about alpha of the data sets. Without the input's autocorrelation matrix in the
    statistic (Ljung 1999, eq. 16.66) it rejected 15 % at alpha = 1 %; the statistic of one
    data set equals N rho' R_u^-1 rho computed with scipy's Toeplitz matrix."""
    import scipy.linalg
    import scipy.signal

    rng = np.random.default_rng(0)
    trials, N, m, alpha = 1000, 500, 20, 0.05
    e = rng.standard_normal((trials, N, 1))
    u = scipy.signal.lfilter([1.0], [1.0, -0.95], rng.standard_normal((trials, N + 200)))
    u = u[:, 200:, None]
    result = residual_test(torch.tensor(e), torch.tensor(u), max_lag=m, alpha=alpha)
    rejected = float((~result.independent).double().mean())
    assert 0.025 <= rejected <= 0.08, rejected  # binomial sd 0.007 around 0.05
    uc = u[0, :, 0] - u[0, :, 0].mean()
    autocorrelation = np.array([uc[k:] @ uc[: N - k] for k in range(m + 1)]) / (uc @ uc)
    rho = result.cross_correlation[0, 0, m:].numpy()
    S = N * rho @ np.linalg.solve(scipy.linalg.toeplitz(autocorrelation), rho)
    np.testing.assert_allclose(float(result.independence_statistic[0, 0]), S, rtol=1e-10)
    np.testing.assert_allclose(
        float(result.independence_pvalue[0, 0]), scipy.stats.chi2.sf(S, m + 1), rtol=1e-10
    )


# ------------------------------------- model form of grey-box and neural/hybrid fit results
def _zoh_first_order(a, b, x0, u, Ts):
    """Exact zero-order-hold samples of x' = -a x + b u, y = x from x(0) = x0 (scipy expm)."""
    M = scipy.linalg.expm(np.array([[-a, b], [0.0, 0.0]]) * Ts)
    x = np.empty(len(u))
    x[0] = x0
    for k in range(len(u) - 1):
        x[k + 1] = M[0, 0] * x[k] + M[0, 1] * u[k]
    return x


def test_greybox_result_model_forms_score_the_fitted_free_run():
    """A grey-box fit of x' = -a x + b u (initial states estimated) to noisy ZOH data of two
    experiments: fit_percent, residual_test, aic and fpe of (result, data) score
    y - yhat with yhat the exact ZOH response of the fitted (a, b) from each experiment's
    estimated x0, d = 4 (a, b and two initial states); the model form refused the result."""
    from sysid import GreyBoxModel, Param

    rng = np.random.default_rng(3)
    Ts, parts = 0.1, []
    for x0, n in ((0.0, 80), (0.8, 70)):
        u = np.repeat(rng.uniform(-1, 1, n // 4 + 1), 4)[:n]
        y = _zoh_first_order(1.5, 0.7, x0, u, Ts) + 0.02 * rng.standard_normal(n)
        parts.append(IOData(u, y, Ts=Ts))
    data = IOData.experiments(parts)
    model = GreyBoxModel(
        lambda t, x, u, p: -p["a"] * x + p["b"] * u,
        {"a": Param(1.0, min=0.0), "b": Param(1.0)},
        nx=1,
        output=[0],
        substeps=2,
        compile=False,
    )
    result = fit(model, data, x0="estimate")
    a, b, x0_1, x0_2 = result.theta.tolist()
    yhat = [
        _zoh_first_order(a, b, x0, p.u.numpy()[:, 0], Ts)
        for x0, p in zip((x0_1, x0_2), parts, strict=True)
    ]
    ys = [p.y.numpy()[:, 0] for p in parts]

    skip = 10
    y_kept = np.concatenate([y[skip:] for y in ys])
    e_kept = y_kept - np.concatenate([h[skip:] for h in yhat])
    percent = 100 * (1 - np.linalg.norm(e_kept) / np.linalg.norm(y_kept - y_kept.mean()))
    np.testing.assert_allclose(float(fit_percent(result, data, skip=skip)), percent, rtol=1e-7)
    y_all, e = np.concatenate(ys), np.concatenate(ys) - np.concatenate(yhat)
    percent_all = 100 * (1 - np.linalg.norm(e) / np.linalg.norm(y_all - y_all.mean()))
    np.testing.assert_allclose(float(fit_percent(result, data)), percent_all, rtol=1e-7)

    got = residual_test(result, data, max_lag=10)
    ref = residual_test(torch.tensor(e), data.u, max_lag=10)
    torch.testing.assert_close(got.autocorrelation, ref.autocorrelation, rtol=0, atol=1e-5)
    torch.testing.assert_close(got.cross_correlation, ref.cross_correlation, rtol=0, atol=1e-5)
    torch.testing.assert_close(got.whiteness_statistic, ref.whiteness_statistic, rtol=1e-4, atol=0)
    torch.testing.assert_close(
        got.independence_statistic, ref.independence_statistic, rtol=1e-4, atol=1e-6
    )

    N, d, V = len(e), 4, np.mean(e**2)
    assert result.theta.shape[-1] == d
    np.testing.assert_allclose(
        float(aic(result, data)), N * np.log(V) + 2 * d + N * (np.log(2 * np.pi) + 1), rtol=1e-7
    )
    np.testing.assert_allclose(float(fpe(result, data)), V * (1 + d / N) / (1 - d / N), rtol=1e-6)


def test_training_result_model_forms_score_the_free_run_after_n_init():
    """A TrainingResult (initial-state encoder, n_init = 3, two experiments): fit_percent
    equals result.validate (default skip n_init) and the numpy fit of result.simulate after
    ``skip`` samples of each experiment; residual_test tests y - yhat and u of the samples
    from n_init of every experiment on; aic/fpe refuse it by name; the model form refused
    the result."""
    rng = np.random.default_rng(4)
    parts = []
    for n in (60, 45):
        u = np.repeat(rng.uniform(-1, 1, n // 3 + 1), 3)[:n]
        y = _zoh_first_order(1.0, 1.0, 0.0, u, 0.1) + 0.01 * rng.standard_normal(n)
        parts.append(IOData(u, y, Ts=0.1))
    data = IOData.experiments(parts)
    result = fit(
        LinearRHS([-0.8], [1.2]),
        data,
        method="adam",
        horizon=5,
        batch_size=4,
        epochs=2,
        steps_per_epoch=2,
        lr=1e-2,
        x0="encoder",
        n_init=3,
        seed=0,
    )
    yhat = result.simulate(data)[:, 0].numpy()
    y = data.y[:, 0].numpy()
    torch.testing.assert_close(fit_percent(result, data), result.validate(data)["fit_percent"])
    for skip in (3, 7):
        keep = np.r_[skip:60, 60 + skip : 105]
        percent = 100 * (
            1 - np.linalg.norm(y[keep] - yhat[keep]) / np.linalg.norm(y[keep] - y[keep].mean())
        )
        np.testing.assert_allclose(float(fit_percent(result, data, skip=skip)), percent, rtol=1e-10)
    with pytest.raises(InputValidationError, match="n_init = 3"):
        fit_percent(result, data, skip=1)

    keep = np.r_[3:60, 63:105]
    got = residual_test(result, data, max_lag=8)
    ref = residual_test(torch.tensor(y[keep] - yhat[keep]), data.u[keep], max_lag=8)
    torch.testing.assert_close(got.autocorrelation, ref.autocorrelation)
    torch.testing.assert_close(got.cross_correlation, ref.cross_correlation)
    torch.testing.assert_close(got.independence_statistic, ref.independence_statistic)
    two_inputs = IOData(np.ones((60, 2)), y[:60], Ts=0.1)
    with pytest.raises(InputValidationError, match="residual_test: the data have nu = 2"):
        residual_test(result, two_inputs)
    for criterion in (aic, fpe):
        with pytest.raises(InputValidationError, match="TrainingResult.*network weights"):
            criterion(result, data)


def test_model_forms_refuse_data_of_another_sample_time():
    """fit refuses a model whose Ts differs from the data's; the model forms of fit_percent
    and residual_test do the same for a polynomial model whose Ts was set (e.g. by fit)."""
    import sysid

    g = torch.Generator().manual_seed(3)
    u = torch.randn(200, 1, generator=g, dtype=torch.float64)
    y = torch.randn(200, 1, generator=g, dtype=torch.float64)
    result = sysid.fit(sysid.ARX(1, 1, 1), sysid.IOData(u, y, Ts=0.1))
    other = sysid.IOData(u, y, Ts=0.5)
    for check in (sysid.fit_percent, sysid.residual_test):
        with pytest.raises(InputValidationError, match=r"Ts = 0.1 s but the data Ts = 0.5 s"):
            check(result, other)
    assert torch.isfinite(sysid.fit_percent(result, sysid.IOData(u, y, Ts=0.1))).all()
    assert torch.isfinite(sysid.fit_percent(sysid.ARX(1, 1, 1), other)).all()  # Ts not set
