"""Every zoo plant through every integrator and every driver the dispatch can choose.

The matrix is generated: plants from :func:`sysid.zoo.scenarios.scenarios` (explicit ODEs,
mechanical plants in their explicit form eq. 2.42) and :func:`dae_scenarios` (index-1 DAEs),
drivers from :data:`DRIVERS`, batch shapes from :data:`BATCH_SHAPES`. Each run is compared
with scipy's DOP853 (Radau for stiff plants) at rtol = atol = 1e-12 on every batch member,
each driver's gradient of one physical parameter with central differences, and each fast
path with the general path it replaces. A new plant joins the matrix through its scenario, a
new driver through one row of :data:`DRIVERS`.
"""

from __future__ import annotations

import dataclasses
import functools
import importlib
import inspect
import math
import warnings
from dataclasses import dataclass, field

import numpy as np
import pytest
import scipy.optimize
import torch
from scipy.integrate import solve_ivp

import sysid.zoo
from integrators import HighIndexError, ImplicitDAE, InputValidationError, Status, daeint, odeint
from integrators._irk_linalg import _DENSE_MAX as HOST_MAX_ROWS
from sysid.mechanics import LagrangianSystem
from sysid.zoo import scenarios as zoo_scenarios

DT = torch.float64
BATCH_SHAPES = [(), (1,), (3,)]
#: output intervals of every run; fixed-step methods take the scenario's ``substeps`` per
#: interval
N_INTERVALS = 10
#: tolerances of the adaptive drivers (the reference is at 1e-12)
RTOL, ATOL = 1e-8, 1e-10
#: a member of a batch starts from x0 scaled by this factor (then made consistent)
MEMBER_SCALE = (1.0, 0.95, 1.05)


@dataclass(frozen=True)
class Driver:
    """One path through ``odeint``: its options, the error it must reach against the reference
    (max-norm relative to 1 + max |x_ref|), the relative tolerance of its gradient against
    central differences, and what ``stats.extra`` must say it ran (``"driver"`` may depend on
    the batch shape)."""

    name: str
    options: dict
    tol: float
    grad_rtol: float
    explicit: bool = False
    extra: dict = field(default_factory=dict)
    max_newton_rows: int | None = None

    def applies(self, sc) -> bool:
        """Whether the dispatch can run this driver on the scenario's plant: explicit methods
        skip stiff plants, the host loops take Newton matrices of at most
        ``max_newton_rows`` rows (3 stages x nx)."""
        if sc.stiff and self.explicit:
            return False
        return self.max_newton_rows is None or 3 * len(sc.x0) <= self.max_newton_rows


_FIXED = dict(rtol=1e-12)
FIXED_METHODS = ("rk4", "gauss_legendre")
_ADAPTIVE = dict(rtol=RTOL, atol=ATOL)
#: errors against the reference: fixed steps (the scenario's substeps) reach 1e-11 .. 5e-5 on
#: the zoo (the springy cranes least), the adaptive drivers at RTOL about 10 RTOL
FIXED_TOL, ADAPTIVE_TOL = 1e-4, 1e-6
DRIVERS = [
    Driver("rk4 eager", dict(method="rk4", compile=False), FIXED_TOL, 1e-6,
           explicit=True, extra={"compiled": False}),
    Driver("rk4 compiled", dict(method="rk4", compile=True), FIXED_TOL, 1e-6,
           explicit=True, extra={"compiled": True, "compile_fallback": None}),
    Driver("dopri5", dict(method="dopri5", **_ADAPTIVE), ADAPTIVE_TOL, 1e-4, explicit=True),
    Driver("gauss fixed", dict(method="gauss_legendre", stages=2, **_FIXED), FIXED_TOL, 1e-6,
           extra={"driver": "torch"}),
    Driver("radau fixed", dict(method="radau_iia", adaptive=False, **_FIXED), FIXED_TOL, 1e-6,
           extra={"driver": "torch"}),
    Driver("radau adaptive torch", dict(method="radau_iia", host_loop=False, **_ADAPTIVE),
           ADAPTIVE_TOL, 1e-4, extra={"driver": "torch"}),
    Driver("radau adaptive host", dict(method="radau_iia", host_loop=True, **_ADAPTIVE),
           ADAPTIVE_TOL, 1e-4, max_newton_rows=HOST_MAX_ROWS,
           extra={"driver": {(): "host, one trajectory", (1,): "host, one trajectory",
                             (3,): "host"}}),
]  # fmt: skip
DRIVER = {d.name: d for d in DRIVERS}
SCENARIOS = {s.name: s for s in zoo_scenarios.scenarios()}


def _cases(shapes=None):
    """(plant, driver[, batch shape]) triples: explicit drivers skip stiff plants, and the
    compiled driver (seconds of compilation per plant) runs at the largest batch shape only."""
    for sc in SCENARIOS.values():
        for drv in DRIVERS:
            if not drv.applies(sc):
                continue
            if shapes is None:
                yield pytest.param(sc.name, drv.name, id=f"{sc.name}-{drv.name}")
                continue
            for shape in shapes:
                if drv.name == "rk4 compiled" and shape != shapes[-1]:
                    continue
                yield pytest.param(sc.name, drv.name, shape, id=f"{sc.name}-{drv.name}-{shape}")


def _grid(t_end: float) -> torch.Tensor:
    return torch.linspace(0.0, t_end, N_INTERVALS + 1, dtype=DT)


def _member_x0(sc, plant, k: int) -> torch.Tensor:
    """The initial state of batch member ``k``: x0 scaled, projected onto the constraints."""
    x0 = MEMBER_SCALE[k] * torch.tensor(sc.x0, dtype=DT)
    if getattr(plant, "is_constrained", False):
        q, qdot = plant.project_consistent(x0[: plant.nq], x0[plant.nq :])
        x0 = torch.cat([q, qdot]).detach()
    return x0


def _batch_x0(sc, plant, shape) -> torch.Tensor:
    n = int(np.prod(shape)) if shape else 1
    return torch.stack([_member_x0(sc, plant, k) for k in range(n)]).reshape(*shape, -1)


def _numpy_rhs(plant, u, nx: int):
    """The plant on a flat numpy state of several members, ``(m * nx,) -> (m * nx,)``, autograd
    allowed inside ``f`` (for scipy)."""

    def fun(t, x):
        tt = torch.tensor(t, dtype=DT)
        xs = torch.from_numpy(x).reshape(-1, nx)
        with torch.enable_grad():
            y = plant(tt, xs, u(tt)) if u is not None else plant(tt, xs)
        return y.detach().reshape(-1).numpy()

    return fun


@functools.cache
def _reference(name: str) -> np.ndarray:
    """The three members' trajectories (3, T, nx) on the output grid: the plant's closed form
    where it has one, else scipy (DOP853; Radau for stiff plants) at rtol = atol = 1e-12 on the
    stacked members."""
    sc = SCENARIOS[name]
    plant = sc.build().to(DT)
    x0 = _batch_x0(sc, plant, (len(MEMBER_SCALE),))
    t = _grid(sc.t_end)
    if hasattr(plant, "exact") and sc.u is None:
        return plant.exact(t, x0).detach().numpy()
    nx = x0.shape[-1]
    sol = solve_ivp(_numpy_rhs(plant, sc.u, nx), (0.0, sc.t_end), x0.reshape(-1).numpy(),
                    "Radau" if sc.stiff else "DOP853", t_eval=t.numpy(), rtol=1e-12,
                    atol=1e-12)  # fmt: skip
    assert sol.success, sol.message
    return sol.y.T.reshape(len(t), -1, nx).transpose(1, 0, 2)


def _options(drv, sc) -> dict:
    """The driver's options, with the scenario's ``substeps`` for fixed-step methods."""
    fixed = drv.options.get("adaptive") is False or drv.options["method"] in FIXED_METHODS
    return {**drv.options, "substeps": sc.substeps} if fixed else dict(drv.options)


def _run(sc, plant, drv, x0):
    return odeint(plant, x0, _grid(sc.t_end), u=sc.u, **_options(drv, sc))


@functools.cache
def _plant(name: str):
    """One plant per scenario for the whole module (compiled runs are cached per model)."""
    return SCENARIOS[name].build().to(DT)


@functools.cache
def _solution(name: str, driver: str, shape: tuple):
    """The driver's no-grad run of the scenario from the first members' states (cached: the
    fast-path tests compare these runs with each other)."""
    sc, plant = SCENARIOS[name], _plant(name)
    with torch.no_grad():
        return _run(sc, plant, DRIVER[driver], _batch_x0(sc, plant, shape))


@pytest.mark.parametrize("name,driver,shape", list(_cases(BATCH_SHAPES)))
def test_plant_matches_reference(name, driver, shape):
    sc, drv = SCENARIOS[name], DRIVER[driver]
    sol = _solution(name, driver, shape)
    _check_ran(drv, _plant(name), shape, sol.stats.extra)
    assert sol.x.shape == (*shape, N_INTERVALS + 1, len(sc.x0))
    assert (sol.status == Status.SUCCESS).all(), sol.messages
    x = sol.x.reshape(-1, N_INTERVALS + 1, len(sc.x0)).numpy()
    ref = _reference(name)
    for k in range(x.shape[0]):
        err = np.abs(x[k] - ref[k]).max() / (1.0 + np.abs(ref[k]).max())
        assert err <= drv.tol, f"member {k}: relative error {err:.2e} > {drv.tol:.0e}"


@pytest.mark.parametrize("name,driver", [c for c in _cases() if c.values[1] != "rk4 compiled"])
def test_batch_member_equals_stand_alone_run(name, driver):
    """Member 0 of a batch of 3 and of a batch of 1 equals the unbatched run: no driver mixes
    members (per-sample step sizes make adaptive members independent too)."""
    alone = _solution(name, driver, ()).x
    for shape in [(1,), (3,)]:
        member = _solution(name, driver, shape).x[0]
        torch.testing.assert_close(member, alone, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("name", [n for n, sc in SCENARIOS.items() if not sc.stiff])
def test_compiled_rk4_equals_eager(name):
    """The compiled fixed-step path gives the eager path's answer."""
    eager, compiled = (_solution(name, d, (3,)) for d in ("rk4 eager", "rk4 compiled"))
    torch.testing.assert_close(compiled.x, eager.x, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("shape", BATCH_SHAPES, ids=lambda s: f"batch{s}")
@pytest.mark.parametrize(
    "name", [n for n, sc in SCENARIOS.items() if DRIVER["radau adaptive host"].applies(sc)]
)
def test_host_radau_equals_torch_radau(name, shape):
    """The numpy host loops (batched and one trajectory) take the torch driver's steps."""
    host, ref = (_solution(name, d, shape) for d in ("radau adaptive host", "radau adaptive torch"))
    torch.testing.assert_close(host.stats.n_steps, ref.stats.n_steps)
    torch.testing.assert_close(host.x, ref.x, rtol=1e-9, atol=1e-11)


def _check_ran(drv, plant, shape: tuple, extra: dict) -> None:
    """The run's ``stats.extra`` says it ran what the driver names. A Lagrangian plant forms
    its equations by autograd inside ``f``: where the compiler loses the second derivatives
    or cannot differentiate its graph (double backward), the compiled driver must step
    eagerly and say why (which happens may depend on what the process compiled before)."""
    if drv.name == "rk4 compiled" and isinstance(plant, LagrangianSystem):
        assert extra["compiled"] == (extra["compile_fallback"] is None), extra
        return
    for key, value in drv.extra.items():
        expected = value[shape] if isinstance(value, dict) else value
        assert extra[key] == expected, (key, extra)


def _loss(sc, plant, drv, x0, scale):
    """A weighted sum of the final states of every member, from ``scale * x0``; the run must
    succeed and say it ran what the driver names."""
    sol = _run(sc, plant, drv, scale * x0)
    assert (sol.status == Status.SUCCESS).all(), sol.messages
    _check_ran(drv, plant, tuple(x0.shape[:-1]), sol.stats.extra)
    w = torch.linspace(0.5, 1.5, x0.shape[-1], dtype=DT)
    return (sol.x[..., -1, :] * w).sum()


@pytest.mark.parametrize("name,driver", list(_cases()))
def test_parameter_gradient_matches_central_differences(name, driver, monkeypatch):
    """d(loss)/dp by autograd through a batch of 3 members sharing the parameter p (the
    scenario's, else a scale of x0), against central differences of the same scheme with the
    step 1e-6 |p|.

    The compiled driver takes one step per output interval and compiles chunks of one
    interval (the time to compile a forward and backward graph grows with the steps in a
    chunk); its differences come from its eager twin, whose runs give the compiled runs'
    numbers (``test_compiled_rk4_equals_eager``); the gradient run must say whether it ran
    compiled (``_check_ran``)."""
    sc, drv, plant = SCENARIOS[name], DRIVER[driver], _plant(name)
    differences = drv
    if driver == "rk4 compiled":
        monkeypatch.setattr(importlib.import_module("integrators.explicit"), "CHUNK_STEPS", 1)
        sc, differences = dataclasses.replace(sc, substeps=1), DRIVER["rk4 eager"]
    x0 = _batch_x0(sc, plant, (3,))
    scale = torch.ones((), dtype=DT, requires_grad=sc.param is None)
    p = scale if sc.param is None else getattr(plant, sc.param)
    grad = float(torch.autograd.grad(_loss(sc, plant, drv, x0, scale), p)[0])
    h = 1e-6 * float(p.detach().abs())
    values = []
    with torch.no_grad():
        p0 = p.detach().clone()
        for sign in (1.0, -1.0):
            p.copy_(p0 + sign * h)
            values.append(float(_loss(sc, plant, differences, x0, scale)))
        p.copy_(p0)
    fd = (values[0] - values[1]) / (2 * h)
    assert abs(grad - fd) <= drv.grad_rtol * max(1.0, abs(fd)), (grad, fd)


@pytest.mark.parametrize("shape", [(), (3,)], ids=lambda s: f"batch{s}")
@pytest.mark.parametrize(
    "driver", [d.name for d in DRIVERS if "rtol" in d.options and d.options.get("rtol") == RTOL]
)
def test_adaptive_driver_is_accurate_far_from_time_zero(driver, shape):
    """An autonomous linear ODE started at t0 = 1e8: the solution cannot depend on t0, and
    each adaptive driver must stay as close to the matrix exponential as at t0 = 0. Steps
    advanced the time by the rounded ``t + h`` but the state by ``h`` (radau 1.1e-6, dopri5
    8e-8 at rtol 1e-8, against 1e-9 at t0 = 0)."""
    A = torch.tensor([[0.0, 1.0], [-4.0, -0.5]], dtype=DT)
    x0 = torch.tensor([1.0, 0.0], dtype=DT).expand(*shape, 2)
    errors = []
    for t0 in (0.0, 1e8):
        t = t0 + torch.linspace(0.0, 2.0, 21, dtype=DT)
        # at the float times of the grid (1e8 + 0.1 is 1e8 + 0.1 +- 7e-9)
        exact = torch.stack([torch.linalg.matrix_exp(A * float(ti - t[0])) for ti in t])
        exact = (exact @ x0[..., None, :, None])[..., 0]
        sol = odeint(lambda t, x: x @ A.T, x0, t, **DRIVER[driver].options)
        assert (sol.status == Status.SUCCESS).all(), sol.messages
        errors.append(float((sol.x - exact).abs().max()))
    assert errors[1] <= 5 * errors[0] + 1e-10, errors


#: input-driven plants whose input gradients are checked on every driver: a non-stiff and a
#: stiff one (the gradient path depends on the driver, not on the plant)
INPUT_GRADIENT_PLANTS = ("SpringMassDamper", "SingularlyPerturbedLinear")


@pytest.mark.parametrize("kind", ["zoh", "linear", "callable"])
@pytest.mark.parametrize(
    "name,driver",
    [c for c in _cases() if c.values[0] in INPUT_GRADIENT_PLANTS and c.values[1] != "rk4 compiled"],
)
def test_input_gradient_matches_central_differences(name, driver, kind):
    """The derivative of the loss along a direction ``v`` of the input, by autograd, against
    central differences: the input's samples (held or interpolated) require grad, or the
    amplitude of a callable input does. The implicit drivers stacked the stage inputs in the
    Newton iterations, without graph, and the gradients to the input were lost (None)."""
    sc, drv, plant = SCENARIOS[name], DRIVER[driver], _plant(name)
    x0 = _batch_x0(sc, plant, (3,))
    t = _grid(sc.t_end)
    samples = torch.stack([sc.u(ti) for ti in t]).detach()  # (T, nu)
    v = torch.linspace(-1.0, 1.0, samples.numel(), dtype=DT).reshape(samples.shape)
    w = torch.linspace(0.5, 1.5, x0.shape[-1], dtype=DT)

    def loss(eps):
        if kind == "callable":
            u, options = (lambda tt: (1 + eps) * sc.u(tt)), {}
        else:
            u, options = samples + eps * v, {"interpolation": kind}
        sol = odeint(plant, x0, t, u=u, **_options(drv, sc), **options)
        assert (sol.status == Status.SUCCESS).all(), sol.messages
        return (sol.x[..., -1, :] * w).sum()

    eps = torch.zeros((), dtype=DT, requires_grad=True)
    (grad,) = torch.autograd.grad(loss(eps), eps, allow_unused=True)
    assert grad is not None, "the gradient did not reach the input"
    h = 1e-6
    with torch.no_grad():
        fd = float(loss(torch.tensor(h, dtype=DT))) - float(loss(torch.tensor(-h, dtype=DT)))
    fd /= 2 * h
    assert abs(float(grad) - fd) <= drv.grad_rtol * max(1.0, abs(fd)), (float(grad), fd)


#: models whose output has no autograd graph to the state, nor to any parameter: the flow is
#: x0 plus a function of time, x(t) = x0 + exact(t), so d x(T) / d x0 = I on every driver
GRAPH_FREE_MODELS = {
    "time-driven": (lambda t, x: torch.cos(t) * torch.ones_like(x), None, torch.sin),
    "input-driven": (
        lambda t, x, u: u.expand_as(x).clone(),
        torch.full((N_INTERVALS + 1, 1), 0.3, dtype=DT),
        lambda t: 0.3 * t,
    ),
}


@pytest.mark.parametrize("shape", [(), (3,)], ids=lambda s: f"batch{s}")
@pytest.mark.parametrize("driver", [d.name for d in DRIVERS])
@pytest.mark.parametrize("model", list(GRAPH_FREE_MODELS))
def test_state_gradient_of_a_model_without_graph_to_the_state(model, driver, shape):
    """x' = cos t and x' = u (an integrator of its input, 2 states): the stages carry no
    gradient, but each step still carries x_k to x_{k+1} (eq. 7.18), so the gradient of the
    final state with respect to x0 is exactly 1 per component (the host Radau loops gave 0:
    they stopped replaying the steps for gradients when the stages had none)."""
    drv = DRIVER[driver]
    f, u, exact = GRAPH_FREE_MODELS[model]
    t = _grid(1.0)
    x0 = torch.tensor([1.0, -2.0], dtype=DT).expand(*shape, 2).clone().requires_grad_(True)
    fixed = drv.options.get("adaptive") is False or drv.options["method"] in FIXED_METHODS
    sol = odeint(f, x0, t, u=u, **({**drv.options, "substeps": 5} if fixed else drv.options))
    assert (sol.status == Status.SUCCESS).all(), sol.messages
    reference = x0.detach()[..., None, :] + exact(t)[:, None]
    err = float((sol.x.detach() - reference).abs().max()) / (1 + float(reference.abs().max()))
    assert err <= drv.tol, err
    (grad,) = torch.autograd.grad(sol.x[..., -1, :].sum(), x0)
    torch.testing.assert_close(grad, torch.ones_like(x0), rtol=0, atol=1e-12)


@pytest.mark.parametrize("shape", [(), (3,)], ids=lambda s: f"batch{s}")
@pytest.mark.parametrize(
    # the compiled driver is left out: a Python branch on t is a graph break, and its gradients
    # are those of its eager twin (test_compiled_rk4_equals_eager)
    "driver",
    [d.name for d in DRIVERS if d.name != "rk4 compiled"],
)
def test_gradients_of_a_model_that_reads_a_parameter_only_in_later_steps(driver, shape):
    """x' = 0 for t < 0.5, x' = -k x after (a Python branch on t): the first steps' stages
    carry no gradient, the later ones do. The implicit drivers decided from the first step
    that nothing needed gradients (dk None, dx0 = 1). Every driver: d x(T) / d x0 is the
    discrete propagator x(T) / x0 (the scheme is linear in x0 once its steps are fixed) and
    d x(T) / dk equals central differences of the same scheme."""
    drv = DRIVER[driver]
    t = _grid(1.0)
    fixed = drv.options.get("adaptive") is False or drv.options["method"] in FIXED_METHODS
    options = {**drv.options, "substeps": 5} if fixed else dict(drv.options)

    def final(k, x0):
        def f(tt, x):  # tt: one time, or one per member of an adaptive batch
            if bool((tt < 0.5).all()):
                return torch.zeros_like(x)
            return torch.where(tt < 0.5, 0.0, -k) * x

        sol = odeint(f, x0, t, **options)
        assert (sol.status == Status.SUCCESS).all(), sol.messages
        return sol.x[..., -1, :]

    k = torch.tensor(2.0, dtype=DT, requires_grad=True)
    x0 = torch.tensor([1.0, -2.0], dtype=DT).expand(*shape, 2).clone().requires_grad_(True)
    x_end = final(k, x0)
    # (fixed steps put the switch inside a step's last stage: first-order accurate there)
    torch.testing.assert_close(x_end.detach(), x0.detach() * math.exp(-1.0), rtol=1e-2, atol=0)
    grad_x0, grad_k = torch.autograd.grad(x_end.sum(), (x0, k), allow_unused=True)
    assert grad_k is not None, "the gradient did not reach k"
    torch.testing.assert_close(grad_x0, (x_end / x0).detach(), rtol=1e-10, atol=0)
    h = 1e-6
    with torch.no_grad():
        fd = (final(k + h, x0).sum() - final(k - h, x0).sum()) / (2 * h)
    assert abs(float(grad_k) - float(fd)) <= drv.grad_rtol * max(1.0, abs(float(fd)))


# ----------------------------------------------------------------------------- index-1 DAEs
DAE_DRIVERS = [
    Driver("radau adaptive", dict(method="radau_iia", **_ADAPTIVE), ADAPTIVE_TOL, 1e-4),
    Driver("radau fixed", dict(method="radau_iia", adaptive=False, **_FIXED), FIXED_TOL, 1e-6),
    Driver("gauss fixed", dict(method="gauss_legendre", stages=2, **_FIXED), FIXED_TOL, 1e-6),
]
DAE_DRIVER = {d.name: d for d in DAE_DRIVERS}
DAE_SCENARIOS = {s.name: s for s in zoo_scenarios.dae_scenarios()}
REFUSED = {s.name: s for s in zoo_scenarios.refused_scenarios()}
DAE_CASES = [
    pytest.param(n, d.name, shape, id=f"{n}-{d.name}-{shape}")
    for n in DAE_SCENARIOS
    for d in DAE_DRIVERS
    for shape in BATCH_SHAPES
]


def _dae_members(sc, plant, shape):
    """x0 of the members (scaled; constrained plants projected) and the shared z0 guess."""
    x0 = _batch_x0(sc, plant, shape)
    z0 = torch.tensor(sc.z0, dtype=DT).expand(*shape, len(sc.z0))
    return x0, z0


def _dae_numpy_rhs(problem, u, nx: int, nz: int):
    """x' of an index-1 DAE on a flat numpy state of several members: the algebraic states
    (and, for a fully implicit DAE, x') solved from the residual by scipy's ``fsolve`` from
    the previous solution, then ``f`` (independent of ``daeint``'s Newton solver)."""
    implicit = isinstance(problem, ImplicitDAE)
    guess = {}

    def residual(t, x, unknowns):
        with torch.enable_grad():
            tt, xs = torch.tensor(t, dtype=DT), torch.from_numpy(x).reshape(-1, nx)
            w = torch.from_numpy(unknowns).reshape(xs.shape[0], -1)
            args = (u(tt),) if u is not None else ()
            if implicit:
                r = problem.F(tt, w[:, :nx], xs, w[:, nx:], *args)
            else:
                r = problem.g(tt, xs, w, *args)
        return r.detach().reshape(-1).numpy()

    def fun(t, x):
        m = x.size // nx
        w0 = guess.get("w", np.zeros(m * (nz + nx * implicit)))
        with warnings.catch_warnings():  # "no further improvement" at round-off level
            warnings.simplefilter("ignore", RuntimeWarning)
            w = scipy.optimize.fsolve(lambda w: residual(t, x, w), w0, xtol=1e-12)
        assert np.abs(residual(t, x, w)).max() <= 1e-11
        guess["w"] = w
        if implicit:
            return w.reshape(m, -1)[:, :nx].reshape(-1)
        tt = torch.tensor(t, dtype=DT)
        xs, zs = torch.from_numpy(x).reshape(m, nx), torch.from_numpy(w).reshape(m, nz)
        with torch.enable_grad():
            y = problem.f(tt, xs, zs, u(tt)) if u is not None else problem.f(tt, xs, zs)
        return y.detach().reshape(-1).numpy()

    return fun


@functools.cache
def _dae_reference(name: str) -> np.ndarray:
    """The differential states of the three members (3, T, nx): DOP853 at 1e-12 on the ODE
    that eliminating the algebraic states leaves (notes §5, index 1)."""
    sc = DAE_SCENARIOS[name]
    plant = sc.build().to(DT)
    problem = sc.problem(plant)
    x0 = _batch_x0(sc, plant, (len(MEMBER_SCALE),))
    nx, t = x0.shape[-1], _grid(sc.t_end)
    fun = _dae_numpy_rhs(problem, sc.u, nx, len(sc.z0))
    sol = solve_ivp(fun, (0.0, sc.t_end), x0.reshape(-1).numpy(), "DOP853", t_eval=t.numpy(),
                    rtol=1e-12, atol=1e-12)  # fmt: skip
    assert sol.success, sol.message
    return sol.y.T.reshape(len(t), -1, nx).transpose(1, 0, 2)


def _dae_run(sc, plant, drv, shape):
    x0, z0 = _dae_members(sc, plant, shape)
    return daeint(sc.problem(plant), x0, z0, _grid(sc.t_end), u=sc.u, **_options(drv, sc))


@pytest.mark.parametrize("name,driver,shape", DAE_CASES)
def test_dae_plant_matches_reference(name, driver, shape):
    """``daeint`` on every index-1 DAE form of the zoo: x against the eliminated ODE, z
    satisfying its algebraic equations at every output time."""
    sc, drv = DAE_SCENARIOS[name], DAE_DRIVER[driver]
    plant = sc.build().to(DT)
    with torch.no_grad():
        sol = _dae_run(sc, plant, drv, shape)
    assert (sol.status == Status.SUCCESS).all(), sol.messages
    assert sol.x.shape == (*shape, N_INTERVALS + 1, len(sc.x0))
    assert sol.z.shape == (*shape, N_INTERVALS + 1, len(sc.z0))
    x = sol.x.reshape(-1, N_INTERVALS + 1, len(sc.x0)).numpy()
    ref = _dae_reference(name)
    for k in range(x.shape[0]):
        err = np.abs(x[k] - ref[k]).max() / (1.0 + np.abs(ref[k]).max())
        assert err <= drv.tol, f"member {k}: relative error {err:.2e} > {drv.tol:.0e}"


@pytest.mark.parametrize("name", [n for n, sc in DAE_SCENARIOS.items() if sc.param])
def test_dae_parameter_gradient_matches_central_differences(name):
    """d(loss)/dp through adaptive ``daeint`` (IFT gradients per step and through the
    consistent start) against central differences."""
    sc, drv = DAE_SCENARIOS[name], DAE_DRIVER["radau adaptive"]
    plant = sc.build().to(DT)
    p = getattr(plant, sc.param)

    def loss():
        sol = _dae_run(sc, plant, drv, (3,))
        assert (sol.status == Status.SUCCESS).all(), sol.messages
        return sol.x[..., -1, :].sum() + sol.z[..., -1, :].sum()

    grad = torch.autograd.grad(loss(), p)[0]
    direction = torch.ones_like(p)
    h = 1e-6 * max(float(p.detach().abs().max()), 1e-3)
    values = []
    with torch.no_grad():
        p0 = p.detach().clone()
        for sign in (1.0, -1.0):
            p.copy_(p0 + sign * h * direction)
            values.append(float(loss()))
        p.copy_(p0)
    fd = (values[0] - values[1]) / (2 * h)
    g = float((grad * direction).sum())
    assert abs(g - fd) <= drv.grad_rtol * max(1.0, abs(fd)), (g, fd)


@pytest.mark.parametrize("name", list(SCENARIOS))
def test_per_member_parameters_broadcast_against_a_shared_state(name):
    """Every scalar parameter of every plant given per member, (3, 1), with one state (nx,)
    shared by the batch: the right-hand side is that of three plants with one value each.
    The cranes stacked a cart position of the state's batch with a bob position of the
    length's batch and raised."""
    sc = SCENARIOS[name]
    x = torch.tensor(sc.x0, dtype=DT)
    t = torch.tensor(0.1, dtype=DT)
    args = (t, x, sc.u(t)) if sc.u is not None else (t, x)
    scalars = [n for n, p in sc.build().to(DT).named_parameters() if p.numel() == 1]
    for param in scalars:
        batched = sc.build().to(DT)
        value = float(batched.get_parameter(param))
        members = value * torch.tensor([1.0, 1.1, 0.9], dtype=DT)
        batched.get_parameter(param).data = members[:, None]
        expected = []
        for v in members:
            one = sc.build().to(DT)
            one.get_parameter(param).data = v.reshape(one.get_parameter(param).shape)
            expected.append(one(*args))
        torch.testing.assert_close(batched(*args), torch.stack(expected), rtol=1e-12, atol=1e-12)


# Constructor arguments of the zoo with a last axis of their own: lam of shape (n,) gives the
# test equation n components (a scalar one acts on every component).
VECTOR_PARAMETERS = {("LinearTestEquation", "lam")}


def _scalar_constructor_arguments():
    for name in sysid.zoo.__all__:
        signature = inspect.signature(getattr(sysid.zoo, name).__init__)
        for arg, p in signature.parameters.items():
            default = p.default
            if isinstance(default, float) and (name, arg) not in VECTOR_PARAMETERS:
                yield name, arg, default


@pytest.mark.parametrize("plant,arg,default", list(_scalar_constructor_arguments()))
def test_a_flat_vector_of_per_member_scalars_is_refused_at_construction(plant, arg, default):
    """Every scalar parameter of every plant given as a flat (3,) vector, meant as one value
    per plant of a batch, is refused by name: it broadcast against the state's components
    instead (SpringMassDamper K = [4, 5, 6] gave x2' = -7.6 to all three plants for -2.1,
    -2.6, -3.1). The column (3, 1) builds the batch (see the test above)."""
    cls = getattr(sysid.zoo, plant)
    values = default * torch.tensor([1.0, 1.1, 0.9], dtype=DT) + 0.1
    with pytest.raises(InputValidationError, match=rf"parameter '{arg}' has shape \(\*batch, 1\)"):
        cls(**{arg: values})
    assert getattr(cls(**{arg: values[:, None]}), arg).shape == (3, 1)


# Scalar constructor arguments of the zoo that must be > 0: masses, lengths (L0 the elastic
# cranes' rest length), the singular-perturbation scales eps, and TwoMassSystem's K (its
# reductions divide by it). Every other scalar argument may take any finite value.
POSITIVE_PARAMETERS = {
    ("SingularlyPerturbedLinear", "eps"),
    ("TwoMassSystem", "m1"),
    ("TwoMassSystem", "m2"),
    ("TwoMassSystem", "K"),
    ("Bowl", "m"),
    ("Crane", "M"),
    ("Crane", "m"),
    ("Crane", "L"),
    ("DistributedRod", "m"),
    ("DistributedRod", "L"),
    ("ElasticCraneCartesian", "M"),
    ("ElasticCraneCartesian", "m"),
    ("ElasticCraneCartesian", "L0"),
    ("ElasticCranePolar", "M"),
    ("ElasticCranePolar", "m"),
    ("ElasticCranePolar", "L0"),
    ("HangingChain", "m"),
    ("RigidCraneCartesian", "M"),
    ("RigidCraneCartesian", "m"),
    ("RigidCraneCartesian", "L"),
    ("SpringMass", "m"),
    ("SpringMassDamper", "m"),
    ("TwoPendulumCraneCartesian", "m"),
    ("TwoPendulumCraneCartesian", "L"),
    ("TwoPendulumCranePolar", "m"),
    ("TwoPendulumCranePolar", "L"),
    ("StiffLinear", "eps"),
    ("StiffVanDerPol", "eps"),
}


@pytest.mark.parametrize("plant,arg,default", list(_scalar_constructor_arguments()))
def test_positive_parameters_and_non_numbers_are_refused_at_construction(plant, arg, default):
    """The parameters of POSITIVE_PARAMETERS are refused at 0 and below, naming them
    (TwoMassSystem(m2=-1) simulated to 4e29 with status SUCCESS; StiffLinear(eps=-1) ran),
    the others accept a negative value; a string is refused by name for every one (it raised
    a raw TypeError)."""
    cls = getattr(sysid.zoo, plant)
    if (plant, arg) in POSITIVE_PARAMETERS:
        for bad in (0.0, -default, torch.tensor([[default], [-default]], dtype=DT)):
            with pytest.raises(InputValidationError, match=rf"parameter '{arg}' must be > 0"):
                cls(**{arg: bad})
    else:
        assert float(getattr(cls(**{arg: -default - 1.0}), arg).detach()) == -default - 1.0
    with pytest.raises(InputValidationError, match=rf"parameter '{arg}' must be a number"):
        cls(**{arg: "a"})


def test_counts_baumgarte_gains_and_matrix_shapes_are_checked_at_construction():
    """Node and mass counts must be integers >= 1 (DistributedRod(n_nodes=0) failed in the
    simulation), a Baumgarte gain a finite number >= 0 or a tensor of them (Bowl(baumgarte=-1)
    ran with a growing drift, 'x' failed in kkt_solve), UnitSphereDAE's A square and b of its
    size (A of shape (1, 3) raised a RuntimeError in f)."""
    for bad in (0, 2.5):
        with pytest.raises(InputValidationError, match="DistributedRod: n_nodes must be an int"):
            sysid.zoo.DistributedRod(n_nodes=bad)
        with pytest.raises(InputValidationError, match="HangingChain: n_masses must be an int"):
            sysid.zoo.HangingChain(n_masses=bad)
    for plant in ("Bowl", "RigidCraneCartesian", "TwoPendulumCraneCartesian"):
        cls = getattr(sysid.zoo, plant)
        for bad in (-1.0, float("nan"), "x", torch.tensor([[1.0], [-1.0]], dtype=DT)):
            with pytest.raises(InputValidationError, match="baumgarte must be None or a finite"):
                cls(baumgarte=bad)
        assert cls(baumgarte=5.0).baumgarte == 5.0
        assert cls(baumgarte=0.0).baumgarte == 0.0  # no stabilisation, as None
    bowl = sysid.zoo.Bowl()
    with pytest.raises(InputValidationError, match="baumgarte must be None or a finite"):
        bowl.index1_dae(baumgarte=-2.0)
    for A, b in ((((1.0, 2.0, 3.0),), (1.0, 0.5)), (((0.0, 1.0), (-1.0, 0.0)), (1.0,))):
        with pytest.raises(InputValidationError, match="UnitSphereDAE: A must be a square"):
            sysid.zoo.UnitSphereDAE(A=A, b=b)


def test_every_zoo_plant_has_a_scenario():
    """A new plant of the zoo joins the matrix through a scenario, or is listed with the
    reason it cannot be simulated as given (and ``daeint`` must refuse it)."""
    covered = {sc.plant_class for sc in SCENARIOS.values()}
    covered |= {sc.plant_class for sc in DAE_SCENARIOS.values()}
    covered |= {sc.plant_class for sc in REFUSED.values()}
    exported = {getattr(sysid.zoo, name) for name in sysid.zoo.__all__}
    assert exported - covered == set()


@pytest.mark.parametrize("name", list(REFUSED))
def test_higher_index_plants_are_refused(name):
    """The zoo's DAEs of index > 1 in their given form are refused by ``daeint`` with
    ``HighIndexError`` (the index check, Theorem 9), never integrated into wrong numbers."""
    problem, x0, z0 = REFUSED[name].setup()
    with pytest.raises(HighIndexError):
        daeint(problem, x0, z0, torch.linspace(0.0, 1.0, 3, dtype=DT))
