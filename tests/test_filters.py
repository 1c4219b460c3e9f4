"""iir_filter / allpole: exactness vs scipy.signal.lfilter (with zi), gradients vs finite
differences (gradcheck), forward mode vs reverse mode, batched coefficients, float32."""

import numpy as np
import pytest
import scipy.signal
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from integrators.errors import InputValidationError
from sysid import filters
from sysid.filters import allpole, iir_filter, poly_mul


@pytest.fixture(autouse=True)
def _pure_torch_path():
    """Every test here exercises the pure-torch block method unless it selects the CPU
    dispatch to scipy itself (the tests at the end of this file)."""
    with filters.cpu_backend("torch"):
        yield


def stable_monic(n: int, rng: np.random.Generator, radius: float = 0.95) -> np.ndarray:
    """[1, a_1..a_n] with random roots of modulus < radius (complex ones in pairs)."""
    n_pairs = n // 2
    r = rng.uniform(0.1, radius, n_pairs) * np.exp(1j * rng.uniform(0, np.pi, n_pairs))
    roots = np.concatenate([r, r.conj(), rng.uniform(-radius, radius, n - 2 * n_pairs)])
    return np.atleast_1d(np.poly(roots).real)


@settings(max_examples=40, deadline=None)
@given(
    n=st.integers(0, 4),
    m=st.integers(1, 5),
    N=st.integers(1, 700),
    batch=st.sampled_from([(), (3,), (2, 2)]),
    small_blocks=st.booleans(),
    seed=st.integers(0, 2**31),
)
def test_matches_scipy_lfilter_with_zi(n, m, N, batch, small_blocks, seed):
    rng = np.random.default_rng(seed)
    a = stable_monic(n, rng)
    b = rng.normal(size=m)
    k = max(n, m - 1)
    x = rng.normal(size=(*batch, N))
    zi = rng.normal(size=(*batch, k))
    expected = scipy.signal.lfilter(b, a, x, zi=zi)[0] if k else scipy.signal.lfilter(b, a, x)
    old = filters._MAX_BLOCK
    filters._MAX_BLOCK = 5 if small_blocks else old  # many blocks: exercise state carrying
    try:
        got = iir_filter(torch.tensor(b), torch.tensor(a[1:]), torch.tensor(x), torch.tensor(zi))
    finally:
        filters._MAX_BLOCK = old
    np.testing.assert_allclose(
        got.numpy(), expected, rtol=0, atol=1e-12 * (1 + abs(expected).max())
    )


def _exact_lfilter(b: np.ndarray, a: np.ndarray, x: np.ndarray, zi=None) -> np.ndarray:
    """``B/A x`` (``a`` monic, with its 1) by the recursion in extended precision (numpy long
    double), batched over the leading axes of ``x``, from rest or from scipy's initial state
    ``zi`` (added to the first samples of ``B x``): the reference."""
    b, a, x = (np.asarray(v, dtype=np.longdouble) for v in (b, a, x))
    w = np.zeros_like(x)
    for j, bj in enumerate(b):
        w[..., j:] += bj * x[..., : x.shape[-1] - j]
    if zi is not None:
        w[..., : zi.shape[-1]] += zi
    y = np.zeros_like(x)
    for k in range(x.shape[-1]):
        acc = w[..., k].copy()
        for i in range(1, min(len(a), k + 1)):
            acc -= a[i] * y[..., k - i]
        y[..., k] = acc
    return y.astype(np.float64)


@settings(max_examples=12, deadline=None)
@given(
    order=st.integers(2, 6),
    radius=st.floats(0.9, 0.995),
    spread=st.floats(0.0, 0.02),
    seed=st.integers(0, 2**31),
)
def test_clustered_poles_near_the_unit_circle_are_as_accurate_as_the_recursion(
    order, radius, spread, seed
):
    """Poles clustered near z = 1 (an oversampled low-pass of order up to 6): the block
    transition has large entries in the basis of past outputs. A prefix scan by doubling made
    ``(1 - 0.99 q^-1)^4`` wrong by a factor 6 and ``(1 - 0.95 q^-1)^6`` by 1e26; the block
    method with its refinement step must be as close to the extended-precision recursion as
    ``scipy.signal.lfilter`` is, for batched coefficients (the path of batched models) and in
    the adjoint (gradient) pass."""
    rng = np.random.default_rng(seed)
    roots = radius - spread * rng.uniform(0, 1, order)
    a = np.poly(roots)
    b = rng.normal(size=3)
    x = rng.normal(size=(2, 1500))
    zi = rng.normal(size=(2, order))
    coefficients = torch.tensor(a[1:]).expand(2, order)  # batched: the block method
    for initial in (None, zi):
        exact = _exact_lfilter(b, a, x, initial)
        scale = abs(exact).max()
        if initial is None:
            reference = scipy.signal.lfilter(b, a, x)
            got = iir_filter(torch.tensor(b), coefficients, torch.tensor(x))
        else:
            reference = scipy.signal.lfilter(b, a, x, zi=zi)[0]
            got = iir_filter(torch.tensor(b), coefficients, torch.tensor(x), torch.tensor(zi))
        scipy_error = abs(reference - exact).max() / scale
        error = abs(got.numpy() - exact).max() / scale
        assert error <= 20 * scipy_error + 1e-13, (error, scipy_error)
    exact = _exact_lfilter([1.0], a, x)
    scipy_error = abs(scipy.signal.lfilter([1.0], a, x) - exact).max() / abs(exact).max()
    # the adjoint pass: d(sum g y)/dx is the time-reversed filter of g
    xt = torch.tensor(x, requires_grad=True)
    g = torch.tensor(rng.normal(size=x.shape))
    (iir_filter(torch.ones(2, 1, dtype=torch.float64), coefficients, xt) * g).sum().backward()
    adjoint = _exact_lfilter([1.0], a, g.numpy()[..., ::-1])[..., ::-1]
    adjoint_error = abs(xt.grad.numpy() - adjoint).max() / abs(adjoint).max()
    assert adjoint_error <= 20 * scipy_error + 1e-13, (adjoint_error, scipy_error)


def test_batched_coefficients_match_scipy_per_member():
    rng = np.random.default_rng(1)
    A = np.stack([stable_monic(3, rng) for _ in range(6)])
    B = rng.normal(size=(6, 4))
    x = rng.normal(size=(6, 2000))
    got = iir_filter(torch.tensor(B), torch.tensor(A[:, 1:]), torch.tensor(x)).numpy()
    for i in range(6):
        np.testing.assert_allclose(got[i], scipy.signal.lfilter(B[i], A[i], x[i]), atol=1e-12)
    # shared signal, batched filters (broadcast), e.g. one input for many models
    got = iir_filter(torch.tensor(B), torch.tensor(A[:, 1:]), torch.tensor(x[0])).numpy()
    np.testing.assert_allclose(got[4], scipy.signal.lfilter(B[4], A[4], x[0]), atol=1e-12)


def test_long_signal_many_blocks():
    rng = np.random.default_rng(2)
    a = stable_monic(4, rng, radius=0.99)
    b = rng.normal(size=5)
    x = rng.normal(size=20_000)
    got = iir_filter(torch.tensor(b), torch.tensor(a[1:]), torch.tensor(x)).numpy()
    expected = scipy.signal.lfilter(b, a, x)
    np.testing.assert_allclose(got, expected, atol=1e-11 * abs(expected).max())


def test_gradcheck_all_inputs_including_initial_state(monkeypatch):
    rng = np.random.default_rng(3)
    a = torch.tensor(stable_monic(3, rng)[1:], requires_grad=True)
    b = torch.tensor(rng.normal(size=3), requires_grad=True)
    x = torch.tensor(rng.normal(size=(2, 16)), requires_grad=True)
    zi = torch.tensor(rng.normal(size=(2, 3)), requires_grad=True)
    monkeypatch.setattr(filters, "_MAX_BLOCK", 7)  # 3 blocks: state carried across blocks
    assert torch.autograd.gradcheck(iir_filter, (b, a, x, zi), check_forward_ad=True)
    assert torch.autograd.gradgradcheck(allpole, (a, x))


def test_gradcheck_batched_coefficients(monkeypatch):
    monkeypatch.setattr(filters, "_MAX_BLOCK", 5)
    rng = np.random.default_rng(4)
    a = torch.tensor(np.stack([stable_monic(2, rng)[1:] for _ in range(3)]), requires_grad=True)
    x = torch.tensor(rng.normal(size=(3, 12)), requires_grad=True)
    assert torch.autograd.gradcheck(allpole, (a, x))
    # a shared denominator broadcast over a batch of signals: gradients summed correctly
    a1 = a[0].detach().clone().requires_grad_(True)
    assert torch.autograd.gradcheck(allpole, (a1, x))


def test_forward_mode_jacobian_equals_reverse_mode():
    rng = np.random.default_rng(5)
    a = torch.tensor(stable_monic(4, rng)[1:])
    w = torch.tensor(rng.normal(size=60))
    jf = torch.func.jacfwd(allpole, argnums=(0, 1))(a, w)
    jr = torch.func.jacrev(allpole, argnums=(0, 1))(a, w)
    for f, r in zip(jf, jr, strict=True):
        torch.testing.assert_close(f, r, rtol=1e-10, atol=1e-12)
    # the Jacobian with respect to w is the lower-triangular Toeplitz matrix of the impulse
    # response of 1/A (closed form via scipy)
    h = scipy.signal.lfilter([1.0], np.r_[1.0, a.numpy()], np.eye(60)[0])
    toeplitz = np.tril(scipy.linalg.toeplitz(h))
    np.testing.assert_allclose(jf[1].numpy(), toeplitz, atol=1e-12)


def test_float32_close_to_float64():
    rng = np.random.default_rng(6)
    a = torch.tensor(stable_monic(2, rng)[1:])
    b = torch.tensor(rng.normal(size=3))
    x = torch.tensor(rng.normal(size=(4, 3000)))
    y64 = iir_filter(b, a, x)
    y32 = iir_filter(b.float(), a.float(), x.float())
    assert y32.dtype == torch.float32
    torch.testing.assert_close(y32.double(), y64, rtol=0, atol=1e-4 * y64.abs().max().item())


def test_poly_mul_matches_numpy_convolve():
    rng = np.random.default_rng(7)
    p, q = rng.normal(size=(3, 4)), rng.normal(size=(3, 2))
    got = poly_mul(torch.tensor(p), torch.tensor(q)).numpy()
    for i in range(3):
        np.testing.assert_allclose(got[i], np.convolve(p[i], q[i]), atol=1e-14)


@pytest.mark.parametrize("k", [0, 1, 3, 4])
def test_initial_state_of_the_wrong_length_is_rejected(k):
    """b with m = 3 and a with n = 2 have k = max(n, m - 1) = 2 states (scipy's lfilter
    refuses another length); a shorter zi was zero-padded, a longer one cut."""
    b = torch.tensor([1.0, 0.5, 0.25], dtype=torch.float64)
    a = torch.tensor([-0.5, 0.1], dtype=torch.float64)
    x = torch.ones(6, dtype=torch.float64)
    for backend in ("auto", "torch"):
        with filters.cpu_backend(backend), pytest.raises(InputValidationError, match="k = .* 2"):
            iir_filter(b, a, x, torch.ones(k, dtype=torch.float64))
    with pytest.raises(ValueError):
        scipy.signal.lfilter(b.numpy(), np.r_[1.0, a.numpy()], x.numpy(), zi=np.ones(k))
    zi = torch.tensor([0.3, -0.7], dtype=torch.float64)
    expected = scipy.signal.lfilter(b.numpy(), np.r_[1.0, a.numpy()], x.numpy(), zi=zi.numpy())
    np.testing.assert_allclose(iir_filter(b, a, x, zi).numpy(), expected[0], atol=1e-14)


def test_dtype_mismatch_is_rejected():
    with pytest.raises(ValueError, match="dtype"):
        iir_filter(
            torch.ones(2, dtype=torch.float64), torch.ones(1, dtype=torch.float32), torch.ones(5)
        )


# ---------------------------------------------------------------- CPU dispatch to scipy


@pytest.mark.parametrize("with_zi", [False, True])
def test_cpu_dispatch_matches_block_method_values_and_gradients(with_zi):
    """cpu_backend("auto") (scipy lfilter inside the autograd node) and the block method
    give the same output and the same gradients in b, a, x, zi (to rounding)."""
    rng = np.random.default_rng(11)
    a = torch.tensor(stable_monic(4, rng)[1:]).unsqueeze(0)  # a leading size-1 dimension
    b = torch.tensor(rng.normal(size=(1, 5)))
    x = torch.tensor(rng.normal(size=(3, 500)))
    zi = torch.tensor(rng.normal(size=(3, 4))) if with_zi else None
    with filters.cpu_backend("auto"):
        assert filters._scipy_eligible(b, a, x, x.new_zeros(0) if zi is None else zi)
    results, weights = {}, torch.tensor(rng.normal(size=(3, 500)))
    for backend in ("auto", "torch"):
        with filters.cpu_backend(backend):
            leaves = [t.clone().requires_grad_(True) for t in (b, a, x)]
            zl = None if zi is None else zi.clone().requires_grad_(True)
            y = iir_filter(*leaves, zl)
            grads = torch.autograd.grad((y * weights).sum(), leaves + ([zl] if with_zi else []))
            results[backend] = (y.detach(), grads)
    expected = scipy.signal.lfilter(
        b[0].numpy(), np.r_[1.0, a[0].numpy()], x.numpy(), zi=None if zi is None else zi.numpy()
    )
    expected = expected[0] if with_zi else expected
    np.testing.assert_allclose(results["auto"][0].numpy(), expected, rtol=0, atol=1e-12)
    torch.testing.assert_close(results["auto"][0], results["torch"][0], rtol=0, atol=1e-11)
    for g_auto, g_torch in zip(results["auto"][1], results["torch"][1], strict=True):
        torch.testing.assert_close(g_auto, g_torch, rtol=1e-10, atol=1e-10)


def test_cpu_dispatch_gradcheck_and_higher_derivatives():
    """Under the default backend: gradients vs finite differences, forward mode, and the
    double backward (which runs the differentiable torch path)."""
    rng = np.random.default_rng(12)
    a = torch.tensor(stable_monic(2, rng)[1:], requires_grad=True)
    b = torch.tensor(rng.normal(size=3), requires_grad=True)
    x = torch.tensor(rng.normal(size=(2, 20)), requires_grad=True)
    zi = torch.tensor(rng.normal(size=(2, 2)), requires_grad=True)
    with filters.cpu_backend("auto"):
        assert filters._scipy_eligible(b, a, x, zi)
        assert torch.autograd.gradcheck(iir_filter, (b, a, x, zi), check_forward_ad=True)
        assert torch.autograd.gradgradcheck(iir_filter, (b, a, x, zi))


def test_cpu_dispatch_only_for_a_shared_filter():
    x = torch.zeros(3, 10, dtype=torch.float64)
    b1, a1 = torch.ones(2, dtype=torch.float64), torch.full((1,), 0.5, dtype=torch.float64)
    none = x.new_zeros(0)
    with filters.cpu_backend("auto"):
        assert filters._scipy_eligible(b1, a1, x, none)
        assert not filters._scipy_eligible(b1.expand(3, 2), a1, x, none)  # batched coefficients
        assert not filters._scipy_eligible(b1, a1, x, x.new_zeros(3, 5))  # unusual zi length
    assert not filters._scipy_eligible(b1, a1, x, none)  # this module's fixture: "torch"
    with pytest.raises(filters.InputValidationError, match="cpu_backend"):
        with filters.cpu_backend("numpy"):
            pass


@pytest.mark.parametrize("shape", [(300,), (1, 300)])
def test_cpu_dispatch_single_signal_gradient_matches_finite_differences(shape):
    """One signal (the OE loss case): the adjoint pass reads the reversed gradient in place
    and the lagged sums are BLAS dot products; gradients in b, a, x equal the block method's
    and central finite differences (gradcheck)."""
    rng = np.random.default_rng(13)
    a = torch.tensor(stable_monic(4, rng)[1:], requires_grad=True)
    b = torch.tensor(rng.normal(size=5), requires_grad=True)
    x = torch.tensor(rng.normal(size=shape), requires_grad=True)
    weights = torch.tensor(rng.normal(size=shape))
    grads = {}
    for backend in ("auto", "torch"):
        with filters.cpu_backend(backend):
            y = iir_filter(b, a, x)
            grads[backend] = torch.autograd.grad((y * weights).sum(), (b, a, x))
    for g_auto, g_torch in zip(grads["auto"], grads["torch"], strict=True):
        torch.testing.assert_close(g_auto, g_torch, rtol=1e-10, atol=1e-10)
    with filters.cpu_backend("auto"):
        assert filters._scipy_eligible(b, a, x, x.new_zeros(0))
        short = (b, a, x[..., :40].detach().clone().requires_grad_(True))
        assert torch.autograd.gradcheck(iir_filter, short)


def test_lagged_dots_single_signal_path_equals_numpy_correlation():
    rng = np.random.default_rng(14)
    g, x = rng.normal(size=(2, 1000))
    want = [np.dot(g[j:], x[: 1000 - j]) for j in range(6)]
    got = filters._lagged_dots(torch.tensor(g).reshape(1, -1), torch.tensor(x), range(6))
    assert got.shape == (1, 6)
    np.testing.assert_allclose(got[0].numpy(), want, rtol=1e-12)
    batched = filters._lagged_dots(torch.tensor(np.stack([g, x])), torch.tensor(x), range(6))
    np.testing.assert_allclose(batched[0].numpy(), want, rtol=1e-12)


def test_torch_func_jacobians_of_iir_filter_match_finite_differences():
    """jacfwd / jacrev through iir_filter (the standard Function.apply path under torch.func)
    agree with each other and with central finite differences in (b, a)."""
    rng = np.random.default_rng(15)
    a = torch.tensor(stable_monic(3, rng)[1:])
    b = torch.tensor(rng.normal(size=4))
    x = torch.tensor(rng.normal(size=50))

    def f(b_, a_):
        return iir_filter(b_, a_, x)

    jf = torch.func.jacfwd(f, argnums=(0, 1))(b, a)
    jr = torch.func.jacrev(f, argnums=(0, 1))(b, a)
    h = 1e-6
    for k, (arg, jac_f, jac_r) in enumerate(zip((b, a), jf, jr, strict=True)):
        for j in range(arg.shape[0]):  # loop over coefficients (finite differences)
            d = torch.zeros_like(arg)
            d[j] = h
            args_p, args_m = [b, a], [b, a]
            args_p[k], args_m[k] = arg + d, arg - d
            fd = (f(*args_p) - f(*args_m)) / (2 * h)
            torch.testing.assert_close(jac_f[:, j], fd, rtol=1e-6, atol=1e-8)
            torch.testing.assert_close(jac_r[:, j], fd, rtol=1e-6, atol=1e-8)
