"""Gradients of fixed-step explicit Runge-Kutta runs (notes eq. 6.26): failed samples do not
poison the gradient of shared parameters, checkpointed segments give the gradients of the
plain run, and a graph that cannot fit in memory is refused before the run."""

import pytest
import torch

import integrators.explicit as explicit
from integrators import GraphMemoryError, InputValidationError, Status, odeint

ESCAPE_T = torch.linspace(0.0, 1.0, 11, dtype=torch.float64)
X0_BY_BATCH = {
    (): [2.0],  # x' = p x^2 escapes at t = 1 / (p x0) = 0.5 (notes eq. 1.44)
    (1,): [[2.0]],
    (3,): [[0.1], [2.0], [-0.3]],
}


def _escape_problem(input_kind):
    """x' = p x^2 (+ 0.1 u) with a shared parameter p, and the u= argument of odeint."""
    p = torch.nn.Parameter(torch.tensor(1.0, dtype=torch.float64))
    if input_kind == "none":
        return p, (lambda t, x: p * x**2), None
    f = lambda t, x, u: p * x**2 + 0.1 * u  # noqa: E731
    if input_kind == "zoh":
        return p, f, torch.sin(3 * ESCAPE_T)[:, None]
    return p, f, lambda t: torch.sin(3 * t).reshape(1)


@pytest.mark.parametrize("input_kind", ["none", "zoh", "callable"])
@pytest.mark.parametrize("batch", [(), (1,), (3,)])
@pytest.mark.parametrize("options", [{}, {"checkpoint": 3}, {"substeps": 3, "checkpoint": 2}])
def test_blown_up_sample_does_not_poison_shared_gradient(
    central_difference, input_kind, batch, options
):
    """The loss reads only finite outputs (those below 1e3, before the escaping sample
    overflows): d loss/dp equals central differences; the outputs, status and messages are
    those of the run without autograd."""
    p, f, u = _escape_problem(input_kind)
    x0 = torch.tensor(X0_BY_BATCH[batch], dtype=torch.float64)
    with torch.no_grad():
        reference = odeint(f, x0, ESCAPE_T, u=u, **options)
    assert not torch.isfinite(reference.x).all()  # the x0 = 2 sample escapes
    mask = reference.x.abs() < 1e3  # finite outputs where central differences are accurate

    def loss():
        return odeint(f, x0, ESCAPE_T, u=u, **options).x[mask].sum()

    sol = odeint(f, x0, ESCAPE_T, u=u, **options)
    (grad,) = torch.autograd.grad(sol.x[mask].sum(), p)
    torch.testing.assert_close(grad, central_difference(loss, p, 1e-6), rtol=1e-6, atol=0)
    torch.testing.assert_close(sol.x, reference.x, rtol=0, atol=0, equal_nan=True)
    assert torch.equal(sol.status, reference.status)
    assert sol.messages == reference.messages
    assert (sol.status == Status.NON_FINITE).sum() == 1


def test_blown_up_sample_gradient_equals_finite_sample_alone():
    """Sample 0's gradient in a batch with an escaping sample is its gradient alone; the
    initial-state gradients of both samples are finite."""
    p, f, _ = _escape_problem("none")
    x0 = torch.tensor([[0.1], [2.0]], dtype=torch.float64, requires_grad=True)
    sol = odeint(f, x0, ESCAPE_T)
    assert sol.status.tolist() == [Status.SUCCESS, Status.NON_FINITE]
    mask = torch.isfinite(sol.x.detach())
    g_p, g_x0 = torch.autograd.grad(sol.x[mask].sum(), (p, x0), retain_graph=True)
    assert torch.isfinite(g_x0).all()
    (alone,) = torch.autograd.grad(odeint(f, x0[:1].detach(), ESCAPE_T).x.sum(), p)
    (escaping,) = torch.autograd.grad(sol.x[1][mask[1]].sum(), p)
    torch.testing.assert_close(g_p, alone + escaping, rtol=1e-13, atol=0)


def test_blown_up_sample_compiled_and_checkpointed_run(central_difference, monkeypatch):
    """compile=True, checkpoint=True with compiled chunks of 2 steps (a short graph to
    compile): two compiled probe chunks, then eager segments of 8 steps (sqrt(40) rounded up
    to whole chunks); the sample escapes inside a segment and the rerun starts there."""
    monkeypatch.setattr(explicit, "CHUNK_STEPS", 2)
    p, f, _ = _escape_problem("none")
    x0 = torch.tensor(X0_BY_BATCH[(3,)], dtype=torch.float64)
    t = torch.linspace(0.0, 1.0, 41, dtype=torch.float64)
    sol = odeint(f, x0, t, compile=True, checkpoint=True)
    # compiled, or an eager fallback reported with its reason (dynamo's process-wide state
    # can refuse a compilation late in a long process)
    extra = sol.stats.extra
    assert extra["compiled"] != bool(extra["compile_fallback"]), extra
    assert extra["checkpoint_steps"] == 8
    mask = sol.x.detach().abs() < 1e3
    (grad,) = torch.autograd.grad(sol.x[mask].sum(), p)

    def loss():
        return odeint(f, x0, t, compile=False).x[mask].sum()

    torch.testing.assert_close(grad, central_difference(loss, p, 1e-6), rtol=1e-6, atol=0)
    assert sol.status.tolist() == [Status.SUCCESS, Status.NON_FINITE, Status.SUCCESS]


def _vdp(mu):
    """Van der Pol x1' = x2, x2' = mu (1 - x1^2) x2 - x1 (+ u) (notes eq. 6.43)."""

    def f(t, x, u=None):
        x1, x2 = x[..., 0], x[..., 1]
        dx2 = mu * (1 - x1**2) * x2 - x1
        return torch.stack([x2, dx2 if u is None else dx2 + u[..., 0]], dim=-1)

    return f


def _vdp_gradients(batch, input_kind, t, **options):
    mu = torch.nn.Parameter(torch.tensor(1.3, dtype=torch.float64))
    x0 = torch.tensor([2.0, 0.0], dtype=torch.float64).expand(*batch, 2).clone()
    x0 = x0 + 0.1 * torch.arange(x0.numel(), dtype=torch.float64).reshape(x0.shape)
    x0.requires_grad_(True)
    u = None
    if input_kind == "zoh":
        u = torch.cos(t)[:, None].expand(*batch, -1, 1).clone().requires_grad_(True)
    elif input_kind == "callable":
        u = lambda s: torch.cos(2 * s).reshape(1)  # noqa: E731
    sol = odeint(_vdp(mu), x0, t, u=u, **options)
    weights = torch.sin(torch.arange(sol.x.numel(), dtype=torch.float64)).reshape(sol.x.shape)
    leaves = [mu, x0] + ([u] if isinstance(u, torch.Tensor) else [])
    return sol, torch.autograd.grad((sol.x * weights).sum(), leaves)


@pytest.mark.parametrize("checkpoint", [True, 7])
@pytest.mark.parametrize("input_kind", ["none", "zoh", "callable"])
@pytest.mark.parametrize("batch", [(), (1,), (3,)])
def test_checkpointed_gradients_equal_plain_gradients(batch, input_kind, checkpoint):
    t = torch.linspace(0.0, 8.0, 161, dtype=torch.float64)
    plain, g_plain = _vdp_gradients(batch, input_kind, t, substeps=2)
    ck, g_ck = _vdp_gradients(batch, input_kind, t, substeps=2, checkpoint=checkpoint)
    assert ck.stats.extra["checkpoint_steps"] == (18 if checkpoint is True else 7)
    assert plain.stats.extra["checkpoint_steps"] is None
    torch.testing.assert_close(ck.x, plain.x, rtol=0, atol=0)
    for a, b in zip(g_ck, g_plain, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)


def test_checkpointed_segments_inside_output_intervals():
    """Segments that end inside an output interval of many substeps (t has 3 points, 600
    steps, segments of 25 steps)."""
    t = torch.linspace(0.0, 4.0, 3, dtype=torch.float64)
    plain, g_plain = _vdp_gradients((3,), "zoh", t, substeps=300)
    ck, g_ck = _vdp_gradients((3,), "zoh", t, substeps=300, checkpoint=True)
    assert ck.stats.extra["checkpoint_steps"] == 25
    torch.testing.assert_close(ck.x, plain.x, rtol=0, atol=0)
    for a, b in zip(g_ck, g_plain, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)


def test_graph_too_large_for_memory_is_refused_before_the_run(monkeypatch):
    """With a (monkeypatched) 250 MiB of available memory, 1000 RK4 steps of 2048 Van der
    Pol oscillators with autograd (about 0.3 MB of graph per step) are refused after the two
    one-step probe chunks, naming the remedies; checkpoint=True (segments of 32 steps) fits
    and runs; without autograd nothing is checked."""
    calls = []
    mu = torch.nn.Parameter(torch.tensor(1.0, dtype=torch.float64))
    vdp = _vdp(mu)

    def f(t, x):
        calls.append(1)
        return vdp(t, x)

    x0 = torch.tensor([[2.0, 0.0]], dtype=torch.float64).expand(2048, 2).clone()
    t = torch.linspace(0.0, 10.0, 1001, dtype=torch.float64)
    monkeypatch.setattr(explicit, "available_bytes", lambda device: 250 * 2**20)
    with pytest.raises(GraphMemoryError) as info:
        odeint(f, x0, t, compile=False)
    assert isinstance(info.value, MemoryError)
    assert len(calls) == 1 + 2 * 4  # odeint's probe of f, two one-step chunks of 4 stages
    message = str(info.value)
    for words in ("GiB", "1001 times", "torch.no_grad()", "fewer output times", "checkpoint=True"):
        assert words in message, words
    sol = odeint(f, x0, t, compile=False, checkpoint=True)
    assert sol.success and sol.stats.extra["checkpoint_steps"] == 32
    with torch.no_grad():
        assert odeint(f, x0, t, compile=False).success


def test_graph_memory_estimate_matches_saved_tensors(monkeypatch):
    """The extrapolated estimate: bytes of the saved tensors and graph nodes of one step
    (an independent count over a plain RK4 step of the same model) times the steps."""
    mu = torch.nn.Parameter(torch.tensor(1.0, dtype=torch.float64))
    f = _vdp(mu)
    x0 = torch.tensor([[2.0, 0.0]], dtype=torch.float64).expand(256, 2).clone()
    seen = {}
    monkeypatch.setattr(
        explicit, "_check_graph_memory", lambda *args: seen.setdefault("args", args)
    )
    odeint(f, x0, torch.linspace(0.0, 1.0, 101, dtype=torch.float64), compile=False)
    data, nodes, n_left, seg, state_bytes, T, _ = seen["args"]
    storages = {}

    def pack(tensor):
        storages[tensor.untyped_storage().data_ptr()] = tensor.untyped_storage().nbytes()
        return tensor

    h = 0.01
    x = x0.clone().requires_grad_(True)
    with torch.autograd.graph.saved_tensors_hooks(pack, lambda tensor: tensor):
        k1 = f(0.0, x)
        k2 = f(0.0, x + h / 2 * k1)
        k3 = f(0.0, x + h / 2 * k2)
        k4 = f(0.0, x + h * k3)
    storages.pop(mu.untyped_storage().data_ptr())
    assert data == sum(storages.values())
    assert 30 <= nodes <= 50
    assert (n_left, seg, state_bytes, T) == (98, None, 256 * 2 * 8, 101)
    del k4


def test_checkpoint_argument_is_validated():
    f = lambda t, x: -x  # noqa: E731
    x0 = torch.ones(2, dtype=torch.float64)
    t = torch.linspace(0.0, 1.0, 5, dtype=torch.float64)
    for bad in (0, -3, 1.5, "yes"):
        with pytest.raises(InputValidationError, match="checkpoint"):
            odeint(f, x0, t, checkpoint=bad)
    with pytest.raises(InputValidationError, match="fixed-step explicit"):
        odeint(f, x0, t, method="dopri5", checkpoint=True)
    with pytest.raises(InputValidationError, match="fixed-step explicit"):
        odeint(f, x0, t, method="radau_iia", stages=3, checkpoint=True)
    assert odeint(f, x0, t, method="dopri5", adaptive=False, checkpoint=2).success


def test_compiled_gradient_of_a_model_calling_autograd_inside_f_runs_eagerly(monkeypatch):
    """A Lagrangian plant calls autograd inside f; aot_autograd cannot differentiate the
    double-backward graph of a compiled chunk, so with autograd on the run falls back to eager
    (reported), and its gradient equals the eager one (without the fallback: RuntimeError in
    the caller's backward). The fallback is decided once: the run's later chunks neither
    compile-run nor probe again (each chunk repeated the eager reference, the compiled chunk
    and the backward probe), and no compiled step is reported."""
    from integrators import explicit
    from integrators._fast import compiled
    from sysid.zoo import SpringMass

    monkeypatch.setattr(explicit, "CHUNK_STEPS", 2)  # several chunks per run
    probes = []
    backward_works = compiled._backward_works
    monkeypatch.setattr(
        compiled, "_backward_works", lambda *a: probes.append(1) or backward_works(*a)
    )
    plant = SpringMass()
    x0 = torch.tensor([[1.5, 0.0], [1.0, 0.2]], dtype=torch.float64)
    t = torch.linspace(0.0, 1.0, 6, dtype=torch.float64)
    grads, extras = [], []
    for compile in (False, True):
        sol = odeint(plant, x0, t, substeps=4, compile=compile)
        grads.append(torch.autograd.grad(sol.x[..., -1, :].sum(), plant.k)[0])
        extras.append(sol.stats.extra)
    assert extras[0]["compiled"] is False and extras[0]["compile_fallback"] is None
    # compiled (when dynamo already runs the model's frames eagerly, the probe passes) or an
    # eager fallback reported with its reason
    assert extras[1]["compiled"] != bool(extras[1]["compile_fallback"]), extras[1]
    assert len(probes) <= 1  # none where the compiled chunk was given up before the probe
    if extras[1]["compile_fallback"]:
        assert extras[1]["compiled_from_step"] is None
    torch.testing.assert_close(grads[1], grads[0], rtol=1e-13, atol=0)
