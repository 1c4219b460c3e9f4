"""Training of neural continuous-time models through ``sysid.fit(method="adam" | "lbfgs")``
(:mod:`sysid.continuous.training`), with stand-in modules that follow the neural-model
contract."""

from __future__ import annotations

import importlib
import math
import warnings

import numpy as np
import pytest
import scipy.linalg
import torch
from _shared_models import LinearRHS
from torch import nn

import sysid
from integrators.errors import InputValidationError
from sysid.continuous.training import simulate


# --------------------------------------------------------------------------- stand-ins
class MLPRHS(nn.Module):
    """dx/dt = net([x, u]) / Ts (an MLP scaled to the sample rate); y = x[..., :ny]."""

    def __init__(self, nx=1, nu=1, ny=1, hidden=16, Ts=0.1, method="rk4", seed=0):
        super().__init__()
        self.nx, self.nu, self.ny, self.method, self.substeps, self.Ts = nx, nu, ny, method, 1, Ts
        torch.manual_seed(seed)
        self.net = nn.Sequential(nn.Linear(nx + nu, hidden), nn.Tanh(), nn.Linear(hidden, nx))
        self.double()

    def forward(self, t, x, u):
        return self.net(torch.cat([x, u], -1)) / self.Ts

    def output(self, x, u):
        return x[..., : self.ny]

    def physical_parameters(self):
        return {}

    def to_physical(self, name, raw):
        raise KeyError(name)


class HybridSpring(nn.Module):
    """Mass-spring-damper x1' = x2, x2' = -k x1 - c x2 + u plus a zero-initialised residual
    MLP of the velocity x2 on x2' (seeing the position too, it could imitate the spring and
    k would not be identifiable beside it); k = exp(log_k) is the physical parameter;
    y = x1."""

    def __init__(self, k0=2.0, c=0.5, method="rk4"):
        super().__init__()
        self.nx, self.nu, self.ny, self.method, self.substeps = 2, 1, 1, method, 1
        self.c = c
        self.log_k = nn.Parameter(torch.tensor(math.log(k0), dtype=torch.float64))
        torch.manual_seed(1)
        self.res = nn.Sequential(nn.Linear(1, 8), nn.Tanh(), nn.Linear(8, 1)).double()
        with torch.no_grad():
            self.res[2].weight.zero_()
            self.res[2].bias.zero_()

    def forward(self, t, x, u):
        k = self.log_k.exp()
        acc = -k * x[..., 0] - self.c * x[..., 1] + u[..., 0]
        acc = acc + self.res(x[..., 1:])[..., 0]
        return torch.stack([x[..., 1], acc], -1)

    def output(self, x, u):
        return x[..., :1]

    def physical_parameters(self):
        return {"k": self.log_k}

    def to_physical(self, name, raw):
        return raw.exp()


# --------------------------------------------------------------------------- data
def zoh_data(A, B, C, N, Ts, seed, noise=0.0, hold=5):
    """Exact zero-order-hold response of x' = A x + B u, y = C x from x(0) = 0 to a random
    piecewise-constant input (held ``hold`` samples): IOData (N, 1) / (N, ny)."""
    rng = np.random.default_rng(seed)
    n = A.shape[0]
    u = np.repeat(rng.uniform(-1, 1, (N + hold) // hold), hold)[:N, None]
    M = scipy.linalg.expm(np.block([[A, B], [np.zeros((1, n + 1))]]) * Ts)
    Ad, Bd = M[:n, :n], M[:n, n:]
    x = np.zeros((N, n))
    for k in range(N - 1):  # reference recursion of the test data
        x[k + 1] = Ad @ x[k] + Bd @ u[k]
    y = x @ C.T + noise * rng.standard_normal((N, C.shape[0]))
    return sysid.IOData(torch.tensor(u), torch.tensor(y), Ts)


def first_order(N=300, seed=0, noise=0.0):
    return zoh_data(np.array([[-1.0]]), np.array([[1.0]]), np.eye(1), N, 0.1, seed, noise)


def spring(N=300, seed=0, k=4.0, c=0.5, noise=0.01):
    A = np.array([[0.0, 1.0], [-k, -c]])
    return zoh_data(A, np.array([[0.0], [1.0]]), np.array([[1.0, 0.0]]), N, 0.1, seed, noise)


def params_of(model):
    return [p.detach().clone() for p in model.parameters()]


# --------------------------------------------------------------------------- tests
def test_neural_ode_learns_first_order_system():
    data, val = first_order(300, seed=0), first_order(200, seed=1)
    model = MLPRHS()
    rmse_untrained = float((simulate(model, val) - val.y).pow(2).mean().sqrt())
    result = sysid.fit(
        model,
        data,
        method="adam",
        horizon=20,
        batch_size=16,
        epochs=50,
        steps_per_epoch=5,
        lr=1e-2,
        schedule="cosine",
        x0="estimate",
        seed=0,
        validation=val,
    )
    diag = result.validate(val)
    rmse = float(diag["rmse"][0])
    # the output amplitude is ~0.5; the untrained network misses it by far more than 0.1
    assert rmse_untrained > 0.1
    assert rmse < 0.05
    assert float(diag["fit_percent"][0]) > 80
    assert float(diag["r2"][0]) > 0.95
    assert result.validation_loss.shape == result.train_loss.shape
    assert result.status == "completed" and bool(result.converged)


def test_lbfgs_train_loss_is_the_loss_after_each_epochs_step():
    """L-BFGS epochs report the criterion after their step (torch's LBFGS.step returns the
    loss before it): without validation data that is the loss the best model is chosen by,
    so the best loss is the smallest reported one, and the losses fall epoch by epoch."""
    data = spring(300, seed=3, noise=0.01)
    result = sysid.fit(
        HybridSpring(k0=3.0), data, method="lbfgs", horizon=50, epochs=3, lr=1.0, x0="zero"
    )
    losses = result.train_loss.tolist()
    assert result.info["best_loss"] == min(losses)
    assert losses[0] > losses[1] > losses[2]


def test_hybrid_recovers_stiffness_with_standard_error():
    data = spring(300, seed=3, noise=0.01)
    model = HybridSpring(k0=3.0)
    result = sysid.fit(
        model, data, method="lbfgs", horizon=299, epochs=4, lr=1.0, x0="zero", seed=0
    )
    k, se = result.params["k"], float(result.standard_errors[0])
    assert result.parameter_names == ["k"]
    assert 0 < se < 0.05
    assert abs(k - 4.0) < 3 * se
    # the network is a nuisance: the standard error is that of the k column of the
    # free-run Jacobian J = [J_k, J_w] (log k and every network weight) after projecting out
    # the numerical column span of J_w (rank by QR with column pivoting), mapped by
    # dk/dlog k = k; J from two reverse passes per column, checked by central differences
    model = result.model
    r, J = _reverse_mode_jacobian(model, data, [model.log_k, *model.res.parameters()])
    torch.testing.assert_close(r, (data.y - simulate(model, data)).reshape(-1))
    columns = [model.log_k, *model.res.parameters()]
    h, entries = 1e-6, [(w, i) for w in columns for i in np.ndindex(*w.shape)]
    for j in (0, 3, len(entries) - 1):
        param, index = entries[j]
        pair = []
        for sign in (1, -1):
            with torch.no_grad():
                param[index] += sign * h
            pair.append((data.y - simulate(model, data)).reshape(-1))
            with torch.no_grad():
                param[index] -= sign * h
        torch.testing.assert_close(J[:, j], (pair[0] - pair[1]) / (2 * h), rtol=0, atol=1e-8)
    Q, R, _ = scipy.linalg.qr(J[:, 1:].numpy(), mode="economic", pivoting=True)
    diag = np.abs(np.diag(R))
    rank = int((diag > diag[0] * max(J.shape) * np.finfo(float).eps).sum())
    Q = torch.from_numpy(Q[:, :rank])
    J_k = J[:, 0] - Q @ (Q.T @ J[:, 0])
    r = r.detach()
    sigma2 = (r @ r) / (r.numel() - 1 - rank)
    se_projected = float(torch.sqrt(sigma2 / (J_k @ J_k))) * k
    conditional = float(torch.sqrt(sigma2 / (J[:, 0] @ J[:, 0]))) * k
    # the span includes directions with singular values 1e-12 of the largest: rounding
    # differences between the two Jacobians (forward vs reverse mode) move it by ~1e-16/1e-12
    assert se == pytest.approx(se_projected, rel=1e-3)
    assert se > 1.3 * conditional  # the network imitates part of the spring's effect
    assert float(result.sigma2) == pytest.approx(float(sigma2), rel=1e-10)


class ImitatedDecay(nn.Module):
    """x' = -a x + u plus a residual w x (a linear layer without bias): the network can
    imitate the physical decay exactly, so a is not identifiable beside it."""

    def __init__(self):
        super().__init__()
        self.nx, self.nu, self.ny, self.method, self.substeps = 1, 1, 1, "rk4", 1
        self.log_a = nn.Parameter(torch.tensor(0.0, dtype=torch.float64))
        self.res = nn.Linear(1, 1, bias=False).double()

    def forward(self, t, x, u):
        return -self.log_a.exp() * x + u + self.res(x)

    def output(self, x, u):
        return x

    def physical_parameters(self):
        return {"a": self.log_a}

    def to_physical(self, name, raw):
        return raw.exp()


def test_a_physical_parameter_the_network_imitates_gets_an_infinite_standard_error():
    data = first_order(200, seed=4, noise=0.01)
    with pytest.warns(sysid.PoorExcitationWarning, match="not identifiable"):
        result = sysid.fit(
            ImitatedDecay(), data, method="lbfgs", horizon=199, epochs=2, x0="zero", seed=0
        )
    assert math.isinf(float(result.standard_errors[0]))


class DecayAndGain(nn.Module):
    """x' = -a x + b u + w x (a linear layer without bias): a is not identifiable beside the
    network, b is; ``with_a=False`` leaves the decay to the network alone."""

    def __init__(self, with_a: bool):
        super().__init__()
        self.with_a = with_a
        self.nx, self.nu, self.ny, self.method, self.substeps = 1, 1, 1, "rk4", 1
        self.log_a = nn.Parameter(torch.tensor(0.0, dtype=torch.float64))
        self.log_b = nn.Parameter(torch.tensor(-0.5, dtype=torch.float64))
        self.res = nn.Linear(1, 1, bias=False).double()
        nn.init.constant_(self.res.weight, -0.5)

    def forward(self, t, x, u):
        decay = self.log_a.exp() * x if self.with_a else 0.0
        return -decay + self.log_b.exp() * u + self.res(x)

    def output(self, x, u):
        return x

    def physical_parameters(self):
        if self.with_a:
            return {"a": self.log_a, "b": self.log_b}
        return {"b": self.log_b}

    def to_physical(self, name, raw):
        return raw.exp()


def test_an_identifiable_physical_parameter_beside_an_imitated_one_keeps_its_standard_error():
    """b keeps the standard error and noise variance of the model without a (the network
    carries the whole decay there), while a gets inf; the delta-method transform to physical
    units made b's entry NaN (0 * inf) beside an inf one."""
    data = first_order(100, seed=4, noise=0.01)
    options = dict(method="lbfgs", horizon=99, epochs=8, x0="zero", seed=0)
    with pytest.warns(sysid.PoorExcitationWarning, match="not identifiable"):
        both = sysid.fit(DecayAndGain(with_a=True), data, **options)
    alone = sysid.fit(DecayAndGain(with_a=False), data, **options)
    assert both.parameter_names == ["a", "b"] and math.isinf(float(both.standard_errors[0]))
    torch.testing.assert_close(both.theta[1], alone.theta[0], rtol=1e-3, atol=0)
    torch.testing.assert_close(both.standard_errors[1], alone.standard_errors[0], rtol=1e-2, atol=0)
    torch.testing.assert_close(both.sigma2, alone.sigma2, rtol=1e-3, atol=0)


def _reverse_mode_jacobian(model, data, columns, x0=None):
    """Free-run residuals (M,) from ``x0`` (zero) and their Jacobian (M, q [+ nx]) with
    respect to ``columns`` (and ``x0`` when given) by reverse-mode autograd through the
    simulation, one vectorised backward pass over all rows."""
    training = importlib.import_module("sysid.continuous.training")
    records = training._Records(data, model, torch.float64, torch.device("cpu"))
    start = torch.zeros(1, model.nx, dtype=torch.float64) if x0 is None else x0
    b, g = torch.zeros(1, dtype=torch.int64), torch.zeros(1, dtype=torch.int64)
    T = data.N - 1
    r = (data.y - training._simulate_windows(model, records, start, b, g, T)[0]).reshape(-1)
    leaves = columns + ([x0] if x0 is not None else [])
    rows = torch.eye(r.numel(), dtype=r.dtype)
    grads = torch.autograd.grad(r, leaves, grad_outputs=rows, is_grads_batched=True)
    J = torch.cat([gr.reshape(r.numel(), -1) for gr in grads], -1)
    return r.detach(), J


class MeasuredWithGain(HybridSpring):
    """HybridSpring whose output map has a parameter: y = g x1."""

    def __init__(self):
        super().__init__(k0=3.0)
        self.gain = nn.Parameter(torch.tensor(1.3, dtype=torch.float64))

    def output(self, x, u):
        return self.gain * x[..., :1]


@pytest.mark.parametrize("window", [7, 1000])
@pytest.mark.parametrize("x0", ["zero", "estimate"])
@pytest.mark.parametrize("build", [lambda: HybridSpring(k0=3.0), MeasuredWithGain])
def test_the_forward_sensitivity_jacobian_equals_reverse_mode_autograd(
    x0, build, window, monkeypatch
):
    """The free-run Jacobian behind the covariance (forward sensitivities over the weights
    and initial states, run in windows chained by the chain rule, plus the output map's own
    parameters, a few rows per reverse pass), reduced to its triangular factor R, against
    reverse-mode autograd through the whole simulation: the same residuals and R'R = J'J
    with the columns in the factor's order (nuisance first)."""
    training = importlib.import_module("sysid.continuous.training")
    monkeypatch.setattr(training, "_ROWS_PER_PASS", 7)
    monkeypatch.setattr(training, "_JACOBIAN_WINDOW", window)
    data = spring(60, seed=3, noise=0.01)
    model = build()
    with torch.no_grad():
        model.res[2].weight.normal_(generator=torch.Generator().manual_seed(2))
    records = training._Records(data, model, torch.float64, torch.device("cpu"))
    output_is_state = not isinstance(model, MeasuredWithGain)
    net = training._Trainable(
        model, x0, records, 0, 8, torch.Generator().manual_seed(0), output_is_state
    )
    columns = [model.log_k, *model.res.parameters()]
    columns += [model.gain] if isinstance(model, MeasuredWithGain) else []
    r, R = training._free_run_jacobian(net, records, columns, 1)
    start = training._record_states(net, records)[0][2].clone().requires_grad_(True)
    r_ref, J_ref = _reverse_mode_jacobian(model, data, columns, start)
    if x0 == "zero":  # known initial states: not among the columns
        J_ref = J_ref[:, :-2]
    J_ref = torch.cat([J_ref[:, 1:], J_ref[:, :1]], -1)  # the nuisance first, then log_k
    torch.testing.assert_close(r, r_ref, rtol=1e-12, atol=1e-12)
    assert R.shape == (J_ref.shape[1], J_ref.shape[1]) and torch.equal(R, R.triu())
    gram = J_ref.T @ J_ref
    torch.testing.assert_close(R.T @ R, gram, rtol=1e-9, atol=1e-11 * gram.abs().max())


def _small_run(model=None, data=None, **kw):
    """A short seeded Adam training of ``model`` (default ``MLPRHS(hidden=8)``) on ``data``
    (default 120 noisy samples of the first-order plant)."""
    data = first_order(120, seed=2, noise=0.01) if data is None else data
    options = dict(
        method="adam",
        horizon=10,
        batch_size=8,
        epochs=4,
        steps_per_epoch=3,
        lr=1e-2,
        x0="encoder",
        n_init=3,
        seed=5,
    )
    options.update(kw)
    return sysid.fit(MLPRHS(hidden=8) if model is None else model, data, **options)


def test_bit_reproducible_from_seed():
    a, b = _small_run(), _small_run()
    for p, q in zip(a.model.parameters(), b.model.parameters(), strict=True):
        assert torch.equal(p, q)
    for p, q in zip(a.encoder.parameters(), b.encoder.parameters(), strict=True):
        assert torch.equal(p, q)
    assert torch.equal(a.train_loss, b.train_loss)
    c = _small_run(seed=6)
    assert not torch.equal(next(a.model.parameters()), next(c.model.parameters()))


def test_checkpoint_resume_equals_uninterrupted_run(tmp_path):
    common = dict(epochs=6, schedule="cosine", x0="estimate")
    full = _small_run(**common)
    path = tmp_path / "train.ckpt"

    def interrupt(epoch, state):
        if epoch == 2:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        _small_run(checkpoint=path, checkpoint_every=2, callback=interrupt, **common)
    assert torch.load(path, weights_only=False)["state"]["epoch"] == 2
    resumed = _small_run(checkpoint=path, checkpoint_every=2, **common)
    for p, q in zip(full.model.parameters(), resumed.model.parameters(), strict=True):
        assert torch.equal(p, q)
    assert torch.equal(full.x0_table, resumed.x0_table)
    assert torch.equal(full.train_loss, resumed.train_loss)
    with pytest.raises(InputValidationError, match="checkpoint"):
        _small_run(checkpoint=path, **{**common, "batch_size": 4})


def test_a_completed_checkpoint_trains_on_to_a_larger_total(tmp_path):
    """epochs is the total also when resuming: a checkpoint of a training completed after 2
    epochs, run again with epochs=4, trains epochs 3 and 4 (it returned the 2-epoch model as
    "completed") and equals the uninterrupted 4-epoch run; under a schedule planned for 2
    epochs it is refused by name."""
    full = _small_run(epochs=4, x0="estimate")
    path = tmp_path / "train.ckpt"
    _small_run(epochs=2, x0="estimate", checkpoint=path)
    extended = _small_run(epochs=4, x0="estimate", checkpoint=path)
    assert extended.status == "completed" and extended.train_loss.shape[0] == 4
    for p, q in zip(full.model.parameters(), extended.model.parameters(), strict=True):
        assert torch.equal(p, q)
    scheduled = tmp_path / "scheduled.ckpt"
    _small_run(epochs=2, x0="estimate", schedule="cosine", checkpoint=scheduled)
    with pytest.raises(InputValidationError, match="schedule planned"):
        _small_run(epochs=4, x0="estimate", schedule="cosine", checkpoint=scheduled)


def test_non_finite_guard_restores_best_model():
    # RK4 at h a = 50 * 0.1 (or -5.1) diverges over 200 steps: the first Adam step (about lr
    # = 50) makes every later loss overflow
    data = first_order(260, seed=0)
    model = LinearRHS([-1.0], [1.0])
    result = sysid.fit(
        model,
        data,
        method="adam",
        horizon=200,
        batch_size=4,
        epochs=5,
        steps_per_epoch=1,
        lr=50.0,
        x0="zero",
        seed=0,
    )
    assert result.status == "non_finite" and not bool(result.converged)
    assert any("non-finite" in m and "restored" in m for m in result.messages)
    assert torch.equal(result.model.a, model.a) and torch.equal(result.model.b, model.b)
    assert result.train_loss.numel() == 0


def test_early_stopping_on_validation_plateau():
    data, val = first_order(100, seed=0), first_order(80, seed=1)
    result = sysid.fit(
        MLPRHS(hidden=4),
        data,
        method="adam",
        horizon=5,
        batch_size=4,
        epochs=50,
        steps_per_epoch=1,
        lr=0.0,
        x0="zero",
        validation=val,
        patience=3,
    )
    # lr = 0: the validation loss is the same every epoch, so it stops after 1 + patience
    assert result.status == "early_stopped"
    assert result.train_loss.numel() == 4
    assert torch.all(result.validation_loss == result.validation_loss[0])


def test_input_model_untouched():
    model = MLPRHS(hidden=8)
    before = params_of(model)
    result = sysid.fit(
        model,
        first_order(100),
        method="adam",
        horizon=5,
        epochs=2,
        steps_per_epoch=2,
        batch_size=4,
        x0="zero",
    )
    assert result.model is not model
    for p, q in zip(before, model.parameters(), strict=True):
        assert torch.equal(p, q) and q.grad is None
    assert any(
        not torch.equal(p, q) for p, q in zip(before, result.model.parameters(), strict=True)
    )


def test_implicit_method_training_decreases_loss():
    # stiff diagonal plant (eigenvalues -1 and -200, h lambda = -20: RK4 would diverge)
    A, B = np.diag([-1.0, -200.0]), np.array([[1.0], [200.0]])
    data = zoh_data(A, B, np.eye(2), 80, 0.1, seed=4)
    model = LinearRHS([-0.5, -100.0], [1.5, 120.0], method="radau_iia")
    result = sysid.fit(
        model,
        data,
        method="adam",
        horizon=10,
        batch_size=8,
        epochs=6,
        steps_per_epoch=2,
        lr=0.05,
        x0="zero",
        seed=0,
    )
    assert result.status == "completed"
    mse0 = float((simulate(model, data) - data.y).pow(2).mean())
    mse1 = float((simulate(result.model, data) - data.y).pow(2).mean())
    assert mse1 < 0.5 * mse0


def test_foh_input_between_samples_matches_closed_form():
    # x' = -x + u with u linear between samples: exact x_{k+1} = e^{-h} x_k
    # + u_k (1 - e^{-h}) + (u_{k+1} - u_k)/h (h - 1 + e^{-h})
    rng = np.random.default_rng(0)
    N, h = 40, 0.1
    u = rng.uniform(-1, 1, N)
    exact = [0.0]
    for k in range(N - 1):  # reference recursion
        slope = (u[k + 1] - u[k]) / h
        exact.append(
            np.exp(-h) * exact[-1] + u[k] * (1 - np.exp(-h)) + slope * (h - 1 + np.exp(-h))
        )
    data = sysid.IOData(torch.tensor(u)[:, None], torch.zeros(N, 1), h, intersample="foh")
    model = LinearRHS([-1.0], [1.0])
    model.substeps = 4  # RK4 error ~1e-6 at one step per interval, / 4^4 here
    y = simulate(model, data)[:, 0].numpy()
    assert np.abs(y - np.array(exact)).max() < 1e-8


@pytest.mark.parametrize(
    ("kwargs", "words"),
    [
        (dict(horizon=500), "horizon T = 500"),
        (dict(method="sgd"), "method"),
        (dict(criterion="simulation"), "criterion"),
        (dict(x0="bogus"), "x0 must be one of"),
        (dict(horizon=[(5, 10)]), "start at epoch 0"),
        (dict(batch_size=0), "batch_size"),
        # clip < 0 made clip_grad_norm_ flip the gradient (ascent), 0 zeroed it
        (dict(clip=-1.0), "clip .* > 0, got -1.0"),
        (dict(clip=0.0), "clip .* > 0, got 0.0"),
        (dict(clip=math.inf), "clip .* > 0, got inf"),
        # -1 trained nothing, 0 fell back to the default, 2.5 a raw TypeError
        (dict(steps_per_epoch=-1), "steps_per_epoch .* integer >= 1, got -1"),
        (dict(steps_per_epoch=0), "steps_per_epoch .* integer >= 1, got 0"),
        (dict(steps_per_epoch=2.5), "steps_per_epoch .* integer >= 1, got 2.5"),
        (dict(method="lbfgs", lbfgs_max_iter=0), "lbfgs_max_iter must be an integer >= 1"),
        (dict(lr=-1.0), "lr must be a finite number >= 0, got -1.0"),
        (dict(lr=math.nan), "lr must be a finite number >= 0, got nan"),
        (dict(weight_decay=-1.0), "weight_decay must be a finite number >= 0"),
        (dict(x0="encoder", n_init=3, encoder_hidden=0), "encoder_hidden must be an integer"),
        (dict(seed=1.5), "seed must be an integer, got 1.5"),
        (dict(patience=0), "patience .* integer >= 1, got 0"),
        # an option train does not have raised train's TypeError
        (dict(foo=3), r"unexpected option\(s\) \['foo'\].*'batch_size', 'callback'"),
        (dict(method="lbfgs", epoch=2), r"unexpected option\(s\) \['epoch'\].*'epochs'"),
    ],
)
def test_bad_options(kwargs, words):
    data = first_order(100)
    options = dict(method="adam", horizon=5, epochs=1)
    options.update(kwargs)
    with pytest.raises(InputValidationError, match=words):
        sysid.fit(MLPRHS(hidden=4), data, **options)


def test_bad_data():
    model = MLPRHS(hidden=4)
    two_outputs = sysid.IOData(torch.zeros(50, 1), torch.zeros(50, 2), 0.1)
    with pytest.raises(InputValidationError, match="ny = 2"):
        sysid.fit(model, two_outputs, method="adam", horizon=5, epochs=1)
    data = first_order(50)
    data.y[7, 0] = math.nan
    with pytest.raises(InputValidationError, match="non-finite value at index"):
        sysid.fit(model, data, method="adam", horizon=5, epochs=1)
    with pytest.raises(InputValidationError, match="nn.Module"):
        sysid.fit(sysid.ARX(1, 1, 1), first_order(50), method="adam")
    with pytest.raises(InputValidationError, match="neural models"):
        sysid.fit(sysid.ARX(1, 1, 1), first_order(50), horizon=5)


def test_validate_skip_per_experiment_and_refused_out_of_range():
    """validate(data, skip) leaves out the first ``skip`` samples of every experiment (the
    rule of IOData.samples_after): the fit equals a numpy computation over those samples; a
    negative skip (it wrapped around: 53.62 % instead of an error) and one longer than an
    experiment (a raw RuntimeError) are refused by name."""
    data = sysid.IOData.experiments([first_order(50, seed=1), first_order(31, seed=2)])
    result = sysid.fit(
        LinearRHS([-0.8], [1.2]), data, horizon=4, batch_size=4, epochs=1, lr=0.0, x0="zero"
    )
    y = data.y[:, 0].numpy()
    yhat = simulate(result.model, data)[:, 0].numpy()
    skip = 5
    keep = np.r_[skip:50, 50 + skip : 81]
    e, d = y[keep] - yhat[keep], y[keep] - y[keep].mean()
    expected = 100 * (1 - np.linalg.norm(e) / np.linalg.norm(d))
    got = float(result.validate(data, skip=skip)["fit_percent"][0])
    assert abs(got - expected) < 1e-9
    for bad in (-3, 30, 60, 2.5):
        with pytest.raises(InputValidationError, match="validate: skip must be an integer"):
            result.validate(data, skip=bad)
    encoded = _small_run(epochs=1)  # n_init = 3: samples 0..2 are not simulated
    with pytest.raises(InputValidationError, match="n_init = 3"):
        encoded.validate(first_order(120, seed=2), skip=1)


def test_simulate_x0_per_data_set_and_wrong_shape():
    """x0 (nx,) or (*batch, nx): per data set it starts each free run there (x' = -x from
    x0 is x0 exp(-t)); any other shape is refused by name (it was a raw RuntimeError from
    expand)."""
    N, h = 30, 0.1
    data = sysid.IOData(torch.zeros(2, N, 1, dtype=torch.float64), torch.zeros(2, N, 1), h)
    model = LinearRHS([-1.0], [1.0])
    model.substeps = 4  # RK4 error ~1e-6 at one step per interval, / 4^4 here
    x0 = torch.tensor([[1.0], [2.0]], dtype=torch.float64)
    y = simulate(model, data, x0=x0)[..., 0].numpy()
    exact = np.array([[1.0], [2.0]]) * np.exp(-h * np.arange(N))
    assert np.abs(y - exact).max() < 1e-8
    for bad in (torch.zeros(3), torch.zeros(4, 1), torch.zeros(1, 2, 1)):
        with pytest.raises(InputValidationError, match=r"x0 has shape .*\(2, 1\)"):
            simulate(model, data, x0=bad)


def test_a_checkpoint_of_other_options_data_or_model_is_refused(tmp_path):
    """Resuming with another lr, weight_decay or clip was silently the checkpoint's run
    (bit-identical to it); other data or another model raised a raw RuntimeError from
    load_state_dict. Each is refused by name."""
    path = tmp_path / "train.ckpt"
    options = dict(x0="estimate", epochs=2, checkpoint=path)
    _small_run(**options)
    for changed in (dict(lr=2e-2), dict(weight_decay=1e-3), dict(clip=1.0)):
        (name,) = changed
        with pytest.raises(InputValidationError, match=f"differing: {name}"):
            _small_run(**{**options, "epochs": 4, **changed})
    resume = {**options, "epochs": 4}
    _small_run(**resume)  # the same options resume
    with pytest.raises(InputValidationError, match="holds the parameters of another model"):
        _small_run(data=first_order(100, seed=2), **resume)  # 100 samples, not 120
    with pytest.raises(InputValidationError, match="holds the parameters of another model"):
        _small_run(model=MLPRHS(hidden=4), **resume)


def test_autonomous_data_trains_alike_under_band_limited_and_foh():
    """nu = 0: intersample="bl" trains exactly as "foh" (no input to interpolate; the rfft
    of the empty input raised an MKL error), and fits the decay y = exp(-t)."""
    N, h = 60, 0.1
    y = torch.exp(-h * torch.arange(N, dtype=torch.float64))[:, None]
    results = {}
    for kind in ("foh", "bl"):
        data = sysid.IOData(torch.zeros(N, 0, dtype=torch.float64), y, h, intersample=kind)
        model = MLPRHS(nu=0, hidden=4)
        results[kind] = sysid.fit(
            model, data, method="lbfgs", horizon=10, epochs=3, lbfgs_max_iter=10, x0="estimate"
        )
    for p, q in zip(
        results["foh"].model.parameters(), results["bl"].model.parameters(), strict=True
    ):
        assert torch.equal(p, q)
    assert torch.equal(results["foh"].train_loss, results["bl"].train_loss)
    assert float(results["bl"].train_loss[-1]) < 1e-4  # outputs of order 0.5


def test_a_diverging_free_run_is_not_converged_and_warns():
    """x' = 20 x + u barely trained (lr = 1e-12): RK4 at h a = 2 grows 7-fold per sample, so
    the free run over 300 samples reaches ~1e250 and its squared residuals overflow. It was
    reported "completed", converged, sigma2 = inf and no warning; now not converged, not
    stable, a message and an UnstableModelWarning."""
    data = first_order(300, seed=0)
    with pytest.warns(sysid.UnstableModelWarning, match="free run .* diverges"):
        result = sysid.fit(
            LinearRHS([20.0], [1.0]),
            data,
            horizon=5,
            batch_size=4,
            epochs=1,
            steps_per_epoch=1,
            lr=1e-12,
            x0="zero",
        )
    assert result.status == "completed"  # every epoch ran
    assert not math.isfinite(float(result.sigma2))
    assert not bool(result.converged) and not bool(result.stable)
    assert any("diverges" in m for m in result.messages)
    result.summary()


def test_a_finite_but_exploding_free_run_is_not_converged():
    """x' = x + u barely trained: the free run grows as e^t to about 1e13 over 30 s, finite,
    with residuals 1e12 times the outputs in norm. It was "completed", converged and
    stable; now not converged and not stable, with an UnstableModelWarning. The true
    x' = -x + u model of the same data stays stable."""
    data = first_order(300, seed=0)
    options = dict(horizon=5, batch_size=4, epochs=1, steps_per_epoch=1, x0="zero")
    with pytest.warns(sysid.UnstableModelWarning, match="free run .* diverges"):
        result = sysid.fit(LinearRHS([1.0], [1.0]), data, lr=1e-12, **options)
    assert math.isfinite(float(result.sigma2))
    assert not bool(result.converged) and not bool(result.stable)
    with warnings.catch_warnings():
        warnings.simplefilter("error", sysid.UnstableModelWarning)
        result = sysid.fit(LinearRHS([-1.0], [1.0]), data, lr=1e-12, **options)
    assert bool(result.converged) and bool(result.stable)
