"""Tests of sysid.estimation.fit and uniform_noise_mle_set (notes §4.2–4.6).

Independent references: exact noise-free recovery, batched Monte-Carlo studies against the
asymptotic covariance, statsmodels OLS, finite differences of the Jacobian, scipy
least_squares (Huber loss), scipy linear programs (LAD and the uniform-noise polytope) and a
brute-force grid search.
"""

import functools
import math
import warnings

import numpy as np
import pytest
import scipy.optimize
import scipy.signal
import statsmodels.api as sm
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from integrators.errors import InputValidationError
from integrators.jacobians import batch_jacobian
from integrators.newton import minimize
from sysid.data import IOData
from sysid.errors import ConvergenceWarning, PoorExcitationWarning
from sysid.estimation import fit, uniform_noise_mle_set
from sysid.estimation import prediction_error as pe
from sysid.estimation.prediction_error import _OutputError
from sysid.estimation.results import inverse_normal_matrix_and_rank
from sysid.filters import iir_filter
from sysid.models import ARMAX, ARX, BJ, FIR, OE
from sysid.montecarlo import input_signal, noise_signal, simulate_data, summarize_estimates

DT = torch.float64
TRUE = {
    "FIR": (FIR(4, 1), [0.5, 0.3, -0.2, 0.1]),
    "ARX": (ARX(2, 2, 1), [-1.2, 0.5, 0.5, 0.3]),
    "OE": (OE(2, 2, 1), [0.5, 0.3, -1.2, 0.5]),
    "ARMAX": (ARMAX(2, 2, 1, 1), [-1.2, 0.5, 0.5, 0.3, 0.4]),
    "BJ": (BJ(2, 1, 1, 2, 1), [0.5, 0.3, 0.4, -0.6, -1.2, 0.5]),
}


def gen(seed):
    return torch.Generator().manual_seed(seed)


@pytest.mark.parametrize("name", list(TRUE))
def test_noise_free_data_gives_true_parameters(name):
    """Every structure recovers its parameters to 1e-10 from noise-free data.

    For ARMAX and BJ only the dynamics (A, B / B, F) are determined: with e = 0 the prediction
    error (A y - B u)/C vanishes for every C (and D), so the noise model is not identifiable
    from noise-free data; it is checked on noisy data in test_armax_bj_noise_models.
    """
    model, th = TRUE[name]
    th = torch.tensor(th, dtype=DT)
    u = input_signal("white", 300, generator=gen(1))
    data = simulate_data(model, u, theta=th)
    res = fit(model, data)
    names = model.parameter_names()
    det = [j for j, n in enumerate(names) if n[0] in "abf"]
    assert (res.theta[det] - th[det]).abs().max() < 1e-10
    if name not in ("FIR", "ARX"):  # Gauss-Newton from a perturbed start: quadratic convergence
        start = th + 0.05 * torch.randn(len(th), generator=gen(2), dtype=DT)
        res2 = fit(model, data, method="gauss_newton", init=start)
        assert (res2.theta[det] - th[det]).abs().max() < 1e-10
        assert bool(res2.converged)


def test_fir_lls_matches_statsmodels_ols():
    model, th = TRUE["FIR"]
    u = input_signal("white", 200, generator=gen(3))
    data = simulate_data(model, u, theta=torch.tensor(th), noise_std=0.1, generator=gen(4))
    res = fit(model, data)
    Phi, target = model.regression(data)
    ref = sm.OLS(target.numpy(), Phi.numpy()).fit()
    np.testing.assert_allclose(res.theta.numpy(), ref.params, rtol=1e-10)
    np.testing.assert_allclose(res.standard_errors.numpy(), ref.bse, rtol=1e-10)
    np.testing.assert_allclose(res.sigma2.item(), ref.scale, rtol=1e-10)
    text = res.summary()
    assert "b1" in text and f"{ref.params[0]:.4g}" in text and f"{ref.bse[0]:.4g}" in text
    # every coefficient row splits into its seven columns (they used to run together)
    rows = [line.split() for line in text.splitlines() if line.split()[:1] == ["b1"]]
    assert len(rows) == 1 and len(rows[0]) == 7
    coef, se, z, p, lo, hi = (float(v) for v in rows[0][1:])
    np.testing.assert_allclose(
        [coef, se, z], [ref.params[0], ref.bse[0], ref.tvalues[0]], rtol=1e-3
    )
    assert abs(z) > 10 and lo < coef < hi


def test_oe_gauss_newton_monte_carlo_coverage():
    """200 noisy data sets in one batched call: truth within 3 SE in >= 90% (notes §4.6.2)."""
    model, th = TRUE["OE"]
    th = torch.tensor(th, dtype=DT)
    u = input_signal("white", 300, (200,), generator=gen(5))
    data = simulate_data(model, u, theta=th, noise_std=0.3, generator=gen(6))
    res = fit(model, data)
    assert res.theta.shape == (200, 4)
    assert res.converged.float().mean() >= 0.99
    assert bool(res.model.is_stable().all())
    s = summarize_estimates(res.theta, th, standard_errors=res.standard_errors, k=3.0)
    assert s.coverage >= 0.90
    # the asymptotic covariance sigma^2 (J'J)^{-1} is calibrated: z-scores have unit spread
    z = (res.theta - th) / res.standard_errors
    assert ((z.std(0) > 0.8) & (z.std(0) < 1.25)).all()
    # the Gauss-Newton loss decreased monotonically per data set
    h = res.loss_history
    assert (h[1:] <= h[:-1] + 1e-12).all()


def test_input_and_noise_signal_arguments_are_checked():
    """Non-integer or zero sizes, integer dtypes, negative std and a contamination outside
    [0, 1] are refused by name; numpy integer sizes are integers."""
    assert input_signal("prbs", np.int64(7), n_inputs=2, seed=0).shape == (7, 2)
    for kwargs, word in [
        (dict(N=10.5), "N must be an integer"),
        (dict(N=10, n_inputs=0), "n_inputs must be an integer >= 1"),
        (dict(N=10, dtype=torch.int64), "floating"),
    ]:
        with pytest.raises(InputValidationError, match=word):
            input_signal("white", seed=0, **kwargs)
    with pytest.raises(InputValidationError, match="std must be"):
        noise_signal((5,), std=-1.0, seed=0)
    with pytest.raises(InputValidationError, match=r"\[0, 1\]"):
        noise_signal((5,), "contaminated", contamination=1.5, seed=0)


def test_summarize_estimates_checks_shapes_and_takes_numpy():
    """Mismatched truth, standard errors or covariance are named; numpy arrays give the
    statistics of the same tensors."""
    est = np.array([[1.0, 2.0], [3.0, 1.0], [2.0, 4.0], [0.0, 1.0]])
    s = summarize_estimates(est, np.zeros(2), np.eye(2), standard_errors=np.ones(2), k=2.5)
    ref = summarize_estimates(torch.tensor(est), torch.zeros(2, dtype=DT), torch.eye(2, dtype=DT))
    torch.testing.assert_close(s.covariance, ref.covariance)
    torch.testing.assert_close(s.std, torch.tensor(est).std(0))
    assert float(s.coverage) == 0.5  # rows within 2.5 of 0 in every parameter: 1st and 4th
    with pytest.raises(InputValidationError, match=r"truth .*\(2,\).*got \(3,\)"):
        summarize_estimates(est, np.zeros(3))
    with pytest.raises(InputValidationError, match=r"standard_errors .*\(4, 2\).*\(5, 2\)"):
        summarize_estimates(est, np.zeros(2), standard_errors=np.ones((5, 2)))
    with pytest.raises(InputValidationError, match=r"predicted_covariance .*got \(3, 3\)"):
        summarize_estimates(est, np.zeros(2), predicted_covariance=np.eye(3))


def test_arx_biased_on_output_noise_oe_and_iv_are_not():
    """White output noise: ARX least squares is biased (coloured equation error A e)."""
    oe, th_oe = TRUE["OE"]
    th_oe = torch.tensor(th_oe, dtype=DT)
    u = input_signal("white", 400, (100,), generator=gen(7))
    data = simulate_data(oe, u, theta=th_oe, noise_std=0.3, generator=gen(8))
    th_arx = torch.tensor([-1.2, 0.5, 0.5, 0.3], dtype=DT)  # same system, ARX parameter order
    r_ls = fit(ARX(2, 2, 1), data)
    r_iv = fit(ARX(2, 2, 1), data, method="iv")
    r_oe = fit(oe, data)
    s_ls = summarize_estimates(r_ls.theta, th_arx)
    s_iv = summarize_estimates(r_iv.theta, th_arx)
    s_oe = summarize_estimates(r_oe.theta, th_oe)
    assert (s_ls.bias.abs() / s_ls.bias_standard_error).max() > 20  # significantly biased
    assert (s_iv.bias.abs() / s_iv.bias_standard_error).max() < 4
    assert (s_oe.bias.abs() / s_oe.bias_standard_error).max() < 4
    assert s_oe.mse < s_iv.mse < s_ls.mse


def test_armax_bj_noise_models():
    """With coloured noise the noise-model parameters are recovered (truth within 3 SE)."""
    for name in ("ARMAX", "BJ"):
        model, th = TRUE[name]
        th = torch.tensor(th, dtype=DT)
        u = input_signal("white", 500, (40,), generator=gen(9))
        data = simulate_data(model, u, theta=th, noise_std=0.2, noise="model", generator=gen(10))
        res = fit(model, data)
        s = summarize_estimates(res.theta, th, standard_errors=res.standard_errors)
        assert s.coverage >= 0.85, name
        assert (s.bias.abs() < 4 * s.std / 40**0.5 + 1e-3).all(), name


def test_fair_and_laplace_mle_beat_least_squares_on_fat_tails():
    """Student-t (2 dof) noise: eq. 4.73 (fair) and LAD have far smaller parameter MSE."""
    model, th = TRUE["FIR"]
    th = torch.tensor(th, dtype=DT)
    u = input_signal("white", 200, (60,), generator=gen(11))
    data = simulate_data(
        model, u, theta=th, noise_std=0.3, noise_kind="student_t", df=2, generator=gen(12)
    )
    mse = {
        loss: ((fit(model, data, method="mle", loss=loss).theta - th) ** 2).sum(-1).mean()
        for loss in ("gaussian", "fair", "laplace")
    }
    assert mse["fair"] < 0.5 * mse["gaussian"]
    assert mse["laplace"] < 0.5 * mse["gaussian"]


def test_fair_loss_optimality_and_laplace_matches_linear_program():
    model, th = TRUE["FIR"]
    u = input_signal("white", 80, (3,), generator=gen(13))
    data = simulate_data(
        model, u, theta=torch.tensor(th), noise_std=0.3, noise_kind="laplace", generator=gen(14)
    )
    Phi, target = model.regression(data)
    # fair loss (4.73) with alpha = 2: the gradient of sum r^2 / (1 + alpha|r|) vanishes
    res = fit(model, data, method="mle", loss="fair", alpha=2.0)
    theta = res.theta.clone().requires_grad_(True)
    r = target - (Phi @ theta.unsqueeze(-1)).squeeze(-1)
    (grad,) = torch.autograd.grad((r**2 / (1 + 2.0 * r.abs())).sum(), theta)
    assert grad.abs().max() < 1e-8
    # Laplace: exact least-absolute-deviations solution by a linear program
    lad = fit(model, data, method="mle", loss="laplace")
    for b in range(3):
        A, y = Phi[b].numpy(), target[b].numpy()
        M, p = A.shape
        lp = scipy.optimize.linprog(
            np.r_[np.zeros(p), np.ones(2 * M)],
            A_eq=np.hstack([A, np.eye(M), -np.eye(M)]),
            b_eq=y,
            bounds=[(None, None)] * p + [(0, None)] * (2 * M),
            method="highs",
        )
        np.testing.assert_allclose(lad.theta[b].numpy(), lp.x[:p], atol=2e-3)
        assert np.abs(y - A @ lad.theta[b].numpy()).sum() <= lp.fun * (1 + 1e-4)


def test_weighted_gaussian_mle_is_wls_eq_4_64():
    """Known per-sample variances: MLE = least squares weighted by 1/sigma_k^2 (eq. 4.64)."""
    model, th = TRUE["ARX"]
    th = torch.tensor(th, dtype=DT)
    N, T = 300, 300
    u = input_signal("white", N, (T,), generator=gen(15))
    sig = 0.05 + 0.5 * (torch.arange(N, dtype=DT) % 10 == 0)  # every 10th sample is noisy
    e = sig * torch.randn(T, N, generator=gen(16), dtype=DT)
    # equation error A y = B u + e (eq. 4.117): y = B/A u + e/A
    y = model.simulate(u, theta=th) + iir_filter(torch.ones(1, dtype=DT), th[:2], e).unsqueeze(-1)
    data = IOData(u, y)
    w = (1 / sig**2).expand(T, N)
    res = fit(model, data, method="mle", weights=w)
    ols = fit(model, data)
    # independent solver: numpy lstsq on the row-scaled regression (rows start at max lag 2)
    Phi, target = model.regression(data)
    sw = w[:, 2:].sqrt()
    for b in range(3):
        ref = np.linalg.lstsq(
            (Phi[b] * sw[b, :, None]).numpy(), (target[b] * sw[b]).numpy(), rcond=None
        )[0]
        np.testing.assert_allclose(res.theta[b].numpy(), ref, rtol=1e-9)
    mse_w = ((res.theta - th) ** 2).sum(-1).mean()
    mse_ols = ((ols.theta - th) ** 2).sum(-1).mean()
    assert mse_w < 0.5 * mse_ols
    # weighted covariance (A'WA)^{-1} sigma2_hat is calibrated (sigma2_hat ~ 1 here)
    z = (res.theta - th) / res.standard_errors
    assert ((z.std(0) > 0.85) & (z.std(0) < 1.15)).all()
    assert abs(res.sigma2.mean().item() - 1) < 0.05


def test_jacobian_matches_finite_differences():
    model, th = TRUE["BJ"]
    th = torch.tensor(th, dtype=DT)
    u = input_signal("white", 60, (2,), generator=gen(17))
    data = simulate_data(model, u, theta=th, noise_std=0.1, noise="model", generator=gen(18))

    def res_fn(t):
        return model.prediction_errors(data, theta=t)[..., 0]

    theta = th.expand(2, -1).clone() + 0.01
    r, J = batch_jacobian(res_fn, theta, strategy="forward")
    h = 1e-6
    for j in range(len(th)):
        dt = torch.zeros_like(theta)
        dt[:, j] = h
        fd = (res_fn(theta + dt) - res_fn(theta - dt)) / (2 * h)
        torch.testing.assert_close(J[..., j], fd, rtol=1e-6, atol=1e-8)


def test_output_error_jacobian_by_filtering_matches_finite_differences_and_autograd():
    """The OE Jacobian built from the filtered signals u/F and (B/F u)/F (no autograd) equals
    central finite differences of the simulation errors and the forward-mode autograd
    Jacobian: two inputs with different orders and delays, a batch, two experiments and
    per-sample weights."""
    model = OE([2, 3], [2, 1], [1, 0], n_inputs=2, batch_shape=(2,))
    th = torch.tensor(
        [[0.5, 0.3, 0.2, -0.1, 0.4, -1.2, 0.5, -0.6], [0.4, 0.2, 0.3, 0.1, -0.2, -1.0, 0.4, -0.5]],
        dtype=DT,
    )
    g = gen(31)
    parts = [
        IOData(
            torch.randn(2, n, 2, generator=g, dtype=DT), torch.randn(2, n, 1, generator=g, dtype=DT)
        )
        for n in (40, 25)
    ]
    data = IOData.experiments(parts)
    sw = torch.rand(2, data.N, generator=g, dtype=DT) + 0.5

    def res_fn(t):
        return model.simulation_errors(data, theta=t)[..., 0] * sw

    problem = _OutputError(model, data, sw)
    torch.testing.assert_close(problem.residuals(th), res_fn(th), rtol=0, atol=0)
    r, J = problem.linearise(th)  # reuses the responses of the residuals just computed
    torch.testing.assert_close(r, res_fn(th), rtol=0, atol=0)
    r2, J2 = _OutputError(model, data, sw).linearise(th + 0)  # computed afresh
    torch.testing.assert_close((r2, J2), (r, J), rtol=0, atol=0)
    r_ad, J_ad = batch_jacobian(res_fn, th, strategy="forward")
    torch.testing.assert_close(J, J_ad, rtol=1e-10, atol=1e-12)
    h = 1e-6
    for j in range(th.shape[-1]):  # loop over parameters (finite differences)
        dt = torch.zeros_like(th)
        dt[:, j] = h
        fd = (res_fn(th + dt) - res_fn(th - dt)) / (2 * h)
        torch.testing.assert_close(J[..., j], fd, rtol=1e-6, atol=1e-8)


def test_oe_fit_with_filtered_jacobian_equals_autograd_jacobian_fit():
    """``fit`` uses the filtered OE Jacobian; the same Levenberg-Marquardt run with the
    autograd Jacobian reaches the same estimate, and both match scipy's least_squares."""
    model, th = TRUE["OE"]
    u = input_signal("white", 400, generator=gen(32))
    data = simulate_data(model, u, theta=torch.tensor(th), noise_std=0.2, generator=gen(33))
    res = fit(OE(2, 2, 1), data)
    theta0 = res.info["initial_theta"]
    oe = OE(2, 2, 1)

    def residual_fn(t):
        return oe.simulation_errors(data, theta=t)[..., 0]

    def stable(t):
        return (
            torch.linalg.eigvals(
                torch.stack([-t[..., 2:], torch.eye(2, dtype=DT)[0].expand_as(t[..., 2:])], -2)
            )
            .abs()
            .amax(-1)
            < 1
        )

    lm = minimize(
        residual_fn,
        theta0,
        method="levenberg_marquardt",
        jacobian=lambda t: batch_jacobian(residual_fn, t, strategy="forward"),
        admissible=stable,
        xtol=1e-8,
    )
    torch.testing.assert_close(res.theta, lm.theta, rtol=1e-7, atol=1e-9)
    un, yn = data.u[:, 0].numpy(), data.y[:, 0].numpy()
    ref = scipy.optimize.least_squares(
        lambda t: yn - scipy.signal.lfilter(np.r_[0.0, t[:2]], np.r_[1.0, t[2:]], un),
        theta0.numpy(),
        xtol=1e-12,
        ftol=1e-12,
    )
    np.testing.assert_allclose(res.theta.numpy(), ref.x, rtol=1e-6, atol=1e-7)


def test_batched_fit_equals_individual_fits():
    model, th = TRUE["OE"]
    u = input_signal("prbs", 200, (3,), generator=gen(19))
    data = simulate_data(model, u, theta=torch.tensor(th), noise_std=0.2, generator=gen(20))
    batched = fit(OE(2, 2, 1), data)
    assert batched.model.batch_shape == (3,)
    for b in range(3):
        single = fit(OE(2, 2, 1), IOData(data.u[b], data.y[b]))
        torch.testing.assert_close(single.theta, batched.theta[b], rtol=1e-7, atol=1e-9)


def _compaction_case(name):
    """A batch of data sets whose fits need different iteration counts: weighted OE on a
    (2, 3) batch with one unstable plant (its estimate stops at the stability boundary),
    BJ on a (2, 3) batch, ARMAX with the Huber loss (a threshold per data set) on a (4,)
    batch."""
    g = gen(60)
    if name == "OE":
        th = torch.tensor([0.5, 0.3, -1.2, 0.5], dtype=DT).expand(2, 3, 4).clone()
        th[1, 0] = torch.tensor([0.5, 0.3, -2.1, 1.2], dtype=DT)
        th[0, 2, 2:] = torch.tensor([-1.6, 0.8], dtype=DT)
        u = input_signal("white", 200, (2, 3), generator=g)
        data = simulate_data(
            OE(2, 2, 1, batch_shape=(2, 3)), u, theta=th, noise_std=0.1, generator=g
        )
        weights = 0.5 + torch.rand(2, 3, 200, generator=g, dtype=DT)
        return OE(2, 2, 1), data, {"weights": weights}
    model, th = TRUE[name]
    batch = (2, 3) if name == "BJ" else (4,)
    u = input_signal("white", 200, batch, generator=g)
    data = simulate_data(
        model, u, theta=torch.tensor(th), noise_std=0.3, noise="model", generator=g
    )
    if name == "BJ":
        return BJ(2, 1, 1, 2, 1), data, {}
    return ARMAX(2, 2, 1, 1), data, {"loss": "huber", "method": "mle"}


def _uncompacted_minimize(minimize_fn, *args, **kwargs):
    """:func:`integrators.newton.minimize` with ``compact=False`` (every member evaluated)."""
    return minimize_fn(*args, **{**kwargs, "compact": False})


@pytest.mark.parametrize("name", ["OE", "BJ", "ARMAX"])
def test_compacted_batched_fit_equals_the_uncompacted_one_and_single_fits(name, monkeypatch):
    """The prediction-error iteration evaluates only the data sets still iterating
    (minimize(compact=True)); estimate, covariance, loss history, iteration counts and
    convergence flags are those of the uncompacted batch and of each data set fitted alone
    from the same start, with a non-converging member (OE, an unstable plant), two batch
    dimensions (OE, BJ) and a per-data-set loss scale (ARMAX, Huber)."""

    def same(a, b):
        for x, y in [
            (a.theta, b.theta),
            (a.covariance, b.covariance),
            (a.sigma2, b.sigma2),
            (a.loss_history, b.loss_history),
            (a.info["damping"], b.info["damping"]),
        ]:
            torch.testing.assert_close(x, y, rtol=1e-12, atol=1e-14)
        assert torch.equal(a.iterations, b.iterations)
        assert torch.equal(a.converged, b.converged)

    model, data, kw = _compaction_case(name)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        compacted = fit(model, data, **kw)
        with monkeypatch.context() as m:
            m.setattr(pe, "minimize", functools.partial(_uncompacted_minimize, pe.minimize))
            full = fit(model, data, **kw)
        same(compacted, full)
        iterations = compacted.iterations.flatten()
        assert int(iterations.max()) > int(iterations.min()) + 2
        if name == "OE":
            assert not bool(compacted.converged[1, 0]) and int(compacted.converged.sum()) == 5
        for index in np.ndindex(*data.batch_shape):
            start = compacted.info["initial_theta"][index]  # batched ARX/IV: not bitwise
            own = {k: v[index] if isinstance(v, torch.Tensor) else v for k, v in kw.items()}
            single = fit(model, data[index], init=start, **own)
            torch.testing.assert_close(single.theta, compacted.theta[index], rtol=1e-12, atol=1e-14)
            torch.testing.assert_close(
                single.covariance, compacted.covariance[index], rtol=1e-10, atol=1e-16
            )
            torch.testing.assert_close(
                single.loss_history[-1], compacted.loss_history[-1][index], rtol=1e-12, atol=0
            )
            assert torch.equal(single.iterations, compacted.iterations[index])
            assert torch.equal(single.converged, compacted.converged[index])


def test_float32_fit():
    model = FIR(3, 1, dtype=torch.float32)
    th = torch.tensor([0.5, -0.3, 0.2])
    u = input_signal("white", 200, generator=gen(21), dtype=torch.float32)
    data = simulate_data(model, u, theta=th)
    res = fit(model, data)
    assert res.theta.dtype == torch.float32
    torch.testing.assert_close(res.theta, th, rtol=1e-5, atol=1e-5)
    # Gauss-Newton in float32: tolerances adapt to eps, every data set converges
    oe = OE(2, 2, 1, dtype=torch.float32)
    th_oe = torch.tensor([0.5, 0.3, -1.2, 0.5])
    u = input_signal("white", 300, (10,), generator=gen(24), dtype=torch.float32)
    data = simulate_data(oe, u, theta=th_oe, noise_std=0.1, generator=gen(25))
    res = fit(oe, data)
    assert res.theta.dtype == torch.float32 and bool(res.converged.all())
    assert ((res.theta - th_oe).abs() < 4 * res.standard_errors).all()


def test_simulate_data_runs_in_the_model_dtype():
    """float32 u with a float64 model: the float64 simulation of the (exactly widened) u, noise
    included; a float32 model with float64 u gives the float64 answer to float32 rounding."""
    th = torch.tensor([0.5, 0.3, -1.2, 0.5], dtype=DT)
    u32 = input_signal("white", 100, (2,), generator=gen(27), dtype=torch.float32)
    d32 = simulate_data(OE(2, 2, 1), u32, theta=th, noise_std=0.1, seed=3)
    d64 = simulate_data(OE(2, 2, 1), u32.double(), theta=th, noise_std=0.1, seed=3)
    assert d32.dtype == torch.float64
    torch.testing.assert_close(d32.u, d64.u, rtol=0, atol=0)
    torch.testing.assert_close(d32.y, d64.y, rtol=0, atol=0)
    low = simulate_data(OE(2, 2, 1, dtype=torch.float32), u32.double(), theta=th)
    exact = OE(2, 2, 1).simulate(u32.double(), theta=th)
    torch.testing.assert_close(low.y, exact, rtol=1e-5, atol=1e-5)
    assert (low.y.float().double() == low.y).all()  # computed in float32


def test_initial_estimate_of_a_model_with_a_and_f_is_the_models_values():
    """The documented exception to the data-based start: a model with both A and F starts
    from its current parameters, broadcast over the data's batch; OE starts from data."""
    from sysid.estimation.initial import _initial_estimate
    from sysid.models import PolynomialModel

    u = input_signal("white", 80, (2,), generator=gen(28))
    th = torch.tensor([0.5, 0.3, -1.2, 0.5], dtype=DT)
    data = simulate_data(OE(2, 2, 1), u, theta=th)
    general = PolynomialModel(na=1, nb=2, nf=1)
    general.set_parameter_vector(torch.tensor([-0.3, 1.0, 0.2, 0.1], dtype=DT))
    start = _initial_estimate(general, data)
    torch.testing.assert_close(start, general.parameter_vector().detach().expand(2, 4))
    assert _initial_estimate(OE(2, 2, 1), data).abs().min() > 0


def test_invalid_requests():
    u = input_signal("white", 50, generator=gen(22))
    data = simulate_data(FIR(2, 1), u, theta=torch.tensor([1.0, 0.5]))
    with pytest.raises(InputValidationError, match="linear in its parameters"):
        fit(OE(1, 1, 1), data, method="lls")
    with pytest.raises(InputValidationError, match="mle"):
        fit(FIR(2, 1), data, method="lls", loss="fair")
    with pytest.raises(InputValidationError, match="method"):
        fit(FIR(2, 1), data, method="newton")
    # 6 samples: the automatic start of OE(2, 2, 1) is named as what cannot be formed
    with pytest.raises(InputValidationError, match="automatic starting estimate of OE"):
        fit(OE(2, 2, 1), IOData(data.u[:6], data.y[:6]))


@pytest.mark.parametrize("method", ["lls", "iv"])
def test_simulation_criterion_with_a_direct_solve_is_refused(method):
    """lls and iv minimise one-step prediction errors; with criterion="simulation" they
    returned that estimate as if it minimised the free-run errors. gauss_newton on the
    same data minimises the simulation errors: its criterion is below the lls estimate's."""
    u = input_signal("white", 200, generator=gen(29))
    theta = torch.tensor(TRUE["ARX"][1], dtype=DT)
    data = simulate_data(ARX(2, 2, 1), u, noise_std=0.3, theta=theta)
    data = IOData(data.u, data.y + 0.5 * torch.randn(200, 1, generator=gen(30), dtype=DT))
    with pytest.raises(InputValidationError, match="criterion='simulation'.*gauss_newton"):
        fit(ARX(2, 2, 1), data, method=method, criterion="simulation")
    sim = fit(ARX(2, 2, 1), data, method="gauss_newton", criterion="simulation")
    lls = fit(ARX(2, 2, 1), data, method="lls")
    errors = [r.model.simulation_errors(data).pow(2).sum() for r in (sim, lls)]
    assert errors[0] < errors[1]


@pytest.mark.parametrize("init", ["foo", "automatic", {"a1": 0.1}, object()])
@pytest.mark.parametrize("structure", ["ARX", "OE"])
def test_an_init_of_no_accepted_form_is_refused(structure, init):
    """init="foo" raised torch's TypeError (invalid data type 'str'); the message lists the
    accepted forms (None, 'model', a tensor); None and a (p,) tensor fit the noise-free data
    below to the true parameters (to 1e-8)."""
    model, truth = TRUE[structure]
    truth = torch.tensor(truth, dtype=DT)
    u = input_signal("white", 100, generator=gen(33))
    data = simulate_data(model, u, theta=truth)
    with pytest.raises(InputValidationError, match=r"init must be None .*'model'.*\(p,\)"):
        fit(model, data, method="gauss_newton", init=init)
    start = truth + 0.05
    for good in (None, start):
        est = fit(model, data, method="gauss_newton", init=good).theta
        torch.testing.assert_close(est, truth, rtol=0, atol=1e-8)


def test_uniform_noise_polytope_eq_4_58():
    """The MLE set for uniform noise contains the truth; LP bounds match a grid search."""
    g = gen(23)
    M, a = 30, 0.2
    A = torch.randn(M, 2, generator=g, dtype=DT)
    th = torch.tensor([0.7, -0.4], dtype=DT)
    y = A @ th + a * (2 * torch.rand(M, generator=g, dtype=DT) - 1)
    s = uniform_noise_mle_set(A, y, a)
    assert bool(s.feasible) and bool(s.contains(th))
    assert bool(s.contains(s.center)) and s.radius > 0
    # brute force: grid over a box around the truth
    n = 801
    g0 = torch.linspace(th[0] - 0.3, th[0] + 0.3, n, dtype=DT)
    g1 = torch.linspace(th[1] - 0.3, th[1] + 0.3, n, dtype=DT)
    T0, T1 = torch.meshgrid(g0, g1, indexing="ij")
    pts = torch.stack([T0.reshape(-1), T1.reshape(-1)], -1)
    inside = ((y - pts @ A.T).abs() <= a).all(-1)
    feas = pts[inside]
    step = 0.6 / (n - 1)
    assert (feas.min(0).values - s.lower).abs().max() < 2 * step
    assert (feas.max(0).values - s.upper).abs().max() < 2 * step
    assert (s.lower > th - 0.3).all() and (s.upper < th + 0.3).all()  # grid box was enough
    # an infeasible problem is reported as such (batched)
    y_bad = torch.stack([y, y + 10 * (torch.arange(M) % 2) - 5])
    s2 = uniform_noise_mle_set(A, y_bad, a)
    assert s2.feasible.tolist() == [True, False]


def test_uniform_noise_set_bad_inputs_are_named():
    """A 0-d tensor bound is a number; unbroadcastable batches and NaN data are refused."""
    A = torch.randn(6, 2, generator=gen(26), dtype=DT)
    y = A @ torch.tensor([0.5, -1.0], dtype=DT)
    s = uniform_noise_mle_set(A, y, torch.tensor(0.1, dtype=DT))
    assert s.a == 0.1 and bool(s.feasible)
    with pytest.raises(InputValidationError, match=r"\(3, 6, 2\).*\(2, 6\).*do not broadcast"):
        uniform_noise_mle_set(A.expand(3, 6, 2), y.expand(2, 6), 0.1)
    y_nan = y.clone()
    y_nan[1] = math.nan
    with pytest.raises(InputValidationError, match="finite"):
        uniform_noise_mle_set(A, y_nan, 0.1)
    with pytest.raises(InputValidationError, match="a number"):
        uniform_noise_mle_set(A, y, torch.tensor([0.1, 0.2]))


def test_uniform_noise_set_scales_with_the_data_in_any_units():
    """S(A, c y, c a) = c S(A, y, a) and S(A / c, y, a) = c S(A, y, a) exactly (eq. 4.58 is
    homogeneous), so the bounds at c = 1e-8 .. 1e6 equal scipy HiGHS' bounds of the unit
    problem; an empty set stays empty in small units, the centre stays inside, a residual of
    50 a is outside for a = 1e-11, and integer regressors give the float regressors' set."""
    g = gen(31)
    A = torch.randn(30, 3, generator=g, dtype=DT)
    y = A @ torch.tensor([1.0, -2.0, 0.5], dtype=DT) + 0.3 * (
        2 * torch.rand(30, generator=g, dtype=DT) - 1
    )
    G = torch.cat([A, -A]).numpy()
    h = torch.cat([y + 0.3, 0.3 - y]).numpy()
    bound = [
        scipy.optimize.linprog(sign * np.eye(3)[j], A_ub=G, b_ub=h, bounds=[(None, None)] * 3).x[j]
        for sign in (1.0, -1.0)
        for j in range(3)
    ]
    truth = torch.tensor(bound, dtype=DT).reshape(2, 3)
    for c in (1e-8, 1e-6, 1e6):
        for scaled in (
            uniform_noise_mle_set(A, c * y, c * 0.3),
            uniform_noise_mle_set(A / c, y, 0.3),
        ):
            assert bool(scaled.solved) and scaled.message == ""
            np.testing.assert_allclose(
                torch.stack([scaled.lower, scaled.upper]) / c, truth, rtol=1e-9
            )
            assert bool(scaled.contains(scaled.center)) and scaled.radius > 0
        outlier = c * y.clone()
        outlier[0] += c * 1.5
        assert not bool(uniform_noise_mle_set(A, outlier, c * 0.3).feasible)
    tiny = uniform_noise_mle_set(torch.ones(2, 1, dtype=DT), torch.zeros(2, dtype=DT), 1e-11)
    assert not bool(tiny.contains(torch.tensor([5e-10], dtype=DT)))
    assert bool(tiny.contains(torch.tensor([1e-11], dtype=DT)))
    integer = uniform_noise_mle_set(
        torch.tensor([[1, 0], [0, 1], [1, 1]]), torch.tensor([1, 2, 2]), 0.5
    )
    real = uniform_noise_mle_set(
        torch.tensor([[1.0, 0], [0, 1], [1, 1]], dtype=DT), torch.tensor([1.0, 2, 2], dtype=DT), 0.5
    )
    assert integer.lower.dtype == DT
    torch.testing.assert_close(integer.lower, real.lower)
    torch.testing.assert_close(integer.center, real.center)


def test_uniform_noise_set_names_a_data_set_whose_programs_fail(monkeypatch):
    """A linear program that ends without an answer (HiGHS status 4, numerical difficulties)
    makes its data set nan with solved False, named in the message and a ConvergenceWarning;
    the other data sets keep their answers."""
    from sysid.estimation import uniform_noise

    solve = uniform_noise._linprog
    calls = []

    def failing_second_set(c, G, h, bounds):
        calls.append(None)
        result = solve(c, G, h, bounds)
        if len(calls) > 7:  # the 7 programs of data set 0 (centre + 2 x 3 bounds) pass
            result.status, result.x, result.message = 4, None, "numerical difficulties"
        return result

    monkeypatch.setattr(uniform_noise, "_linprog", failing_second_set)
    A = torch.randn(20, 3, generator=gen(32), dtype=DT)
    y = torch.stack([A @ torch.ones(3, dtype=DT)] * 2)
    with pytest.warns(ConvergenceWarning, match=r"data sets \[1\].*numerical difficulties"):
        s = uniform_noise_mle_set(A, y, 0.1)
    assert s.solved.tolist() == [True, False] and "data sets [1]" in s.message
    assert bool(torch.isfinite(s.lower[0]).all()) and bool(torch.isnan(s.lower[1]).all())
    assert bool(torch.isnan(s.center[1]).all()) and bool(torch.isnan(s.radius[1]))


def _unstable_batch():
    """Three OE data sets; the middle one from an unstable plant (F roots of modulus sqrt(1.2))."""
    th = torch.tensor([[0.5, 0.3, -1.2, 0.5], [0.5, 0.3, -2.1, 1.2], [0.5, 0.3, -1.2, 0.5]])
    u = input_signal("white", 200, (3,), generator=gen(40))
    model = OE(2, 2, 1, batch_shape=(3,))
    return simulate_data(model, u, theta=th.double(), noise_std=0.1, generator=gen(41))


def test_oe_on_unstable_plant_is_reported_not_converged():
    """OE cannot simulate an unstable plant: the estimate stops on the stability boundary.

    It used to report converged=True (fit ~ -1 %) silently. The criterion is not stationary
    there: a Gauss-Newton step would move the estimate by several standard errors.
    """
    import warnings

    from sysid.errors import ConvergenceWarning

    data = _unstable_batch()
    with pytest.warns(
        ConvergenceWarning, match=r"batch index \(1,\).*leave the stable models"
    ) as rec:
        res = fit(OE(2, 2, 1), data)
    assert "1 of 3 data sets did not converge" in str(rec[0].message)
    assert res.converged.tolist() == [True, False, True]
    assert res.info["step_in_standard_errors"][1] > 1
    assert (res.info["step_in_standard_errors"][[0, 2]] < 1e-3).all()
    assert len(res.messages) == 1 and res.messages[0].startswith("batch index (1,)")
    assert res.stable.tolist() == [True, True, True]  # the steps keep it stable
    assert bool(res.info["stationary_point_unstable"][1])
    with warnings.catch_warnings():  # the stable data sets alone: no warning
        warnings.simplefilter("error")
        fit(OE(2, 2, 1), data[[0, 2]])


def test_arx_on_unstable_plant_warns_unstable_model():
    """Least squares identifies the unstable plant (consistent for ARX data): the estimate is
    flagged unstable (its simulation diverges) with the true pole modulus 1.5 (closed form
    roots of z^2 - 2.3 z + 1.2 = (z - 1.5)(z - 0.8))."""
    from sysid.errors import PoorExcitationWarning, UnstableModelWarning

    th = torch.tensor([[-1.2, 0.5, 0.5, 0.3], [-2.3, 1.2, 0.5, 0.3]], dtype=DT)
    u = input_signal("white", 60, (2,), generator=gen(42))
    data = simulate_data(
        ARX(2, 2, 1, batch_shape=(2,)),
        u,
        theta=th,
        noise_std=0.01,
        noise="model",
        generator=gen(43),
    )
    with (
        pytest.warns(UnstableModelWarning, match=r"batch index \(1,\).*unstable"),
        # the diverging output (1.5^k) makes member 1's regressors badly scaled
        pytest.warns(PoorExcitationWarning, match=r"ill-conditioned.*batch index \(1,\)"),
    ):
        res = fit(ARX(2, 2, 1), data)
    assert res.stable.tolist() == [True, False] and res.converged.all()
    assert abs(float(res.info["max_pole_modulus"][1]) - 1.5) < 0.05


def test_iteration_limit_is_reported():
    from sysid.errors import ConvergenceWarning

    model, th = TRUE["BJ"]
    u = input_signal("white", 300, generator=gen(44))
    data = simulate_data(
        model, u, theta=torch.tensor(th), noise_std=0.3, noise="model", generator=gen(45)
    )
    with pytest.warns(ConvergenceWarning, match=r"iteration limit max_iter = 1"):
        res = fit(BJ(2, 1, 1, 2, 1), data, max_iter=1)
    assert not bool(res.converged)


@pytest.mark.parametrize("alpha", [0.0, -1.0, float("inf"), float("nan")])
def test_fair_loss_rejects_non_positive_or_non_finite_alpha(alpha):
    """alpha <= 0 makes the fair loss non-convex (standard errors 3-30x too small) and
    alpha = inf made the linear algebra print oneMKL errors: both are rejected."""
    model, th = TRUE["ARX"]
    u = input_signal("white", 100, generator=gen(46))
    data = simulate_data(model, u, theta=torch.tensor(th), noise_std=0.1, generator=gen(47))
    with pytest.raises(
        InputValidationError, match=r"alpha of the fair loss must be finite and > 0"
    ):
        fit(ARX(2, 2, 1), data, loss="fair", alpha=alpha)


def test_output_error_without_denominator_has_finite_standard_errors():
    """A general model with B only (nf = 0) fitted by Gauss-Newton on the output error: its
    Jacobian columns are the delayed inputs (they were zero, giving inf standard errors).
    Truth: the FIR least-squares estimate and standard errors (same model; the Gauss-Newton
    criterion has the nb extra start-up rows)."""
    from sysid.models import PolynomialModel

    model, th = TRUE["FIR"]
    u = input_signal("white", 400, generator=gen(48))
    data = simulate_data(model, u, theta=torch.tensor(th), noise_std=0.1, generator=gen(49))
    ref = fit(FIR(4, 1), data)
    res = fit(PolynomialModel(nb=4, nk=1), data, method="gauss_newton")
    torch.testing.assert_close(
        res.theta, ref.theta, rtol=0, atol=0.2 * ref.standard_errors.min().item()
    )
    torch.testing.assert_close(res.standard_errors, ref.standard_errors, rtol=0.05, atol=0)


def test_init_and_weights_with_a_foreign_batch_shape_are_named():
    model, th = TRUE["OE"]
    u = input_signal("white", 100, (3,), generator=gen(50))
    data = simulate_data(model, u, theta=torch.tensor(th), noise_std=0.1, generator=gen(51))
    with pytest.raises(InputValidationError, match=r"init has shape \(2, 4\)"):
        fit(OE(2, 2, 1), data, init=torch.zeros(2, 4))
    with pytest.raises(InputValidationError, match=r"weights has shape \(5, 100\)"):
        fit(ARX(2, 2, 1), data, weights=torch.ones(5, 100))


@pytest.mark.parametrize("alpha", [0.2, None])
def test_huber_mle_matches_scipy_least_squares_huber(alpha):
    """loss="huber": the minimiser of Huber's loss with threshold c = alpha, or by default
    c = 1.345 * 1.4826 MAD of the least-squares residuals, is scipy's loss="huber"."""
    model, th = TRUE["FIR"]
    u = input_signal("white", 200, (3,), generator=gen(40))
    data = simulate_data(
        model,
        u,
        theta=torch.tensor(th),
        noise_std=0.3,
        noise_kind="student_t",
        df=2,
        generator=gen(41),
    )
    res = fit(model, data, loss="huber", alpha=alpha)
    assert res.method == "mle" and res.loss == "huber" and bool(res.converged.all())
    Phi, target = model.regression(data)
    for b in range(3):
        A, y = Phi[b].numpy(), target[b].numpy()
        c = alpha
        if alpha is None:
            r0 = y - A @ np.linalg.lstsq(A, y, rcond=None)[0]
            c = 1.345 * 1.4826 * np.median(np.abs(r0 - np.median(r0)))
        ref = scipy.optimize.least_squares(
            lambda q, A=A, y=y: y - A @ q,
            np.zeros(A.shape[1]),
            loss="huber",
            f_scale=c,
            xtol=1e-15,
            ftol=1e-15,
            gtol=1e-15,
        )
        # to a small part of a standard error (the iteration stops on a relative decrease)
        err = np.abs(res.theta[b].numpy() - ref.x) / res.standard_errors[b].numpy()
        assert err.max() < 1e-3


def test_robust_loss_history_is_the_reported_criterion():
    """An OE fit with loss="huber" runs Gaussian start iterations, then Huber ones:
    ``iterations`` counts both, ``loss_history`` holds the Huber stage (its last row is Huber's
    criterion sum rho(r) at the estimate, by hand), and the Gaussian fit's rows match its
    iterations."""
    model = OE(2, 2, 1)
    u = input_signal("white", 300, generator=gen(42))
    th = torch.tensor([0.5, 0.3, -1.2, 0.5], dtype=DT)
    data = simulate_data(
        model, u, theta=th, noise_std=0.3, noise_kind="student_t", df=2, generator=gen(43)
    )
    gauss = fit(model, data)
    assert gauss.loss_history.shape[0] == int(gauss.iterations) + 1
    res = fit(model, data, loss="huber", alpha=0.4)
    assert 2 <= res.loss_history.shape[0] <= int(res.iterations)
    r = (data.y[:, 0] - res.model.simulate(data.u)[:, 0]).detach().numpy()
    a = np.abs(r)
    huber = np.where(a <= 0.4, 0.5 * r * r, 0.4 * a - 0.5 * 0.4**2).sum()
    assert float(res.loss_history[-1]) == pytest.approx(huber, rel=1e-10)


def test_huber_sandwich_covariance_matches_monte_carlo():
    """Student-t (3 dof) noise: the sandwich E[psi^2]/E[psi']^2 (J'J)^{-1} gives the spread of
    400 Huber estimates to within 10 %, and Huber beats least squares."""
    model, th = TRUE["FIR"]
    th = torch.tensor(th, dtype=DT)
    u = input_signal("white", 200, (400,), generator=gen(42))
    data = simulate_data(
        model, u, theta=th, noise_std=0.3, noise_kind="student_t", df=3, generator=gen(43)
    )
    res = fit(model, data, loss="huber")
    ratio = res.theta.std(0) / res.standard_errors.pow(2).mean(0).sqrt()
    assert bool(((ratio > 0.9) & (ratio < 1.1)).all()), ratio
    ls = fit(model, data)
    assert ((res.theta - th) ** 2).sum(-1).mean() < 0.7 * ((ls.theta - th) ** 2).sum(-1).mean()


@pytest.mark.parametrize(("model_batch", "data_batch"), [((), ()), ((3,), (3,)), ((), (3,))])
def test_fit_never_modifies_the_input_model(model_batch, data_batch):
    """One rule: the input model keeps its parameters; result.model is a separate copy that
    holds the estimate, batched like the data."""
    model, th = TRUE["OE"]
    u = input_signal("white", 200, (3,), generator=gen(44))
    data = simulate_data(model, u, theta=torch.tensor(th), noise_std=0.1, generator=gen(45))
    if not data_batch:
        data = IOData(data.u[0], data.y[0])
    start = torch.tensor([0.4, 0.2, -1.0, 0.3], dtype=DT)
    oe = OE(2, 2, 1, batch_shape=model_batch)
    oe.set_parameter_vector(start)
    before = oe.parameter_vector().detach().clone()
    res = fit(oe, data, init="model")
    assert torch.equal(oe.parameter_vector().detach(), before)
    assert res.model is not oe
    assert res.model.batch_shape == data_batch
    torch.testing.assert_close(res.model.parameter_vector(), res.theta, rtol=0, atol=0)
    torch.testing.assert_close(res.info["initial_theta"], start.expand(*data_batch, 4))
    assert (res.theta - torch.tensor(th, dtype=DT)).abs().max() < 0.1


def test_covariance_of_a_degenerate_member_is_inf_not_a_crash():
    """A batch member whose Jacobian holds inf/NaN (an estimate that ran off to a degenerate
    model) gets an inf covariance and a PoorExcitationWarning; the others keep their exact
    (J'J)^-1."""
    from sysid.errors import PoorExcitationWarning

    g = torch.Generator().manual_seed(0)
    J = torch.randn(3, 50, 2, generator=g, dtype=torch.float64)
    J[1, 4, 0] = float("inf")
    J[2, 7, 1] = float("nan")
    with pytest.warns(PoorExcitationWarning, match="batch index \\(1,\\)"):
        P, rank = inverse_normal_matrix_and_rank(J)
    assert bool(torch.isinf(P[1:]).all()) and rank.tolist() == [2, 2, 2]
    exact = torch.linalg.inv(J[0].T @ J[0])
    assert torch.allclose(P[0], exact, rtol=1e-12)


def _numpy_arx_rows(u: np.ndarray, y: np.ndarray, na: int, nb: int, nk: int):
    """Explicit ARX/FIR regressor rows ``[-y_{t-1}..-y_{t-na}, u_{t-nk}..u_{t-nk-nb+1}]`` and
    targets ``y_t`` for ``t >= max lag`` (one experiment, 1-D signals), by plain indexing."""
    start = max(na, nk + nb - 1)
    rows = [
        [-y[t - i] for i in range(1, na + 1)] + [u[t - nk - j] for j in range(nb)]
        for t in range(start, len(y))
    ]
    return np.array(rows), y[start:]


@settings(max_examples=25, deadline=None)
@given(
    na=st.integers(0, 3),
    nb=st.integers(1, 4),
    nk=st.integers(0, 2),
    N=st.integers(16, 60),
    batch=st.integers(1, 3),
    n_exp=st.integers(1, 2),
    seed=st.integers(0, 2**31 - 1),
)
def test_lls_fit_equals_numpy_lstsq_per_data_set(na, nb, nk, N, batch, n_exp, seed):
    """The batched direct fit (normal equations from lagged products, residuals without a
    regressor matrix) equals numpy's lstsq on the explicit regressor of each data set:
    estimate, residuals, sigma^2 = r'r / (M - p) and covariance sigma^2 (Phi'Phi)^-1
    (eq. 4.101); several experiments stack their rows."""
    rng = np.random.default_rng(seed)
    parts = [(rng.standard_normal((batch, n)), rng.standard_normal((batch, n))) for n in (N, N + 5)]
    parts = parts[:n_exp]
    data = IOData.experiments(
        [IOData(torch.tensor(u).unsqueeze(-1), torch.tensor(y).unsqueeze(-1)) for u, y in parts]
    )
    model = ARX(na, nb, nk) if na else FIR(nb, nk)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # random data may give an unstable ARX estimate
        res = fit(model, data, method="lls")
    for b in range(batch):
        rows = [_numpy_arx_rows(u[b], y[b], na, nb, nk) for u, y in parts]
        Phi = np.concatenate([r[0] for r in rows])
        target = np.concatenate([r[1] for r in rows])
        theta, *_ = np.linalg.lstsq(Phi, target, rcond=None)
        r = target - Phi @ theta
        s2 = r @ r / (len(target) - Phi.shape[1])
        np.testing.assert_allclose(res.theta[b].numpy(), theta, rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(res.residuals[b].numpy(), r, rtol=0, atol=1e-11)
        np.testing.assert_allclose(res.sigma2[b].item(), s2, rtol=1e-10)
        cov = s2 * np.linalg.inv(Phi.T @ Phi)
        np.testing.assert_allclose(res.covariance[b].numpy(), cov, rtol=1e-9, atol=1e-13)


def test_normal_equations_and_residuals_equal_the_explicit_regressor():
    """``normal_equations`` (lagged products minus the edge rows) is ``Z'Z`` of the augmented
    regressor ``Z = [Phi, target]`` and ``regression_residuals`` is ``target - Phi theta``,
    for two inputs with different delays and two experiments (numpy on explicit rows)."""
    rng = np.random.default_rng(3)
    model = ARX(2, [3, 1], [0, 2], n_inputs=2)
    u1, y1 = rng.standard_normal((4, 30, 2)), rng.standard_normal((4, 30, 1))
    u2, y2 = rng.standard_normal((4, 21, 2)), rng.standard_normal((4, 21, 1))
    data = IOData.experiments(
        [IOData(torch.tensor(u1), torch.tensor(y1)), IOData(torch.tensor(u2), torch.tensor(y2))]
    )
    theta = torch.tensor(rng.standard_normal((4, 6)))
    G, M = model.normal_equations(data)
    r = model.regression_residuals(data, theta)
    for b in range(4):
        Z = []
        for u, y in ((u1, y1), (u2, y2)):
            start = 2
            for t in range(start, u.shape[1]):
                Z.append(
                    [-y[b, t - 1, 0], -y[b, t - 2, 0]]
                    + [u[b, t - j, 0] for j in range(3)]
                    + [u[b, t - 2, 1], y[b, t, 0]]
                )
        Z = np.array(Z)
        assert M == len(Z)
        np.testing.assert_allclose(G[b].numpy(), Z.T @ Z, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(
            r[b].numpy(), Z[:, -1] - Z[:, :-1] @ theta[b].numpy(), rtol=0, atol=1e-12
        )


def test_ill_conditioned_lls_fit_keeps_qr_accuracy():
    """Nearly noise-free ARX data from slowly varying inputs: the scaled condition number of
    Phi'Phi is above 1e6, where the normal equations' rounding bound eps cond exceeds 1e-10
    (solving them here misses numpy's lstsq by ~3e-8), so the fit uses QR and agrees with
    lstsq on the explicit regressor to 1e-10."""
    k = torch.arange(400, dtype=torch.float64)
    u = torch.stack([torch.sin(0.003 * k), torch.sin(0.004 * k + 1.0)]).unsqueeze(-1)
    true = torch.tensor([-1.5, 0.7, 1.0, 0.5], dtype=torch.float64)
    g = torch.Generator().manual_seed(0)
    y = ARX(2, 2, 1).simulate(u, theta=true)
    y = y + 1e-9 * torch.randn(y.shape, generator=g, dtype=torch.float64)
    with pytest.warns(PoorExcitationWarning):
        res = fit(ARX(2, 2, 1), IOData(u, y), method="lls")
    assert (res.info["scaled_condition_number"] > 1e6).all()
    for b in range(2):
        Phi, target = _numpy_arx_rows(u[b, :, 0].numpy(), y[b, :, 0].numpy(), 2, 2, 1)
        ref, *_ = np.linalg.lstsq(Phi, target, rcond=None)
        np.testing.assert_allclose(res.theta[b].numpy(), ref, rtol=1e-10)


def test_the_fitted_model_takes_the_sample_time_of_its_data():
    """A model built without ``Ts`` and fitted to data sampled at 0.1 s describes that
    sampling: its frequency response equals python-control's of the true system with
    dt = 0.1 (to the estimate's accuracy), and ``to_control`` carries dt = 0.1. A model whose
    ``Ts`` was set to another value than the data's is refused."""
    import control

    Ts = 0.1
    rng = np.random.default_rng(0)
    u = rng.standard_normal(500)
    y = scipy.signal.lfilter([0, 0.5], [1, -0.8], u) + 0.01 * rng.standard_normal(500)
    data = IOData(u, y, Ts=Ts)
    model = OE(1, 1, 1)
    result = fit(model, data)
    assert result.model.Ts == Ts and model.Ts == 1.0
    omega = np.array([1.0, 10.0])  # rad/s
    truth = control.tf([0.5], [1, -0.8], Ts)(np.exp(1j * omega * Ts))
    ours = result.model.frequency_response(torch.tensor(omega)).numpy().ravel()
    np.testing.assert_allclose(ours, truth, rtol=0.02)
    assert result.model.to_control().dt == Ts
    with pytest.raises(InputValidationError, match="Ts = 0.2 s but the data Ts = 0.1 s"):
        fit(OE(1, 1, 1, Ts=0.2), data)


def test_a_parameter_the_criterion_ignores_gets_inf_only_in_its_own_row():
    """ARMAX under the simulation criterion: C does not enter the simulated output, so its
    column of the Jacobian is zero. Its standard error is inf (with a PoorExcitationWarning),
    while A and B keep the covariance of the same fit without C: the OE model with F = A
    (same estimates and standard errors: the residual degrees of freedom count the
    parameters the residuals depend on, the rank of J)."""
    rng = np.random.default_rng(13)
    u = rng.standard_normal(400)
    y = scipy.signal.lfilter([0, 1, 0.5], [1, -1.5, 0.7], u) + 0.1 * rng.standard_normal(400)
    data = IOData(u, y)
    with pytest.warns(PoorExcitationWarning, match="does not depend on"):
        armax = fit(ARMAX(2, 2, 1, 1), data, criterion="simulation")
    oe = fit(OE(2, 2, 1), data)
    order = [2, 3, 0, 1]  # OE's (b1, b2, f1, f2) as ARMAX's (a1, a2, b1, b2)
    torch.testing.assert_close(armax.theta[:4], oe.theta[order], rtol=1e-6, atol=1e-8)
    assert math.isinf(float(armax.standard_errors[4]))
    torch.testing.assert_close(
        armax.standard_errors[:4], oe.standard_errors[order], rtol=1e-5, atol=0
    )
    torch.testing.assert_close(armax.sigma2, oe.sigma2, rtol=1e-9, atol=0)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), rows=st.integers(6, 40))
def test_a_singular_normal_matrix_keeps_the_covariance_of_estimable_parameters(seed, rows):
    """J (rows, 5) whose null space is spanned by directions with zero components 0 and 1:
    only parameters 0 and 1 are estimable (their unit vectors lie in J's row space). Their
    block equals the Moore-Penrose inverse of J'J (numpy), shared by every generalised inverse;
    the other rows and columns are inf, and the rank is 3. A single-parameter null direction
    (a zero column) counts the same way."""
    rng = np.random.default_rng(seed)
    null = np.zeros((5, 2))
    null[2:, :] = rng.standard_normal((3, 2))
    q, _ = np.linalg.qr(null)
    J = rng.standard_normal((rows, 5)) @ (np.eye(5) - q @ q.T) * rng.uniform(0.1, 10, 5)
    with pytest.warns(PoorExcitationWarning, match="not identifiable"):
        P, rank = inverse_normal_matrix_and_rank(torch.from_numpy(J))
    expected = np.linalg.pinv(J.T @ J, hermitian=True)
    np.testing.assert_allclose(P[:2, :2].numpy(), expected[:2, :2], rtol=1e-6)
    assert bool(torch.isinf(P[2:, :]).all()) and bool(torch.isinf(P[:, 2:]).all())
    assert int(rank) == 3
    J[:, 1] = 0.0  # a parameter the residuals do not depend on: one more null direction
    with pytest.warns(PoorExcitationWarning, match="not identifiable"):
        P, rank = inverse_normal_matrix_and_rank(torch.from_numpy(J))
    expected = np.linalg.pinv(J.T @ J, hermitian=True)
    np.testing.assert_allclose(float(P[0, 0]), expected[0, 0], rtol=1e-6)
    assert int(torch.isinf(P).sum()) == 24 and int(rank) == 2


def test_unseeded_draws_differ_between_calls_and_an_unseeded_fir_fit_is_unbiased():
    """Without a seed or generator every call seeded 0: the output noise of simulate_data
    equalled a white input drawn the same way, so the FIR (nk = 0) estimate was off by exactly
    the noise level (b1 = 1.5 +- 1e-17 for a true 1.0). Unseeded calls draw fresh entropy;
    a seed still reproduces."""
    u = input_signal("white", 400)
    assert not torch.equal(u, input_signal("white", 400))
    assert torch.equal(input_signal("white", 400, seed=3), input_signal("white", 400, seed=3))
    data = simulate_data(FIR(2, 0), u, theta=torch.tensor([1.0, 0.5]), noise_std=0.5)
    noise = data.y[..., 0] - scipy.signal.lfilter([1.0, 0.5], [1.0], u[..., 0].numpy())
    assert abs(float(np.corrcoef(noise.numpy(), u[..., 0].numpy())[0, 1])) < 0.25
    res = fit(FIR(2, 0), data)
    assert bool(((res.theta - torch.tensor([1.0, 0.5])).abs() < 6 * res.standard_errors).all())


def test_robust_scale_is_the_normalised_median_absolute_deviation():
    """``1.4826 MAD`` with numpy's median (the mean of the two middle values of an even
    count; torch.median gave the lower one: 1.4826 instead of 2.2239 for [0, 1, 3, 10]),
    batched along the leading axes."""
    from sysid.estimation.losses import robust_scale

    r = np.random.default_rng(0).standard_normal((3, 10))
    r[0, :4] = [0.0, 1.0, 3.0, 10.0]
    expected = 1.4826 * np.median(np.abs(r - np.median(r, -1, keepdims=True)), -1)
    np.testing.assert_allclose(robust_scale(torch.tensor(r)).numpy(), expected, rtol=1e-15)
    assert float(robust_scale(torch.tensor([0.0, 1.0, 3.0, 10.0]))) == pytest.approx(2.2239)


def _batch_with_a_silent_input(seed=12, N=300):
    """Three ARX(2, 2) data sets; the middle one's input is zero (its b's are not
    identifiable, its a's are an AR(2) fit of y)."""
    g = torch.Generator().manual_seed(seed)
    u = torch.randn(3, N, 1, generator=g, dtype=DT)
    u[1] = 0.0
    e = 0.1 * torch.randn(3, N, 1, generator=g, dtype=DT)
    b, a = torch.tensor([0.0, 0.5, 0.3], dtype=DT), torch.tensor([-1.2, 0.5], dtype=DT)
    y = iir_filter(b, a, u[..., 0]).unsqueeze(-1) + e
    return IOData(u, y, Ts=1.0)


@pytest.mark.parametrize("structure", ["FIR", "ARX"])
def test_least_squares_with_a_non_exciting_member_keeps_the_batch(structure):
    """A data set with a zero input no longer raises for the whole batch: its estimate is
    the minimum-norm least-squares solution (b = 0, the a's of statsmodels' OLS on the
    output lags, with OLS's standard errors), the b's have infinite standard errors, a
    PoorExcitationWarning names it, and the other data sets equal their own fits."""
    data = _batch_with_a_silent_input()
    model = FIR(3, 1) if structure == "FIR" else ARX(2, 2, 1)
    with pytest.warns(PoorExcitationWarning, match=r"1 of 3 data sets \(batch index \(1,\)\)"):
        result = fit(model, data)
    assert result.converged.all() and result.messages == []
    na = 0 if structure == "FIR" else 2
    assert (result.theta[1, na:] == 0).all()
    assert torch.isinf(result.standard_errors[1, na:]).all()
    if na:
        Phi, target = model.regression(data[1])
        ols = sm.OLS(target.numpy(), Phi[:, :na].numpy()).fit()
        np.testing.assert_allclose(result.theta[1, :na].numpy(), ols.params, rtol=1e-12)
        np.testing.assert_allclose(result.standard_errors[1, :na].numpy(), ols.bse, rtol=1e-10)
        np.testing.assert_allclose(float(result.sigma2[1]), ols.scale, rtol=1e-12)
    for i in (0, 2):
        alone = fit(model, data[i])
        torch.testing.assert_close(result.theta[i], alone.theta, rtol=1e-12, atol=1e-14)
        torch.testing.assert_close(result.covariance[i], alone.covariance, rtol=1e-10, atol=0)


def test_instrumental_variables_with_a_non_exciting_member_reports_it():
    """IV has no estimate where Z'Phi is singular: NaN, not converged, info["singular"] and a
    message naming the data set; the others equal their own IV fits."""
    data = _batch_with_a_silent_input(seed=13)
    with pytest.warns(ConvergenceWarning, match=r"batch index \(1,\): no instrumental"):
        result = fit(ARX(2, 2, 1), data, method="iv")
    assert result.converged.tolist() == [True, False, True]
    assert result.info["singular"].tolist() == [False, True, False]
    assert torch.isnan(result.theta[1]).all() and torch.isnan(result.covariance[1]).all()
    assert len(result.messages) == 1 and "Z'Phi" in result.messages[0]
    for i in (0, 2):
        alone = fit(ARX(2, 2, 1), data[i], method="iv")
        torch.testing.assert_close(result.theta[i], alone.theta, rtol=1e-12, atol=1e-14)
        torch.testing.assert_close(result.covariance[i], alone.covariance, rtol=1e-10, atol=0)


@pytest.mark.parametrize("structure", ["OE", "ARMAX", "BJ"])
def test_iterative_fits_start_with_a_non_exciting_member(structure):
    """The automatic start of OE, ARMAX and BJ survives a zero-input data set (its start is
    the minimum-norm least-squares one): the input parameters of that data set have infinite
    standard errors, the other data sets equal their own fits."""
    data = _batch_with_a_silent_input(seed=14)
    model = {"OE": OE(2, 2, 1), "ARMAX": ARMAX(2, 2, 1, 1), "BJ": BJ(2, 1, 1, 2, 1)}[structure]
    with pytest.warns(PoorExcitationWarning, match=r"batch index \(1,\)"):
        result = fit(model, data)
    b = [j for j, name in enumerate(result.parameter_names) if name.startswith("b")]
    assert torch.isinf(result.standard_errors[1, b]).all()
    assert torch.isfinite(result.theta[1]).all()
    for i in (0, 2):
        alone = fit(model, data[i])
        torch.testing.assert_close(result.theta[i], alone.theta, rtol=1e-7, atol=1e-9)
        assert bool(result.converged[i]) and bool(alone.converged)


def test_options_that_do_not_apply_are_refused_not_ignored():
    """fit names an option the model or method would ignore: x0 / segment_length for a
    polynomial model, init for a direct solve, alpha without a tuned loss, weights / init for
    a grey-box fit; xtol reaches the grey-box fit (a loose one stops earlier)."""
    from sysid.continuous import GreyBoxModel

    g = torch.Generator().manual_seed(21)
    u = torch.randn(120, 1, generator=g, dtype=DT)
    y = iir_filter(torch.tensor([0.0, 1.0], dtype=DT), torch.tensor([-0.5], dtype=DT), u[:, 0])
    data = IOData(u, y.unsqueeze(-1) + 0.05 * torch.randn(120, 1, generator=g, dtype=DT), Ts=0.1)
    for kwargs, names in [
        ({"x0": "zero"}, "x0"),
        ({"segment_length": 5}, "segment_length"),
        ({"method": "lls", "init": torch.zeros(2)}, "init"),
        ({"method": "lls", "max_iter": 3}, "max_iter"),
        ({"method": "mle", "init": torch.zeros(2)}, "init"),  # Gaussian, linear: direct solve
        ({"method": "gauss_newton", "x0": "zero", "segment_length": 3}, "segment_length, x0"),
    ]:
        with pytest.raises(InputValidationError, match=rf"fit: {names} do\(es\) not apply"):
            fit(ARX(1, 1, 1), data, **kwargs)
    with pytest.raises(InputValidationError, match="alpha tunes the fair and Huber"):
        fit(ARX(1, 1, 1), data, method="mle", loss="laplace", alpha=1.0)
    model = GreyBoxModel(
        lambda t, x, u, p: -p["a"] * x + p["b"] * u, {"a": 1.0, "b": 1.0}, nx=1, output=[0]
    )
    for kwargs, names in [
        ({"weights": torch.ones(120)}, "weights"),
        ({"init": torch.ones(2)}, "init"),
        ({"segment_length": 5}, "segment_length"),
    ]:
        with pytest.raises(InputValidationError, match=rf"fit: {names} do\(es\) not apply"):
            fit(model, data, **kwargs)
    tight, loose = fit(model, data), fit(model, data, xtol=1e-2, ftol=1e-2)
    assert int(loose.iterations) < int(tight.iterations)
