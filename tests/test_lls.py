"""Tests of sysid.lls: eq. 4.81 (estimate), 4.92/4.93 (covariance), 4.101 (FIR covariance).

Independent references: statsmodels OLS/WLS/GLS on bundled data sets, numpy.linalg.lstsq,
explicit inverses computed in numpy, and a batched Monte-Carlo study.
"""

import math
import re
import warnings

import numpy as np
import pytest
import statsmodels.api as sm
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from integrators.errors import InputValidationError, SingularMatrixError
from sysid.errors import PoorExcitationWarning
from sysid.lls import lls

DT = torch.float64


def toeplitz_regressor(u: torch.Tensor, n_taps: int) -> torch.Tensor:
    """FIR regressor U of eq. 4.8 with zero initial inputs: U[k, i] = u[k - i]; u (*batch, N)."""
    padded = torch.nn.functional.pad(u, (n_taps - 1, 0))
    return padded.unfold(-1, n_taps, 1).flip(-1)


@pytest.mark.filterwarnings("ignore::sysid.errors.PoorExcitationWarning")
@pytest.mark.parametrize("method", ["qr", "cholesky"])
def test_ols_matches_statsmodels_longley(method):
    data = sm.datasets.longley.load_pandas()
    X = sm.add_constant(data.exog).to_numpy()
    yv = data.endog.to_numpy()
    ref = sm.OLS(yv, X).fit()
    res = lls(torch.tensor(X, dtype=DT), torch.tensor(yv, dtype=DT), method=method)
    # Longley is notoriously ill-conditioned (cond(X'X) ~ 2e19); the normal-equation route
    # (cholesky) squares the scaled condition number and loses more digits than QR
    rtol = 1e-7 if method == "qr" else 1e-4
    np.testing.assert_allclose(res.theta.numpy(), ref.params, rtol=rtol)
    np.testing.assert_allclose(res.standard_errors.numpy(), ref.bse, rtol=rtol)
    np.testing.assert_allclose(res.sigma2.item(), ref.scale, rtol=rtol)
    np.testing.assert_allclose(res.residuals.numpy(), ref.resid, rtol=rtol, atol=1e-4)
    if method == "qr":  # statsmodels' condition number is that of X: sqrt of cond(X'X)
        np.testing.assert_allclose(res.condition_number.item(), ref.condition_number**2, rtol=1e-4)


def test_longley_warns_of_poor_conditioning():
    data = sm.datasets.longley.load_pandas()
    X = torch.tensor(sm.add_constant(data.exog).to_numpy(), dtype=DT)
    with pytest.warns(PoorExcitationWarning, match="ill-conditioned"):
        lls(X, torch.tensor(data.endog.to_numpy(), dtype=DT))


@pytest.mark.parametrize("method", ["qr", "cholesky"])
def test_wls_and_gls_match_statsmodels_spector(method):
    data = sm.datasets.spector.load_pandas()
    X = sm.add_constant(data.exog).to_numpy()
    yv = data.endog.to_numpy()
    w = 1.0 + X[:, 1] ** 2 / 10.0  # positive weights, varying across samples
    ref = sm.WLS(yv, X, weights=w).fit()
    Xt, yt = torch.tensor(X, dtype=DT), torch.tensor(yv, dtype=DT)
    res = lls(Xt, yt, W=torch.tensor(w, dtype=DT), method=method)
    np.testing.assert_allclose(res.theta.numpy(), ref.params, rtol=1e-9)
    np.testing.assert_allclose(res.standard_errors.numpy(), ref.bse, rtol=1e-9)
    np.testing.assert_allclose(res.sigma2.item(), ref.scale, rtol=1e-9)
    # GLS with a full (AR(1)) covariance: W = Sigma^{-1} given as a full matrix
    M = len(yv)
    idx = np.arange(M)
    Sigma = 0.6 ** np.abs(idx[:, None] - idx[None, :])
    ref_gls = sm.GLS(yv, X, sigma=Sigma).fit()
    res_gls = lls(Xt, yt, W=torch.tensor(np.linalg.inv(Sigma), dtype=DT), method=method)
    np.testing.assert_allclose(res_gls.theta.numpy(), ref_gls.params, rtol=1e-8)
    np.testing.assert_allclose(res_gls.standard_errors.numpy(), ref_gls.bse, rtol=1e-8)


def test_sandwich_covariance_eq_4_92_and_4_93():
    g = torch.Generator().manual_seed(3)
    A = torch.randn(4, 40, 3, generator=g, dtype=DT)
    y = torch.randn(4, 40, generator=g, dtype=DT)
    s = torch.rand(4, 40, generator=g, dtype=DT) + 0.2  # noise variances (diagonal Sigma)
    w = torch.rand(4, 40, generator=g, dtype=DT) + 0.5  # some other weights
    res = lls(A, y, W=w, sigma=s)
    An, Wn, Sn = A.numpy(), np.stack([np.diag(v) for v in w.numpy()]), s.numpy()
    for b in range(4):  # reference with explicit inverses (numpy, test only)
        P = np.linalg.inv(An[b].T @ Wn[b] @ An[b])
        ref = P @ An[b].T @ Wn[b] @ np.diag(Sn[b]) @ Wn[b] @ An[b] @ P  # eq. 4.92
        np.testing.assert_allclose(res.covariance[b].numpy(), ref, rtol=1e-10)
    # W = Sigma^{-1}: eq. 4.93, (A' Sigma^{-1} A)^{-1}; diagonal and full Sigma agree
    res_ml = lls(A, y, W=1 / s, sigma=s)
    res_full = lls(A, y, W=torch.diag_embed(1 / s), sigma=torch.diag_embed(s))
    for b in range(4):
        ref = np.linalg.inv(An[b].T @ np.diag(1 / Sn[b]) @ An[b])
        np.testing.assert_allclose(res_ml.covariance[b].numpy(), ref, rtol=1e-10)
        np.testing.assert_allclose(res_full.covariance[b].numpy(), ref, rtol=1e-10)
    # scalar sigma^2 with W = I: sigma^2 (A'A)^{-1} (eq. 4.101)
    res_s = lls(A, y, sigma=0.25)
    ref = 0.25 * np.linalg.inv(np.einsum("bmi,bmj->bij", An, An))
    np.testing.assert_allclose(res_s.covariance.numpy(), ref, rtol=1e-10)


def test_fir_monte_carlo_covariance_eq_4_101():
    """10 000 noise realisations, one batched lls call (shared U factorised once)."""
    g = torch.Generator().manual_seed(7)
    N, n_taps, sigma, trials = 400, 20, 0.3, 10_000
    u = torch.randn(N, generator=g, dtype=DT)
    U = toeplitz_regressor(u, n_taps)
    b_true = torch.exp(-torch.arange(n_taps, dtype=DT) / 4) * torch.cos(torch.arange(n_taps) / 2)
    y = U @ b_true + sigma * torch.randn(trials, N, generator=g, dtype=DT)
    res = lls(U, y)
    assert res.theta.shape == (trials, n_taps)
    dev = res.theta - b_true
    emp = dev.T @ dev / trials
    predicted = sigma**2 * torch.linalg.inv(U.T @ U)  # eq. 4.101 (test-only inverse)
    rel = torch.linalg.matrix_norm(emp - predicted) / torch.linalg.matrix_norm(predicted)
    assert rel < 0.10
    # unbiased (eq. 4.91): mean error within 4 standard errors of the Monte-Carlo mean
    se_mean = predicted.diagonal().sqrt() / trials**0.5
    assert (dev.mean(0).abs() < 4 * se_mean).all()
    # sigma^2 estimated from residuals is unbiased (divide by M - p)
    assert abs(res.sigma2.mean().item() / sigma**2 - 1) < 0.01


def test_sinusoid_and_step_inputs_warn_white_noise_and_prbs_do_not():
    """Notes Fig. 4.1: a sinusoid (and a step) does not excite a 20-tap FIR model."""
    N, n_taps = 200, 20
    k = torch.arange(N, dtype=DT)
    g = torch.Generator().manual_seed(0)
    inputs = {
        "sinusoid": torch.sin(0.3 * k),
        "step": torch.ones(N, dtype=DT),
        "white": torch.randn(N, generator=g, dtype=DT),
        "prbs": torch.sign(torch.randn(N, generator=g, dtype=DT)),
    }
    y = torch.randn(N, generator=g, dtype=DT)
    conds = {}
    for name, u in inputs.items():
        U = toeplitz_regressor(u, n_taps)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            res = lls(U, y)
        warned = any(issubclass(w.category, PoorExcitationWarning) for w in caught)
        assert warned == (name in ("sinusoid", "step")), name
        conds[name] = res.condition_number.item()
        # reference condition number of U'U from numpy
        np.testing.assert_allclose(conds[name], np.linalg.cond(U.T @ U), rtol=1e-6)
    assert conds["sinusoid"] > 1e5 and conds["step"] > 1e4
    assert conds["white"] < 10 and conds["prbs"] < 10


@pytest.mark.parametrize("method", ["qr", "cholesky"])
def test_singular_normal_matrix_names_batch_index(method):
    g = torch.Generator().manual_seed(2)
    A = torch.randn(5, 30, 3, generator=g, dtype=DT)
    A[3, :, 2] = 2 * A[3, :, 0]  # batch member 3 has dependent columns
    y = torch.randn(5, 30, generator=g, dtype=DT)
    with pytest.raises(SingularMatrixError, match=r"batch index \(3,\)"):
        lls(A, y, method=method)


def test_invalid_inputs_are_reported():
    A = torch.randn(10, 2, dtype=DT)
    y = torch.randn(10, dtype=DT)
    y_bad = y.clone()
    y_bad[7] = float("nan")
    with pytest.raises(InputValidationError, match=r"index \(7,\)"):
        lls(A, y_bad)
    with pytest.raises(InputValidationError, match="more equations"):
        lls(A[:2], y[:2])
    with pytest.raises(InputValidationError, match="rows"):
        lls(A, y[:9])
    with pytest.raises(InputValidationError, match="non-negative"):
        lls(A, y, W=-torch.ones(10, dtype=DT))


@settings(max_examples=15, deadline=None)
@given(
    batch=st.integers(1, 4),
    M=st.integers(4, 30),
    p=st.integers(1, 3),
    seed=st.integers(0, 10_000),
    weighted=st.booleans(),
)
def test_batched_matches_numpy_lstsq(batch, M, p, seed, weighted):
    rng = np.random.default_rng(seed)
    A = rng.standard_normal((batch, M, p))
    y = rng.standard_normal((batch, M))
    w = rng.uniform(0.1, 2.0, (batch, M)) if weighted else np.ones((batch, M))
    res = lls(torch.tensor(A), torch.tensor(y), W=torch.tensor(w) if weighted else None)
    for b in range(batch):
        sw = np.sqrt(w[b])
        ref = np.linalg.lstsq(A[b] * sw[:, None], y[b] * sw, rcond=None)[0]
        np.testing.assert_allclose(res.theta[b].numpy(), ref, rtol=1e-8, atol=1e-10)


def test_float32_and_gradients():
    g = torch.Generator().manual_seed(4)
    A = torch.randn(3, 50, 4, generator=g, dtype=DT)
    th = torch.randn(3, 4, generator=g, dtype=DT)
    y = (A @ th.unsqueeze(-1)).squeeze(-1) + 0.01 * torch.randn(3, 50, generator=g, dtype=DT)
    r64 = lls(A, y)
    r32 = lls(A.float(), y.float())
    assert r32.theta.dtype == torch.float32
    torch.testing.assert_close(r32.theta.double(), r64.theta, rtol=1e-4, atol=1e-5)
    # differentiable: d theta / d y = (A'A)^{-1} A' (checked by gradcheck, finite differences)
    A1 = A[0].clone().requires_grad_(True)
    y1 = y[0].clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda a, b: lls(a, b).theta, (A1, y1))


@settings(max_examples=15, deadline=None)
@given(
    N=st.integers(22, 120),
    nb=st.integers(1, 20),
    nk=st.integers(0, 3),
    seed=st.integers(0, 10_000),
)
def test_fir_lls_equals_lls_on_explicit_regressor(N, nb, nk, seed):
    """fir_lls builds U'U and U'y from correlations (no U); it must equal lls(U, y)."""
    from sysid.lls import fir_lls
    from sysid.montecarlo import fir_regressor

    g = torch.Generator().manual_seed(seed)
    u = torch.randn(2, N, generator=g, dtype=DT)
    y = torch.randn(2, N, generator=g, dtype=DT)
    U = fir_regressor(u, nb, nk)
    np.testing.assert_allclose(U[0].numpy()[nk + 1, 0], u[0, 1].item())  # U[k, i] = u_{k-nk-i}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", PoorExcitationWarning)
        ref = lls(U, y)
        got = fir_lls(u, y, nb, nk)
    # Normal equations (fir_lls) against QR (lls) agree to the normal equations' error,
    # about cond(U)^2 eps relative: short records with many taps are ill-conditioned (e.g.
    # N = 22, nb = 17: cond 9e4, differences 4e-7 relative).
    tol = max(1e-9, 50 * float(torch.linalg.cond(U).max()) ** 2 * torch.finfo(DT).eps)
    scale = float(ref.theta.abs().max())
    torch.testing.assert_close(got.theta, ref.theta, rtol=tol, atol=tol * scale)
    # standard errors from diag((U'U)^{-1}) at once, the covariance matrix on first read
    se, cov = ref.standard_errors, ref.covariance
    torch.testing.assert_close(got.standard_errors, se, rtol=tol, atol=tol * float(se.max()))
    torch.testing.assert_close(got.covariance, cov, rtol=tol, atol=tol * float(cov.abs().max()))
    ninv, ninv_max = ref.normal_inverse, float(ref.normal_inverse.abs().max())
    torch.testing.assert_close(got.normal_inverse, ninv, rtol=tol, atol=tol * ninv_max)
    # |U (theta_got - theta_ref)| <= max row sum of |U| x the parameter tolerance
    row_sum = float(U.abs().sum(-1).max())
    torch.testing.assert_close(
        got.residuals, ref.residuals, rtol=tol, atol=max(1e-11, tol * scale * row_sum)
    )
    # the power-iteration condition estimate is a close lower bound of the exact one
    assert (got.condition_number <= ref.condition_number * (1 + 1e-9)).all()
    assert (got.condition_number >= 0.5 * ref.condition_number).all()


def test_fir_lls_sigma2_without_cancellation_loss():
    """fir_lls takes r'r = y'y - 2 theta'U'y + theta'U'U theta where that is accurate and
    recomputes it from explicit residuals where it would cancel (tiny noise): sigma^2 and
    the residuals still match lls on the explicit regressor (batched and unbatched)."""
    from sysid.lls import fir_lls
    from sysid.montecarlo import fir_regressor

    g = torch.Generator().manual_seed(21)
    nb, N = 6, 300
    u = torch.randn(3, N, generator=g, dtype=DT)
    U = fir_regressor(u, nb)
    b = torch.randn(nb, generator=g, dtype=DT)
    noise = torch.tensor([1e-7, 0.1, 1e-3], dtype=DT).unsqueeze(-1)
    y = U @ b + noise * torch.randn(3, N, generator=g, dtype=DT)
    ref = lls(U, y)
    for got, want in [(fir_lls(u, y, nb), ref), (fir_lls(u[0], y[0], nb), lls(U[0], y[0]))]:
        torch.testing.assert_close(got.sigma2, want.sigma2, rtol=1e-6, atol=0)
        torch.testing.assert_close(got.residuals, want.residuals, rtol=0, atol=1e-12)
        torch.testing.assert_close(got.theta, want.theta, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("N", [7, 12, 13, 100, 1001])
@pytest.mark.parametrize("nb", [1, 5, 12, 20, 31])
def test_lagged_products_equal_direct_sums(N, nb):
    """Block-Gram correlations sum_m w_m z_{m+d} (whole blocks of 12 samples plus the pairs
    ending in the last partial block) equal the direct sums, with broadcast batch shapes."""
    from sysid.lls import _lagged_products

    g = torch.Generator().manual_seed(N + 100 * nb)
    w = torch.randn(3, N, generator=g, dtype=DT)
    z = torch.randn(2, 1, N, generator=g, dtype=DT)
    got = _lagged_products(w, z, nb)
    wn, zn = w.numpy(), z.numpy()
    want = np.zeros((2, 3, nb))
    for d in range(min(nb, N)):  # loop over lags (reference)
        want[..., d] = (wn[:, : N - d] * zn[..., d:]).sum(-1)
    assert got.shape == (2, 3, nb)
    np.testing.assert_allclose(got.numpy(), want, rtol=1e-12, atol=1e-12)


def test_scaled_condition_screening_is_exact_where_needed_and_lazy_elsewhere():
    """fir_lls and lls(method="cholesky") estimate the scaled condition number by power
    iteration only where the bound p * trace(S^-1) reaches the thresholds; the warning then
    names the right batch member, and the deferred estimates are those of the eager
    computation (a close lower bound of numpy's condition number of the scaled U'U)."""
    from sysid.lls import _condition_estimate, fir_lls
    from sysid.montecarlo import fir_regressor

    N, nb = 200, 20
    k = torch.arange(N, dtype=DT)
    g = torch.Generator().manual_seed(5)
    u = torch.randn(4, N, generator=g, dtype=DT)
    u[2] = torch.sin(0.3 * k)  # poorly exciting for 20 taps (notes Fig. 4.1)
    y = torch.randn(4, N, generator=g, dtype=DT)
    U = fir_regressor(u, nb)
    G = (U.transpose(-1, -2) @ U).numpy()
    dinv = 1 / np.sqrt(np.diagonal(G, axis1=-2, axis2=-1))
    exact = np.linalg.cond(G * dinv[:, :, None] * dinv[:, None, :])
    for solve in (lambda: fir_lls(u, y, nb), lambda: lls(U, y, method="cholesky")):
        with pytest.warns(PoorExcitationWarning, match=r"batch index \(2,\)"):
            res = solve()
        assert isinstance(res._scaled_condition_number, torch.Tensor) is False  # deferred
        got = res.scaled_condition_number.numpy()
        assert (got <= exact * (1 + 1e-9)).all() and (got >= 0.5 * exact).all()
        assert got[2] > 1e4 and (np.delete(got, 2) < 1e3).all()
        Gs = torch.tensor(G * dinv[:, :, None] * dinv[:, None, :])
        eager = _condition_estimate(Gs, torch.linalg.inv(Gs))
        torch.testing.assert_close(res.scaled_condition_number, eager, rtol=1e-6, atol=0)
    # white-noise inputs only: the bound rules the warning out, nothing is estimated at once
    with warnings.catch_warnings():
        warnings.simplefilter("error", PoorExcitationWarning)
        res = fir_lls(u[[0, 1, 3]], y[[0, 1, 3]], nb)
    np.testing.assert_allclose(res.scaled_condition_number.numpy(), np.delete(exact, 2), rtol=0.5)


def test_fir_lls_singular_member_and_non_finite_samples_are_named():
    """Singularity (a zero input) and non-finite samples are reported with their batch and
    sample indices, also for samples that only the delay hides from the regressor."""
    from sysid.lls import fir_lls

    g = torch.Generator().manual_seed(6)
    u = torch.randn(3, 60, generator=g, dtype=DT)
    y = torch.randn(3, 60, generator=g, dtype=DT)
    u0 = u.clone()
    u0[1] = 0.0
    with pytest.raises(SingularMatrixError, match=r"batch index \(1,\)"):
        fir_lls(u0, y, 4)
    for name, tensor, index in [("u", u, (2, 59)), ("y", y, (0, 3)), ("u", u, (1, 0))]:
        bad = tensor.clone()
        bad[index] = float("inf")
        args = (bad, y) if name == "u" else (u, bad)
        with pytest.raises(
            InputValidationError, match=rf"^fir_lls: {name} contains .* {re.escape(str(index))}"
        ):
            fir_lls(*args, 4, 2)


def test_fir_regressor_values_and_refused_orders():
    """U[k, i] = u_{k-nk-i} from rest with N rows; nb < 1 and nk < 0 are refused by name."""
    from sysid.montecarlo import fir_regressor

    u = torch.tensor([1.0, 2.0, 3.0], dtype=DT)
    expected = torch.tensor([[0.0, 0.0], [1.0, 0.0], [2.0, 1.0]], dtype=DT)
    torch.testing.assert_close(fir_regressor(u, 2, 1), expected)
    with pytest.raises(InputValidationError, match="nb must be an integer >= 1"):
        fir_regressor(u, 0)
    with pytest.raises(InputValidationError, match="nk must be an integer >= 0"):
        fir_regressor(u, 2, -1)


def test_batch_shapes_that_do_not_broadcast_are_named():
    """lls and fir_lls name both shapes when the batch dimensions of the data disagree."""
    from sysid.lls import fir_lls

    with pytest.raises(InputValidationError, match=r"A \(3, 10, 2\) and y \(2, 10\)"):
        lls(torch.randn(3, 10, 2, dtype=DT), torch.randn(2, 10, dtype=DT))
    with pytest.raises(InputValidationError, match=r"u \(3, 10\) and y \(2, 10\)"):
        fir_lls(torch.randn(3, 10, dtype=DT), torch.randn(2, 10, dtype=DT), 2)


def test_weight_and_noise_batches_that_do_not_broadcast_are_named():
    """W and sigma must broadcast to the batch of A and y (W may widen it: one estimate per
    weighting; sigma may not, as the estimate does not depend on it); the estimate and its
    standard errors then share one batch shape, each member equal to its own fit."""
    g = torch.Generator().manual_seed(8)
    A = torch.randn(3, 40, 2, generator=g, dtype=DT)
    y = torch.randn(3, 40, generator=g, dtype=DT)
    with pytest.raises(InputValidationError, match=r"W has batch shape \(4,\).* \(3,\) of A and y"):
        lls(A, y, W=torch.rand(4, 40, generator=g, dtype=DT))
    with pytest.raises(InputValidationError, match=r"sigma has batch shape \(2, 1\)"):
        lls(A, y, W=torch.rand(3, 40, generator=g, dtype=DT), sigma=torch.ones(2, 1, 40, dtype=DT))
    with pytest.raises(InputValidationError, match=r"sigma has batch shape \(4,\)"):
        lls(A, y, sigma=torch.eye(40, dtype=DT).expand(4, 40, 40))
    W = torch.rand(2, 3, 40, generator=g, dtype=DT) + 0.1
    sigma = torch.rand(2, 1, 40, generator=g, dtype=DT) + 0.1
    res = lls(A, y, W=W, sigma=sigma)
    assert res.theta.shape == res.standard_errors.shape == (2, 3, 2)
    for i in range(2):
        for j in range(3):
            one = lls(A[j], y[j], W=W[i, j], sigma=sigma[i, 0])
            torch.testing.assert_close(res.theta[i, j], one.theta)
            torch.testing.assert_close(res.standard_errors[i, j], one.standard_errors)


@pytest.mark.parametrize(
    "sigma",
    [-1.0, 0.0, float("inf"), float("nan"), torch.full((60,), -0.5), torch.zeros(60)],
)
def test_non_positive_or_non_finite_noise_variance_is_rejected(sigma):
    """sigma is a variance: a value <= 0 gave zero (or NaN) standard errors before."""
    g = torch.Generator().manual_seed(3)
    A, y = (
        torch.randn(60, 3, generator=g, dtype=torch.float64),
        torch.randn(60, dtype=torch.float64),
    )
    with pytest.raises(InputValidationError, match="sigma"):
        lls(A, y, sigma=sigma)


def test_complex_regressor_or_output_is_rejected():
    g = torch.Generator().manual_seed(4)
    A, y = (
        torch.randn(40, 2, generator=g, dtype=torch.float64),
        torch.randn(40, dtype=torch.float64),
    )
    for a, b, name in [(A.to(torch.complex128), y, "A"), (A, y.to(torch.complex128), "y")]:
        with pytest.raises(InputValidationError, match=f"{name} is complex"):
            lls(a, b)
    from sysid.lls import fir_lls

    with pytest.raises(InputValidationError, match="u is complex"):
        fir_lls(A[:, 0].to(torch.complex128), y, 3)


def test_poor_excitation_warning_accounts_for_the_dtype():
    """Same nearly collinear regressor in float32 and float64 (scaled cond(A'A) ~ 3.5e6).

    With the statistical threshold raised out of the way (cond_warn=1e12) float64 keeps
    >= 9 digits and is silent, while float32 warns and names the precision. The rounding
    bound the message quotes must bound the actual float32 error (truth: the float64
    solution), and the float64 message must report many more digits than the float32 one.
    """
    g = torch.Generator().manual_seed(0)
    M = 200
    x = torch.randn(M, generator=g, dtype=torch.float64)
    near = x + 1e-3 * torch.randn(M, generator=g, dtype=torch.float64)
    A = torch.stack([x, near, torch.randn(M, generator=g, dtype=torch.float64)], -1)
    noise = 0.3 * torch.randn(M, generator=g, dtype=torch.float64)
    y = A @ torch.tensor([1.0, -2.0, 0.5], dtype=torch.float64) + noise
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        ref = lls(A, y, cond_warn=1e12)  # float64: no warning
    with pytest.warns(PoorExcitationWarning, match="float32") as record:
        r32 = lls(A.float(), y.float(), cond_warn=1e12)
    message = str(record[0].message)
    bound = float(re.search(r"rounding-error bound ([0-9.e+-]+)\)", message).group(1))
    error = ((r32.theta.double() - ref.theta).norm() / ref.theta.norm()).item()
    assert 1e-2 < bound < 1 and error <= bound
    with pytest.warns(PoorExcitationWarning) as rec64:
        lls(A, y)  # default threshold 1e4: warns about noise sensitivity, not precision
    digits64 = int(re.search(r"about (\d+) correct digits", str(rec64[0].message)).group(1))
    digits32 = int(re.search(r"about (\d+) correct digits", message).group(1))
    assert digits64 >= 9 and digits32 <= 1


@pytest.mark.parametrize("method", ["qr", "cholesky", "fir_lls"])
def test_singular_members_are_nan_and_the_others_as_if_solved_alone(method):
    """singular="nan": a member with a zero regressor, one with dependent columns and (for
    the FIR route) one with a zero input are NaN, flagged and infinitely ill-conditioned; the
    healthy members equal their own solve and numpy's lstsq."""
    from sysid.lls import fir_lls
    from sysid.montecarlo import fir_regressor

    g = torch.Generator().manual_seed(7)
    if method == "fir_lls":
        u = torch.randn(4, 60, generator=g, dtype=DT)
        u[1] = 0.0
        y = torch.randn(4, 60, generator=g, dtype=DT)
        bad = [1]
        result = fir_lls(u, y, 3, 1, singular="nan")
        A = fir_regressor(u, 3, 1)
    else:
        A = torch.randn(4, 40, 3, generator=g, dtype=DT)
        A[1, :, 2] = 0.0
        A[2, :, 2] = 2 * A[2, :, 0]
        y = torch.randn(4, 40, generator=g, dtype=DT)
        bad = [1, 2]
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # no ill-conditioning warning for the singular
            result = lls(A, y, method=method, singular="nan")
    assert result.singular.tolist() == [i in bad for i in range(4)]
    for i in range(4):
        if i in bad:
            for value in (result.theta[i], result.standard_errors[i], result.sigma2[i]):
                assert torch.isnan(value).all()
            assert torch.isnan(result.covariance[i]).all()
            assert torch.isnan(result.normal_inverse[i]).all()
            assert torch.isnan(result.residuals[i]).all()
            assert math.isinf(result.condition_number[i])
            assert math.isinf(result.scaled_condition_number[i])
            continue
        reference = np.linalg.lstsq(A[i].numpy(), y[i].numpy(), rcond=None)[0]
        np.testing.assert_allclose(result.theta[i].numpy(), reference, rtol=0, atol=1e-13)
        alone = lls(A[i], y[i])
        torch.testing.assert_close(result.covariance[i], alone.covariance, rtol=1e-12, atol=0)
        torch.testing.assert_close(result.residuals[i], alone.residuals, rtol=0, atol=1e-13)
    with pytest.raises(InputValidationError, match="singular must be 'raise' or 'nan'"):
        lls(A, y, singular="ignore")


def test_rows_of_weight_zero_are_not_counted_as_observations():
    """Diagonal weights with zeros: sigma^2, the standard errors and dof equal statsmodels'
    WLS on the rows of positive weight (the zero rows used to count in M - p: standard errors
    4x too small with 4 of 20 rows weighted); per-problem counts where they differ; too few
    weighted rows are refused."""
    g = torch.Generator().manual_seed(9)
    A = torch.randn(2, 20, 3, generator=g, dtype=DT)
    y = torch.randn(2, 20, generator=g, dtype=DT)
    W = torch.rand(2, 20, generator=g, dtype=DT) + 0.5
    W[0, 6:] = 0.0
    W[1, 11:] = 0.0
    for method in ("qr", "cholesky"):
        result = lls(A, y, W=W, method=method)
        assert result.dof.tolist() == [3.0, 8.0]
        for i, m in enumerate((6, 11)):
            wls = sm.WLS(y[i, :m].numpy(), A[i, :m].numpy(), weights=W[i, :m].numpy()).fit()
            np.testing.assert_allclose(result.theta[i].numpy(), wls.params, rtol=1e-10)
            np.testing.assert_allclose(result.standard_errors[i].numpy(), wls.bse, rtol=1e-10)
            np.testing.assert_allclose(float(result.sigma2[i]), wls.scale, rtol=1e-10)
    assert lls(A[0], y[0], W=W[0]).dof == 3
    W[1, 3:] = 0.0
    with pytest.raises(InputValidationError, match=r"problem \(1,\) has 3 rows with a positive"):
        lls(A, y, W=W)


@pytest.mark.parametrize("cond_warn", [-1, 0.5, float("nan"), "1e8", True])
def test_cond_warn_out_of_range_is_refused(cond_warn):
    """cond_warn = -1 warned at a condition number of 2, NaN never warned: both refused."""
    from sysid.lls import fir_lls

    A, y = torch.randn(10, 2, dtype=DT), torch.randn(10, dtype=DT)
    with pytest.raises(InputValidationError, match="cond_warn .* must be a number >= 1"):
        lls(A, y, cond_warn=cond_warn)
    with pytest.raises(InputValidationError, match="cond_warn .* must be a number >= 1"):
        fir_lls(y, y, 2, cond_warn=cond_warn)
