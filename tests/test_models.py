"""Polynomial model structures (notes §4.6): predictors vs direct recursions and the notes'
formulas, simulation vs scipy, regression rows, python-control conversion, batching.

Notes typos/conventions found while checking: the notes write A(z) = 1 - sum a_i z^-i
(eq. 4.119), so their a_i is -a_i in the MATLAB convention used here; eq. 4.111 indexes the
rows 0..N while eq. 4.110 indexes yhat 1..N (N vs N+1 rows); the formulas themselves
(4.117, 4.130-4.132) check out numerically below.
"""

import math

import numpy as np
import pytest
import scipy.signal
import torch

from integrators.errors import InputValidationError
from sysid import ARMAX, ARX, BJ, FIR, OE, IOData

TRUE = {
    "FIR": (FIR(3, nk=2), [0.5, -0.3, 0.2]),
    "ARX": (ARX(2, 2, nk=1), [-1.5, 0.7, 1.0, 0.5]),
    "OE": (OE(2, 2, nk=1), [1.0, 0.5, -1.2, 0.5]),
    "ARMAX": (ARMAX(2, 2, 1, nk=1), [-1.5, 0.7, 1.0, 0.5, 0.3]),
    "BJ": (BJ(2, 1, 2, 2, nk=1), [1.0, 0.5, 0.4, -1.0, 0.3, -1.2, 0.5]),
}


def model_with(name):
    model, theta = TRUE[name]
    model.set_parameter_vector(torch.tensor(theta, dtype=torch.float64))
    return model


def signals(N, seed=0, batch=()):
    g = torch.Generator().manual_seed(seed)
    u = torch.randn(*batch, N, 1, generator=g, dtype=torch.float64)
    e = 0.2 * torch.randn(*batch, N, generator=g, dtype=torch.float64)
    return u, e


_DATA = IOData(*signals(30, seed=12))


def lag(x, t, i):
    return float(x[t - i]) if t - i >= 0 else 0.0


def test_armax_predictor_matches_direct_recursion_eq_4_117():
    """ARMAX: y_t = -sum a_i y_{t-i} + sum b_j u_{t-nk-j+1} + e_t + sum c_i e_{t-i}; the
    one-step predictor replaces e_t by 0 and past e by past prediction errors."""
    model = model_with("ARMAX")
    a, b, c = [-1.5, 0.7], [1.0, 0.5], [0.3]
    u, e = signals(200)
    u1 = u[:, 0]
    y = np.zeros(200)
    yhat = np.zeros(200)
    for t in range(200):
        ar = -sum(a[i] * lag(y, t, i + 1) for i in range(2))
        x = sum(b[j] * lag(u1, t, 1 + j) for j in range(2))
        y[t] = ar + x + float(e[t]) + c[0] * lag(e, t, 1)
        yhat[t] = -sum(a[i] * lag(y, t, i + 1) for i in range(2)) + x
        yhat[t] += c[0] * (lag(y, t, 1) - lag(yhat, t, 1))
    data = IOData(u, torch.tensor(y))
    np.testing.assert_allclose(model.predict(data)[:, 0].detach().numpy(), yhat, atol=1e-12)
    # the prediction errors are the innovations e
    np.testing.assert_allclose(
        model.prediction_errors(data)[:, 0].detach().numpy(), e.numpy(), atol=1e-12
    )


def test_bj_predictor_satisfies_eq_4_131_and_direct_recursion():
    model = model_with("BJ")
    B, C, D, F = [0, 1.0, 0.5], [1, 0.4], [1, -1.0, 0.3], [1, -1.2, 0.5]
    u, e = signals(300, seed=1)
    un, en = u[:, 0].numpy(), e.numpy()
    y = scipy.signal.lfilter(B, F, un) + scipy.signal.lfilter(C, D, en)
    yhat = model.predict(IOData(u, torch.tensor(y)))[:, 0].detach().numpy()
    # eq. 4.131: H yhat = G u + (H - 1) y with G = B/F, H = C/D
    lhs = scipy.signal.lfilter(C, D, yhat)
    rhs = scipy.signal.lfilter(B, F, un) + scipy.signal.lfilter(C, D, y) - y
    np.testing.assert_allclose(lhs, rhs, atol=1e-11)
    # direct recursion: w = y - B/F u (Python loop), C eps = D w, yhat = y - eps
    x = np.zeros(300)
    eps = np.zeros(300)
    for t in range(300):
        x[t] = (
            B[1] * lag(un, t, 1) + B[2] * lag(un, t, 2) - F[1] * lag(x, t, 1) - F[2] * lag(x, t, 2)
        )
        w = [y[t - i] - x[t - i] if t - i >= 0 else 0.0 for i in range(3)]
        eps[t] = w[0] + D[1] * w[1] + D[2] * w[2] - C[1] * lag(eps, t, 1)
    np.testing.assert_allclose(yhat, y - eps, atol=1e-11)
    np.testing.assert_allclose(eps, en, atol=1e-11)  # true model: errors = innovations


@pytest.mark.parametrize("name", ["ARMAX", "BJ", "ARX"])
@pytest.mark.parametrize("k", [2, 4])
def test_k_step_predictor_is_conditional_mean(name, k):
    """yhat(t|t-k) = G u_t + sum_{j>=k} h_j e_{t-j} (h: impulse response of H)."""
    model = model_with(name)
    u, e = signals(150, seed=2)
    y_det = model.simulate(u)[:, 0].detach()
    b_h = np.r_[1.0, model.c.detach().numpy()]
    a_h = np.convolve(np.r_[1.0, model.a.detach().numpy()], np.r_[1.0, model.d.detach().numpy()])
    v = scipy.signal.lfilter(b_h, a_h, e.numpy())
    h = scipy.signal.lfilter(b_h, a_h, np.eye(150)[0])
    v_past = np.convolve(e.numpy(), np.r_[np.zeros(k), h[k:]])[:150]
    data = IOData(u, y_det + torch.tensor(v))
    yk = model.predict(data, horizon=k)[:, 0].detach().numpy()
    np.testing.assert_allclose(yk, y_det.numpy() + v_past, atol=1e-11)


def test_infinite_horizon_is_simulation():
    model = model_with("ARMAX")
    u, e = signals(80)
    data = IOData(u, model.simulate(u).detach()[:, 0] + e)
    torch.testing.assert_close(model.predict(data, horizon=math.inf), model.simulate(u))


def test_oe_predict_equals_simulate_multi_input_batched():
    g = torch.Generator().manual_seed(3)
    model = OE([2, 1], [2, 1], nk=[1, 0], n_inputs=2, batch_shape=(4,))
    model.set_parameter_vector(
        0.3 * torch.randn(4, model.n_params, generator=g, dtype=torch.float64)
    )
    u = torch.randn(4, 100, 2, generator=g, dtype=torch.float64)
    data = IOData(u, torch.randn(4, 100, 1, generator=g, dtype=torch.float64))
    torch.testing.assert_close(model.predict(data), model.simulate(u), rtol=0, atol=1e-13)
    # simulate vs scipy per batch member and input
    theta = model.parameter_vector().detach().numpy()
    for i in range(4):
        b1, b2, f1, f2 = theta[i, 0:2], theta[i, 2:3], theta[i, 3:5], theta[i, 5:6]
        ref = scipy.signal.lfilter(np.r_[0, b1], np.r_[1, f1], u[i, :, 0].numpy())
        ref += scipy.signal.lfilter(b2, np.r_[1, f2], u[i, :, 1].numpy())
        np.testing.assert_allclose(model.simulate(u)[i, :, 0].detach().numpy(), ref, atol=1e-12)


@pytest.mark.parametrize("name", list(TRUE))
def test_noise_free_data_has_zero_prediction_error_at_truth(name):
    model = model_with(name)
    u, _ = signals(400, seed=4, batch=(3,))
    data = IOData(u, model.simulate(u).detach())
    assert model.prediction_errors(data).abs().max() < 1e-12
    assert model.simulation_errors(data).abs().max() < 1e-12
    wrong = model.parameter_vector().detach() + 0.01
    assert model.prediction_errors(data, theta=wrong).abs().max() > 1e-4


def test_noise_free_multi_input_structures():
    g = torch.Generator().manual_seed(5)
    u = torch.randn(300, 2, generator=g, dtype=torch.float64)
    for model in (
        ARX(2, [2, 1], nk=[1, 3], n_inputs=2),
        BJ([1, 2], 1, 1, [1, 2], nk=[0, 2], n_inputs=2),
    ):
        theta = 0.2 * torch.randn(model.n_params, generator=g, dtype=torch.float64)
        model.set_parameter_vector(theta)
        assert bool(model.is_stable())
        data = IOData(u, model.simulate(u).detach())
        assert model.prediction_errors(data).abs().max() < 1e-12


@pytest.mark.parametrize("name", ["FIR", "ARX"])
def test_regression_rows_reproduce_output_at_truth(name):
    model = model_with(name)
    theta = model.parameter_vector().detach()
    parts = []
    for n, seed in ((60, 6), (35, 7)):  # two experiments, each with its own start
        u, e = signals(n, seed=seed)
        y = model.simulate(u).detach()[:, 0]
        if name == "ARX":  # equation-error noise keeps the ARX relation exact
            v = scipy.signal.lfilter([1.0], np.r_[1.0, theta[:2].numpy()], e.numpy())
            y = y + torch.from_numpy(v)
        parts.append(IOData(u, y))
    data = IOData.experiments(parts)
    Phi, target = model.regression(data)
    max_lag = {"FIR": 4, "ARX": 2}[name]
    assert Phi.shape == (95 - 2 * max_lag, model.n_params)
    residual = target - Phi @ theta
    if name == "FIR":
        assert residual.abs().max() < 1e-12
    else:
        e_rows = torch.cat([signals(n, seed=s)[1][max_lag:] for n, s in ((60, 6), (35, 7))])
        torch.testing.assert_close(residual, e_rows, rtol=0, atol=1e-12)
    # a row written out by hand (ARX, sample t = 5 of experiment 0): [-y4, -y3, u4, u3]
    if name == "ARX":
        y0, u0 = parts[0].y[:, 0], parts[0].u[:, 0]
        expected = torch.stack([-y0[4], -y0[3], u0[4], u0[3]])
        torch.testing.assert_close(Phi[5 - max_lag], expected)


def test_regression_only_for_linear_structures():
    with pytest.raises(InputValidationError, match="not linear"):
        model_with("OE").regression(IOData(np.zeros(10), np.zeros(10)))


def test_to_control_frequency_response_matches_model():
    w = np.linspace(0.01, 3.0, 25)
    for name in TRUE:
        model = model_with(name)
        model.Ts = 0.1
        G = model.frequency_response(w / 0.1)[:, 0].numpy()
        sys = model.to_control()
        assert sys.dt == 0.1
        np.testing.assert_allclose(
            np.squeeze(sys.frequency_response(w / 0.1).complex), G, rtol=1e-10
        )
        H = model.frequency_response(w / 0.1, noise=True).numpy()
        np.testing.assert_allclose(
            np.squeeze(model.to_control(noise=True).frequency_response(w / 0.1).complex),
            H,
            rtol=1e-10,
        )
        model.Ts = 1.0
    # and the model's own response is the DTFT of its impulse response (scipy.freqz)
    model = model_with("OE")
    _, ref = scipy.signal.freqz([0, 1.0, 0.5], [1, -1.2, 0.5], worN=w)
    np.testing.assert_allclose(model.frequency_response(w)[:, 0].numpy(), ref, rtol=1e-10)


@pytest.mark.parametrize("Ts", [0, -1.0, math.nan, math.inf, True, "0.1", torch.ones(2)])
def test_sample_time_must_be_finite_and_positive(Ts):
    """Ts = 0 made frequency_response G(1) at every frequency and Ts < 0 its conjugate;
    construction and assignment refuse it."""
    with pytest.raises(InputValidationError, match="sample time Ts must be a finite number > 0"):
        OE(2, 2, 1, Ts=Ts)
    model = OE(2, 2, 1)
    with pytest.raises(InputValidationError, match="sample time Ts"):
        model.Ts = Ts
    assert model.Ts == 1.0


def test_sample_time_forms_and_frequency_response():
    """The default, numpy and 0-d tensor sample times are floats; G(e^{j w Ts}) with Ts = 0.5
    equals scipy.signal.freqz at w Ts rad/sample."""
    assert OE(2, 2, 1).Ts == 1.0
    assert OE(2, 2, 1, Ts=np.float32(0.5)).Ts == 0.5
    model = OE(2, 2, 1)
    model.set_parameter_vector(torch.tensor(TRUE["OE"][1], dtype=torch.float64))
    model.Ts = torch.tensor(0.5)
    assert type(model.Ts) is float
    w = np.linspace(0.1, 6.0, 7)
    _, ref = scipy.signal.freqz([0, 1.0, 0.5], [1, -1.2, 0.5], worN=w * 0.5)
    np.testing.assert_allclose(model.frequency_response(w)[:, 0].numpy(), ref, rtol=1e-10)


def test_poles_zeros_stability_and_stabilize():
    model = model_with("BJ")
    poles = np.sort_complex(model.poles().numpy())
    expected = np.sort_complex(np.r_[np.roots([1, -1.0, 0.3]), np.roots([1, -1.2, 0.5])])
    np.testing.assert_allclose(poles, expected, atol=1e-12)
    np.testing.assert_allclose(model.zeros().numpy(), [-0.5 + 0j], atol=1e-14)
    assert bool(model.is_stable())
    oe = OE(2, 2, batch_shape=(2,))
    oe.set_parameter_vector(torch.tensor([[1.0, 0.5, -2.5, 1.0], [1.0, 0.5, -1.2, 0.5]]))
    assert oe.is_stable().tolist() == [False, True]  # F = (1 - 2q^-1)(1 - 0.5q^-1)
    changed = oe.stabilize()
    assert changed.tolist() == [True, False]
    np.testing.assert_allclose(oe.f[0][0].detach().numpy(), np.poly([0.5, 0.5])[1:], atol=1e-12)
    np.testing.assert_allclose(oe.f[0][1].detach().numpy(), [-1.2, 0.5])
    assert oe.is_stable().all()


def test_parameter_vector_names_and_indexing():
    model = BJ([2, 1], 1, 1, [1, 2], nk=[1, 0], n_inputs=2, batch_shape=(3,))
    assert model.parameter_names() == [
        "b1_u1",
        "b2_u1",
        "b1_u2",
        "c1",
        "d1",
        "f1_u1",
        "f1_u2",
        "f2_u2",
    ]
    theta = torch.arange(24, dtype=torch.float64).reshape(3, 8) / 100
    model.set_parameter_vector(theta)
    torch.testing.assert_close(model.parameter_vector().detach(), theta)
    one = model[1]
    assert type(one) is BJ and one.batch_shape == ()
    torch.testing.assert_close(one.parameter_vector().detach(), theta[1])
    u = torch.randn(50, 2, dtype=torch.float64)
    torch.testing.assert_close(one.simulate(u), model.simulate(u)[1])
    assert len(model.to_control()) == 3
    with pytest.raises(InputValidationError, match="8 parameters"):
        model.set_parameter_vector(torch.zeros(7))


def test_experiments_are_predicted_separately():
    model = model_with("ARMAX")
    u1, e1 = signals(40, seed=8)
    u2, e2 = signals(30, seed=9)
    d1 = IOData(u1, model.simulate(u1).detach()[:, 0] + e1)
    d2 = IOData(u2, model.simulate(u2).detach()[:, 0] + e2)
    both = model.predict(IOData.experiments([d1, d2]))
    torch.testing.assert_close(both, torch.cat([model.predict(d1), model.predict(d2)], dim=-2))


def test_simulate_initial_state_matches_scipy():
    model = model_with("OE")
    u, _ = signals(50)
    zi = torch.tensor([[0.7, -0.2]], dtype=torch.float64)  # (nu, max(nf, nk + nb - 1))
    ref = scipy.signal.lfilter([0, 1.0, 0.5], [1, -1.2, 0.5], u[:, 0].numpy(), zi=zi[0].numpy())
    np.testing.assert_allclose(model.simulate(u, zi=zi)[:, 0].detach().numpy(), ref[0], atol=1e-12)


@pytest.mark.parametrize("k", [0, 1, 3, 7])
def test_simulate_refuses_an_initial_state_of_the_wrong_length(k):
    """OE(2, 2, 1)'s filter q^-1 B / F has k = max(nf, nk + nb - 1) = 2 states; a zi of
    another length was padded or cut and gave numbers (7 entries: a 5-sample output)."""
    model = model_with("OE")
    u, _ = signals(5)
    with pytest.raises(InputValidationError, match="k = max.* = 2"):
        model.simulate(u, zi=torch.ones(1, k, dtype=torch.float64))
    zi = torch.ones(1, 2, dtype=torch.float64)
    ref = scipy.signal.lfilter([0, 1.0, 0.5], [1, -1.2, 0.5], u[:, 0].numpy(), zi=zi[0].numpy())
    np.testing.assert_allclose(model.simulate(u, zi=zi)[:, 0].detach().numpy(), ref[0], atol=1e-12)


def test_gradient_of_simulation_loss_matches_finite_differences():
    model = model_with("BJ")
    u, e = signals(60)
    data = IOData(u, model.simulate(u).detach()[:, 0] + e)
    theta = model.parameter_vector().detach().clone().requires_grad_(True)

    def loss(th):
        return (model.prediction_errors(data, theta=th) ** 2).sum()

    assert torch.autograd.gradcheck(loss, (theta,))
    jac = torch.func.jacfwd(lambda th: model.prediction_errors(data, theta=th))(theta.detach())
    assert jac.shape == (60, 1, 7)


def test_float32_models_work():
    model = model_with("ARMAX")
    model32 = ARMAX(2, 2, 1, dtype=torch.float32)
    model32.set_parameter_vector(model.parameter_vector().detach().float())
    u, e = signals(500)
    data = IOData(u, model.simulate(u).detach()[:, 0] + e)
    y32 = model32.predict(data.to(dtype=torch.float32))
    assert y32.dtype == torch.float32
    torch.testing.assert_close(y32.double(), model.predict(data), rtol=0, atol=1e-4)


def test_input_noise_example_after_eq_4_134():
    """Notes §4.6.4: with H = G = B/A the predictor obeys B yhat = B u + (B - A) y."""
    model = ARMAX(2, 2, 1, nk=0)  # B = 1 + 0.5 q^-1 (monic), C = B  =>  H = C/A = B/A = G
    model.set_parameter_vector(torch.tensor([-1.5, 0.7, 1.0, 0.5, 0.5], dtype=torch.float64))
    A, B = np.array([1, -1.5, 0.7]), np.array([1.0, 0.5, 0.0])
    u, e = signals(120, seed=10)
    y = scipy.signal.lfilter(B, A, u[:, 0].numpy() + e.numpy())  # input noise: G (u + e)
    yhat = model.predict(IOData(u, torch.tensor(y)))[:, 0].detach().numpy()
    lhs = scipy.signal.lfilter(B, [1.0], yhat)
    rhs = scipy.signal.lfilter(B, [1.0], u[:, 0].numpy()) + scipy.signal.lfilter(B - A, [1.0], y)
    np.testing.assert_allclose(lhs, rhs, atol=1e-11)


@pytest.mark.parametrize(
    "build, order",
    [
        (lambda: FIR(0), "nb"),
        (lambda: OE(2, 0), "nf"),
        (lambda: OE(0, 2), "nb"),
        (lambda: OE([2, 0], [1, 1], n_inputs=2), "nb"),
        (lambda: ARMAX(2, 2, 0), "nc"),
        (lambda: BJ(2, 1, 1, 0), "nf"),
    ],
)
def test_structures_reject_a_missing_polynomial(build, order):
    """A zero order drops a polynomial the structure is named for (OE(2, 0) gave infinite
    standard errors, FIR(0) a bare IndexError): raise, saying what the orders mean."""
    with pytest.raises(InputValidationError, match=rf"{order} >= 1.*number of coefficients"):
        build()


@pytest.mark.parametrize(
    "build, order",
    [
        (lambda: ARX(2, [2.7], 1), "nb"),
        (lambda: ARX(True, 2, 1), "na"),
        (lambda: ARX(2, 2.0, 1), "nb"),
        (lambda: ARX(2, 2, 1.5), "nk"),
        (lambda: ARX(2, 2, None), "nk"),
        (lambda: ARX(2, "2", 1), "nb"),
        (lambda: OE([2, True], [1, 1], n_inputs=2), "nb"),
        (lambda: ARMAX(2, 2, 1.0), "nc"),
        (lambda: ARX(2, 2, 1, n_inputs=True), "n_inputs"),
    ],
)
def test_orders_that_are_not_integers_are_refused(build, order):
    """nb = [2.7] was truncated to 2 and na = True taken as 1; nb = 2.0, nk = 1.5 and
    nk = None raised a bare TypeError."""
    with pytest.raises(InputValidationError, match=rf"{order} must be an integer"):
        build()


@pytest.mark.parametrize(
    "call, match",
    [
        (lambda: ARX(2, 2, 1, batch_shape=-1), "batch_shape must be an integer >= 0"),
        (lambda: ARX(2, 2, 1, batch_shape=(2, 1.5)), "batch_shape must be an integer >= 0"),
        (lambda: model_with("ARX").set_parameter_vector(torch.ones(3, 4)), "does not broadcast"),
        (lambda: ARX(2, 2, 1, batch_shape=2).set_parameter_vector(torch.ones(3, 4)), "(2,)"),
        (lambda: model_with("ARX").predict(_DATA, math.nan), "horizon must be an integer"),
        (lambda: model_with("ARX").predict(_DATA, -math.inf), "horizon must be an integer"),
        (lambda: model_with("ARX").predict(_DATA, 1.5), "horizon must be an integer"),
        (lambda: model_with("ARX").predict(_DATA, True), "horizon must be an integer"),
        (lambda: model_with("ARX").zeros(5), r"integer in \[0, 0\]"),
        (lambda: model_with("ARX").zeros(-1), r"integer in \[0, 0\]"),
    ],
)
def test_bad_arguments_raise_named_errors(call, match):
    """batch_shape=-1, a (3, 4) theta for an unbatched model, horizon NaN / -inf and an
    input index out of range raised RuntimeError, ValueError, OverflowError, IndexError."""
    with pytest.raises(InputValidationError, match=match):
        call()


def test_valid_horizons_batches_and_inputs_still_work():
    """numpy integer horizons and batch sizes, a (p,) theta broadcast over a batch and the
    last input's zeros (roots of b1 z + b2: -b2 / b1, by hand)."""
    model = model_with("ARX")
    torch.testing.assert_close(model.predict(_DATA, np.int64(2)), model.predict(_DATA, 2))
    batched = ARX(2, 2, 1, batch_shape=np.int64(3))
    batched.set_parameter_vector(torch.tensor(TRUE["ARX"][1], dtype=torch.float64))
    torch.testing.assert_close(batched.parameter_vector()[2], model.parameter_vector())
    two = ARX(1, [2, 2], [1, 1], n_inputs=2)
    two.set_parameter_vector(torch.tensor([0.1, 1.0, 0.5, 2.0, -0.5], dtype=torch.float64))
    torch.testing.assert_close(two.zeros(1), torch.tensor([0.25 + 0j], dtype=torch.complex128))


def test_numpy_integer_orders_are_orders():
    """numpy integers (scalars and arrays) give the model of the same Python ints."""
    model = ARX(np.int64(2), np.array([2, 3]), [np.int32(1), 0], n_inputs=np.int64(2))
    assert (model.na, model.nb, model.nk, model.n_inputs) == (2, [2, 3], [1, 0], 2)
    assert all(type(v) is int for v in [model.na, *model.nb, *model.nk])
    assert model.parameter_names() == ARX(2, [2, 3], [1, 0], n_inputs=2).parameter_names()


def test_arx_without_one_polynomial_is_ar_or_fir_and_without_both_is_refused():
    """ARX(na, 0) is an AR model, ARX(0, nb) the FIR model (same regression, eq. 4.111);
    ARX(0, 0) has nothing to estimate."""
    u, e = signals(200, seed=3)
    data = IOData(u, e)
    fir_phi, fir_y = FIR(3).regression(data)
    arx_phi, arx_y = ARX(0, 3).regression(data)
    torch.testing.assert_close(arx_phi, fir_phi)
    torch.testing.assert_close(arx_y, fir_y)
    assert ARX(2, 0).parameter_vector().shape == (2,)
    with pytest.raises(InputValidationError, match="no coefficient"):
        ARX(0, 0)
