"""odeint: every invalid input raises a clear error from the hierarchy, and the
method dispatch reaches the right solver (checked against closed forms)."""

import math

import numpy as np
import pytest
import torch

from integrators import (
    InputValidationError,
    ODELayer,
    SemiExplicitDAE,
    TableauError,
    daeint,
    gauss_legendre,
    odeint,
    solve_adaptive,
    solve_implicit_ode,
    tableau,
)
from integrators.errors import RKIdentError

T = torch.linspace(0, 1, 5, dtype=torch.float64)
X0 = torch.ones(2, 1, dtype=torch.float64)


def decay(t, x):
    return -x


@pytest.mark.parametrize(
    "x0, match",
    [
        (torch.tensor(1.0, dtype=torch.float64), r"shape \(\*batch, n\)"),
        (torch.zeros(3, 0, dtype=torch.float64), r"n >= 1"),
        (torch.tensor([1.0 + 1j]), "real floating point"),
        (torch.tensor([[1.0], [float("nan")]], dtype=torch.float64), r"sample index \(1,\)"),
        ("abc", "not numeric"),
    ],
)
def test_bad_x0(x0, match):
    with pytest.raises(InputValidationError, match=match):
        odeint(decay, x0, T)


@pytest.mark.parametrize(
    "t, match",
    [
        (torch.zeros(2, 3), "1-D"),
        (torch.tensor([0.0]), "T >= 2"),
        (torch.tensor([0.0, 0.5, 0.5, 1.0]), r"strictly increasing, but t\[2\]"),
        (torch.tensor([0.0, 1.0, 0.5]), r"t\[2\] = 0.5 <= t\[1\] = 1.0"),
        (torch.tensor([0.0, float("inf")]), "non-finite"),
    ],
)
def test_bad_t(t, match):
    with pytest.raises(InputValidationError, match=match):
        odeint(decay, X0, t)


def test_non_finite_input_names_time_index():
    u = torch.zeros(5, 1, dtype=torch.float64)
    u[3] = float("nan")
    with pytest.raises(InputValidationError, match="time index 3"):
        odeint(lambda t, x, u: -x + u, X0, T, u=u)


def test_model_output_checks():
    with pytest.raises(InputValidationError, match=r"returned shape \(2, 2\)"):
        odeint(lambda t, x: torch.cat([x, x], dim=-1), X0, T)
    with pytest.raises(InputValidationError, match="must return a tensor"):
        odeint(lambda t, x: 1.0, X0, T)
    with pytest.raises(InputValidationError, match="dtype"):
        odeint(lambda t, x: -x.float(), X0, T)
    with pytest.raises(InputValidationError, match="non-finite at the initial time"):
        odeint(lambda t, x: x / 0.0, X0, T)
    with pytest.raises(InputValidationError, match=r"f\(t, x, u\)"):
        odeint(decay, X0, T, u=torch.zeros(5, 1, dtype=torch.float64))


@pytest.mark.parametrize(
    "kwargs, error, match",
    [
        (dict(method="rk5"), TableauError, "unknown method 'rk5'"),
        (dict(method=3), TableauError, "unknown method"),
        (dict(substeps=0), InputValidationError, "substeps"),
        (dict(substeps=1.5), InputValidationError, "substeps"),
        (dict(rtol=-1.0), InputValidationError, "rtol"),
        (dict(rtol=0.0, atol=0.0), InputValidationError, "rtol = 0 is below"),
        (dict(max_steps=0), InputValidationError, "max_steps"),
        (dict(compile="yes"), InputValidationError, "compile"),
        (dict(method="rk4", adaptive=True), TableauError, "no embedded weights"),
        (dict(method="rk4", newton_tol=1e-3), InputValidationError, "unexpected keyword"),
        (dict(interpolation="spline", u=torch.zeros(5, 1)), InputValidationError, "interp"),
    ],
)
def test_bad_options(kwargs, error, match):
    f = decay if "u" not in kwargs else (lambda t, x, u: -x)
    with pytest.raises(error, match=match):
        odeint(f, X0, T, **kwargs)


def test_errors_belong_to_hierarchy_and_value_error():
    with pytest.raises(RKIdentError):
        odeint(decay, X0, torch.tensor([1.0, 0.0]))
    with pytest.raises(ValueError):
        odeint(decay, X0, torch.tensor([1.0, 0.0]))


def test_array_likes_become_float64_and_t_follows_x0():
    sol = odeint(decay, [[1.0], [2.0]], [0.0, 0.5, 1.0], substeps=10)
    assert sol.x.dtype == torch.float64 and sol.t.dtype == torch.float64
    np.testing.assert_allclose(
        sol.x[:, :, 0].numpy(), np.outer([1.0, 2.0], np.exp(-np.array([0, 0.5, 1.0]))), atol=1e-8
    )
    sol32 = odeint(decay, torch.ones(1, dtype=torch.float32), torch.tensor([0.0, 1.0]))
    assert sol32.t.dtype == torch.float32


def test_dispatch_dopri5_adaptive_and_fixed():
    """'dopri5' is adaptive by default; adaptive=False runs it at fixed step (6 f-evals/step)."""
    t = torch.linspace(0, 2, 5, dtype=torch.float64)
    x0 = torch.tensor([[1.0], [3.0]], dtype=torch.float64)
    exact = x0[:, None] * torch.exp(-t)[None, :, None]
    fixed = odeint(decay, x0, t, method="dopri5", adaptive=False, substeps=5)
    assert fixed.stats.n_f_evals == 4 * 5 * 6
    torch.testing.assert_close(fixed.x, exact, rtol=1e-8, atol=0)
    adaptive = odeint(decay, x0, t, method=tableau("dopri5"), rtol=1e-9, atol=1e-12)
    torch.testing.assert_close(adaptive.x, exact, rtol=1e-7, atol=0)
    assert adaptive.success


def test_dispatch_implicit_methods():
    """Implicit tableaus and collocation names reach integrators.implicit.solve_implicit_ode."""
    pytest.importorskip("integrators.implicit")
    lam = -50.0
    t = torch.linspace(0, 0.2, 3, dtype=torch.float64)
    x0 = torch.ones(1, 1, dtype=torch.float64)
    sol = odeint(lambda t, x: lam * x, x0, t, method="implicit_euler", substeps=10, adaptive=False)
    h = 0.01  # implicit Euler: x_{k+1} = x_k / (1 - lam h)
    torch.testing.assert_close(sol.x[0, -1, 0], torch.tensor((1 / (1 - lam * h)) ** 20).double())
    sol = odeint(lambda t, x: lam * x, x0, t, method="gauss_legendre", stages=2, substeps=4)
    growth = gauss_legendre(2).stability_function(lam * 0.025).real  # one step: R(lam h)
    assert abs(float(sol.x[0, -1, 0]) - growth**8) < 1e-10
    assert sol.x[0, -1, 0] == pytest.approx(math.exp(lam * 0.2), abs=1e-3)


def test_dispatch_auto_records_the_choice():
    """method="auto" asks integrators.auto.choose_method and records its choice."""
    pytest.importorskip("integrators.auto")
    t = torch.linspace(0, 1, 11, dtype=torch.float64)
    x0 = torch.ones(2, 1, dtype=torch.float64)
    sol = odeint(decay, x0, t, method="auto")
    assert sol.stats.extra["auto"]["method"] == "dopri5"
    torch.testing.assert_close(sol.x[:, :, 0], torch.exp(-t).expand(2, -1), rtol=1e-6, atol=0)
    # stiff relaxation to cos(t): x = cos t + O(1/lam) once the transient has decayed
    lam = 1e4
    sol = odeint(lambda t, x: -lam * (x - torch.cos(t)), x0, t, method="auto")
    assert sol.stats.extra["auto"]["method"] == "radau_iia"
    assert sol.success
    assert (sol.x[:, 1:, 0] - torch.cos(t[1:])).abs().max() < 1e-3


# ---------------------------------------------------------------------------------------------
# Options are checked at entry, with the same rule on every path they reach (issue 12).

DAE = SemiExplicitDAE(lambda t, x, z: -x + z, lambda t, x, z: x - 2.0 * z)  # z = x / 2
X2 = torch.tensor([[1.0, 0.5], [0.2, -0.3], [2.0, 1.0]], dtype=torch.float64)
IMPLICIT_PATHS = [
    dict(method="radau_iia", host_loop=True),
    dict(method="radau_iia", host_loop=False),
    dict(method="radau_iia", adaptive=False),
    dict(method="gauss_legendre"),
    dict(method="implicit_euler"),
]
EVERY_PATH = [dict(method="rk4"), dict(method="dopri5"), dict(method="dopri5", adaptive=False)]
EVERY_PATH += IMPLICIT_PATHS


def _dae(**kwargs):
    return daeint(DAE, X0, torch.zeros(2, 1, dtype=torch.float64), T, **kwargs)


@pytest.mark.parametrize("method", ["rk4", "dopri5", "radau_iia", "gauss_legendre"])
@pytest.mark.parametrize("value", ["no", "False", 0, 1, 1.0])
def test_adaptive_must_be_a_bool(method, value):
    """``adaptive="no"`` was truthy: dopri5 and Radau ran adaptive, rk4 raised a TableauError."""
    with pytest.raises(InputValidationError, match=r"adaptive must be one of True, False, None"):
        odeint(decay, X0, T, method=method, adaptive=value)


@pytest.mark.parametrize(
    "call",
    [
        lambda: odeint(decay, X0, T, compile=1),
        lambda: odeint(decay, X0, T, compile="false"),
        lambda: odeint(decay, X0, T, method="radau_iia", host_loop="yes"),
        lambda: odeint(decay, X0, T, method="radau_iia", host_loop=None),
        lambda: solve_implicit_ode(decay, X0, T, "radau_iia", adaptive="no"),
        lambda: _dae(adaptive="no"),
        lambda: _dae(host_loop=1),
    ],
)
def test_flags_must_be_bools(call):
    with pytest.raises(InputValidationError, match="must be one of True, False"):
        call()


def test_numpy_bools_are_bools():
    """np.bool_ flags work like Python bools: dopri5 at fixed step takes 6 evaluations/step."""
    sol = odeint(decay, X0, T, method="dopri5", adaptive=np.False_, substeps=2, compile=np.False_)
    assert sol.stats.n_f_evals == 4 * 2 * 6
    host = odeint(decay, X0, T, method="radau_iia", host_loop=np.True_)
    assert host.stats.extra["host_loop"] is True
    torch.testing.assert_close(host.x[..., 0], torch.exp(-T).expand(2, -1), rtol=1e-5, atol=0)


@pytest.mark.parametrize(
    "kwargs",
    [dict(method="dopri5"), *[k for k in IMPLICIT_PATHS if k["method"] != "implicit_euler"]],
)
def test_dense_output_refuses_nan_and_times_outside_the_span(kwargs):
    """Every interpolant (dopri5's continuous extension, the collocation polynomials of the
    fixed and adaptive implicit drivers) answers only inside [t0, t_end]: NaN returned a
    number and implicit dense output extrapolated before."""
    sol = odeint(decay, X0, T, **kwargs)
    for bad in (float("nan"), float("inf"), 1.0 + 1e-6, -1e-6, [0.5, 2.0]):
        with pytest.raises(InputValidationError, match=r"solution covers \[0, 1\]"):
            sol.at(bad)
    # a rounding error outside counts as the end point; inside, dense output matches e^-t
    ends = sol.at(torch.tensor([-1e-17, 1.0 + 2e-16], dtype=torch.float64))
    torch.testing.assert_close(ends, sol.x[:, [0, -1]], rtol=1e-12, atol=0)
    tq = torch.tensor([0.1, 0.33, 0.9], dtype=torch.float64)
    exact = torch.exp(-tq)[None, :, None].expand(2, -1, -1)
    tol = 2e-3 if kwargs["method"] == "implicit_euler" else 1e-4
    torch.testing.assert_close(sol.at(tq), exact, rtol=tol, atol=0)


def _shape_changer(after_calls):
    """x' = -x whose output loses its last state component after ``after_calls`` calls."""
    calls = [0]

    def f(t, x):
        calls[0] += 1
        return -x if calls[0] <= after_calls else -x[..., :1]

    return f


@pytest.mark.parametrize("kwargs", EVERY_PATH)
def test_output_shape_change_during_the_run_raises(kwargs):
    """A model whose output stops matching the state was broadcast silently (rk4) or failed
    with a raw reshape error (implicit drivers)."""
    with pytest.raises(InputValidationError, match=r"returned shape \(3, 1\) for a state of"):
        odeint(_shape_changer(3), X2, T, **kwargs)


@pytest.mark.parametrize("kwargs", EVERY_PATH)
@pytest.mark.parametrize(
    "bad", [lambda x: -x[0], lambda x: torch.cat([x, x[..., :1]], -1), lambda x: -x[..., :1]]
)
def test_wrong_output_shape_at_t0_names_both_shapes(kwargs, bad):
    with pytest.raises(InputValidationError, match=r"returned shape .* for x0 of shape \(3, 2\)"):
        odeint(lambda t, x: bad(x), X2, T, **kwargs)


@pytest.mark.parametrize("kwargs", [dict(method="rk4"), dict(method="dopri5", adaptive=False)])
def test_fixed_explicit_gradient_wrt_output_times_matches_central_differences(
    kwargs, central_difference
):
    """Fixed-step explicit methods differentiate the discrete map with respect to the grid."""
    t = torch.tensor([0.0, 0.3, 0.7, 1.2], dtype=torch.float64, requires_grad=True)
    w = torch.linspace(0.5, 1.5, 2 * 4, dtype=torch.float64).reshape(2, 4, 1)

    def f(tt, x):
        return -x + torch.sin(3.0 * tt) * x**2

    def loss():
        return (w * odeint(f, X0 * 0.7, t, substeps=3, **kwargs).x).sum()

    (grad,) = torch.autograd.grad(loss(), t)
    torch.testing.assert_close(grad, central_difference(loss, t), rtol=1e-6, atol=1e-9)
    assert float(grad[1:].abs().min()) > 1e-3  # every output time matters


@pytest.mark.parametrize("kwargs", [dict(method="dopri5"), *IMPLICIT_PATHS])
def test_gradient_wrt_output_times_is_refused_where_unsupported(kwargs):
    t = T.clone().requires_grad_(True)
    with pytest.raises(InputValidationError, match="gradients with respect to the output times"):
        odeint(decay, X0, t, **kwargs)
    with torch.no_grad():  # no autograd, no gradient to lose
        assert odeint(decay, X0, t, **kwargs).success


def test_gradient_wrt_output_times_is_refused_by_daeint():
    with pytest.raises(InputValidationError, match="gradients with respect to the output times"):
        daeint(DAE, X0, torch.zeros(2, 1, dtype=torch.float64), T.clone().requires_grad_(True))


@pytest.mark.parametrize("kwargs", [dict(method="dopri5"), *IMPLICIT_PATHS])
@pytest.mark.parametrize(
    "dtype, rtol, smallest",
    [
        (torch.float64, 1e-16, "8.9e-16"),
        (torch.float64, torch.tensor([1e-6, 1e-17]), "8.9e-16"),
        (torch.float32, 1e-7, "4.8e-07"),
    ],
)
def test_tolerances_below_the_dtype_resolution_are_refused(kwargs, dtype, rtol, smallest):
    """rtol = 1e-16 made 100 000 attempts at t = 0 (dopri5) or silently loosened Newton."""
    x0 = X0.to(dtype)
    with pytest.raises(InputValidationError, match=f"smallest sensible value is rtol = {smallest}"):
        odeint(decay, x0, T.to(dtype), rtol=rtol, max_steps=50, **kwargs)


@pytest.mark.parametrize(
    "rtol, atol, match",
    [
        (float("nan"), 1e-9, "rtol must be a finite"),
        (1e-6, float("inf"), "atol must be a finite"),
        (1e-6, -1e-9, "atol must be >= 0"),
        (1e-6, torch.tensor([1e-9, -1.0]), "atol must be >= 0"),
        ("1e-6", 1e-9, "rtol must be a finite"),
    ],
)
@pytest.mark.parametrize("kwargs", [dict(method="dopri5"), *IMPLICIT_PATHS[2:]])
def test_bad_tolerances(rtol, atol, match, kwargs):
    with pytest.raises(InputValidationError, match=match):
        odeint(decay, X0, T, rtol=rtol, atol=atol, **kwargs)


def test_tolerance_checks_reach_daeint_and_the_default_float32_rtol_works():
    with pytest.raises(InputValidationError, match="smallest sensible value is rtol = 8.9e-16"):
        _dae(rtol=1e-16)
    with pytest.raises(InputValidationError, match="atol must be >= 0"):
        _dae(atol=-1.0)
    for method in ("dopri5", "radau_iia"):  # rtol = 1e-6 (8.4 eps) is fine in float32
        sol = odeint(decay, X0.float(), T.float(), method=method)
        torch.testing.assert_close(sol.x[0, :, 0], torch.exp(-T.float()), rtol=1e-5, atol=0)


@pytest.mark.parametrize("dtype", [torch.bfloat16, torch.float16])
@pytest.mark.parametrize("kwargs", EVERY_PATH)
def test_half_precision_states_are_refused(dtype, kwargs):
    with pytest.raises(InputValidationError, match="compute in torch.float32 or torch.float64"):
        odeint(decay, X0.to(dtype), T, **kwargs)


def test_half_precision_states_are_refused_by_daeint():
    with pytest.raises(InputValidationError, match="compute in torch.float32 or torch.float64"):
        daeint(DAE, X0.half(), torch.zeros(2, 1), T)


@pytest.mark.parametrize("kwargs", EVERY_PATH)
@pytest.mark.parametrize("batch", [(0,), (3, 0)])
def test_empty_batch_gives_an_empty_solution(kwargs, batch):
    sol = odeint(decay, torch.ones(*batch, 2, dtype=torch.float64), T, **kwargs)
    assert sol.x.shape == (*batch, 5, 2) and sol.status.shape == batch
    assert sol.success and sol.messages == []
    if sol.interpolant is not None:
        assert sol.at(torch.tensor([0.25, 0.5], dtype=torch.float64)).shape == (*batch, 2, 2)


def test_empty_batch_daeint():
    x0, z0 = torch.ones(0, 1, dtype=torch.float64), torch.zeros(0, 1, dtype=torch.float64)
    for adaptive in (True, False):
        sol = daeint(DAE, x0, z0, T, adaptive=adaptive)
        assert sol.x.shape == (0, 5, 1) and sol.z.shape == (0, 5, 1) and sol.status.shape == (0,)


@pytest.mark.parametrize("kwargs", IMPLICIT_PATHS)
def test_linear_solver_typo_lists_the_valid_names(kwargs):
    with pytest.raises(InputValidationError, match="'auto', 'transformed', 'full'"):
        odeint(decay, X0, T, linear_solver="ful", **kwargs)
    with pytest.raises(InputValidationError, match="unknown linear_solver"):
        _dae(linear_solver=None)


@pytest.mark.parametrize("dt0", [0.0, -0.1, float("nan"), float("inf"), True, "0.1"])
@pytest.mark.parametrize("kwargs", [dict(method="dopri5"), *IMPLICIT_PATHS[:2]])
def test_bad_dt0_is_refused(dt0, kwargs):
    """Radau reported dt0 <= 0 as STEP_TOO_SMALL (or NaN as MAX_STEPS) at run time."""
    with pytest.raises(InputValidationError, match="dt0 must be a finite number > 0"):
        odeint(decay, X0, T, dt0=dt0, **kwargs)


def test_dt0_longer_than_the_span_is_cut_to_it_and_dt0_needs_an_adaptive_method():
    for kwargs in (dict(method="dopri5"), *IMPLICIT_PATHS[:2]):
        sol = odeint(decay, X0, T, dt0=10.0, rtol=1e-8, **kwargs)
        torch.testing.assert_close(sol.x[..., 0], torch.exp(-T).expand(2, -1), rtol=1e-6, atol=0)
    with pytest.raises(InputValidationError, match="dt0 must be a finite number > 0"):
        _dae(dt0=0.0)
    for kwargs in (dict(method="rk4"), dict(method="dopri5", adaptive=False), *IMPLICIT_PATHS[2:]):
        with pytest.raises(InputValidationError, match="dt0.*fixed steps"):
            odeint(decay, X0, T, dt0=0.1, **kwargs)


@pytest.mark.parametrize(
    "option, values",
    [
        ("max_iter", [0, -1, 2.5, True, "7"]),
        ("index_check_every", [0, 1.0]),
        ("newton_tol", [0.0, -1e-3, float("nan")]),
        ("index_tol", [-1.0, float("inf")]),
    ],
)
@pytest.mark.parametrize("kwargs", IMPLICIT_PATHS)
def test_bad_newton_options_are_refused(option, values, kwargs):
    """max_iter <= 0 ended as NEWTON_FAILED / STEP_TOO_SMALL at run time; 2.5 was truncated."""
    for value in values:
        with pytest.raises(InputValidationError, match=option):
            odeint(decay, X0, T, **{option: value}, **kwargs)


@pytest.mark.parametrize(
    "call, match",
    [
        (lambda: odeint(decay, X0, T, method="rk4", stages=3), "stages=3 applies to"),
        (lambda: odeint(decay, X0, T, method="implicit_euler", stages=2), "stages=2 applies to"),
        (lambda: odeint(decay, X0, T, method="radau_iia", stages=0), "stages"),
        # an even number of Radau stages ran at one fixed step per interval under rtol
        (lambda: odeint(decay, X0, T, method="radau_iia", stages=2, rtol=1e-9), "even number"),
        (lambda: _dae(method="radau_iia", stages=4), "even number"),
        (lambda: odeint(decay, X0, T, method="radau_iia", controller=1), "controller must be"),
        (lambda: odeint(decay, X0, T, method="rk4", controller=1), "controller=1 applies"),
        (lambda: solve_implicit_ode(decay, X0, T, substeps=2.0, adaptive=False), "substeps"),
        (lambda: solve_implicit_ode(decay, X0, T, max_steps=10.5), "max_steps"),
        (lambda: _dae(max_steps=0), "max_steps"),
        (lambda: _dae(substeps=True, adaptive=False), "substeps"),
        (lambda: solve_adaptive(decay, X0, T, max_steps=2.5), "max_steps"),
        (lambda: solve_adaptive(decay, X0, T, rtol=1e-17), "smallest sensible"),
    ],
)
def test_other_numeric_options(call, match):
    with pytest.raises(InputValidationError, match=match):
        call()


def _entry_points():
    """Every public entry that takes an initial state, as ``run(x0) -> result tensor``."""
    from integrators import ImplicitODE, minimize, newton

    def implicit_decay(t, xd, x):
        return xd + x

    return {
        "odeint dopri5": lambda x0: odeint(decay, x0, T).x,
        "odeint rk4": lambda x0: odeint(decay, x0, T, method="rk4").x,
        "solve_implicit_ode": lambda x0: solve_implicit_ode(decay, x0, T).x,
        "daeint": lambda x0: daeint(ImplicitODE(implicit_decay), x0, None, T).x,
        "newton": lambda x0: newton(lambda x: x - 0.5, x0).x,
        "minimize": lambda x0: minimize(lambda x: ((x - 0.5) ** 2).sum(-1), x0).theta,
    }


@pytest.mark.parametrize("entry", list(_entry_points()))
def test_state_check_is_shared(entry):
    """One state check at every entry: numbers become float64 (not the default dtype), and
    a non-finite or scalar state is refused with the same message."""
    run = _entry_points()[entry]
    assert run([[1.0], [2.0]]).dtype == torch.float64
    assert run(torch.tensor([[1], [2]])).dtype == torch.float64
    with pytest.raises(InputValidationError, match=r"non-finite value at sample index \(1,\)"):
        run([[1.0], [float("inf")]])
    with pytest.raises(InputValidationError, match=r"shape \(\*batch, n\).*got shape \(\)"):
        run(torch.tensor(1.0, dtype=torch.float64))


def test_one_initial_state_per_record_of_a_sampled_input():
    """x0 (nx,) with input records (B, T, nu): x0 is expanded to the records' batch before the
    model sees it, so a plant that does not broadcast its state against the input (the
    zoo's crane) gives each record's own run; a per-member parameter of the crane broadcasts
    against one state; a model that fails on the unbatched x0 (a per-member parameter it
    cannot broadcast) is named with the fix."""
    from sysid.zoo import Crane

    t = torch.linspace(0, 1, 6, dtype=torch.float64)
    u = torch.linspace(-1, 1, 12, dtype=torch.float64).reshape(2, 6, 1)
    x0 = torch.tensor([0.1, 0.4, 0.2, -0.3], dtype=torch.float64)
    shared = odeint(Crane(), x0, t, u=u, method="rk4", substeps=4)
    for i in range(2):
        alone = odeint(Crane(), x0, t, u=u[i], method="rk4", substeps=4)
        torch.testing.assert_close(shared.x[i], alone.x, rtol=0, atol=1e-14)
    # the crane broadcasts a per-member length against the shared state: one run per member
    lengths = torch.tensor([[0.8], [1.2]], dtype=torch.float64)
    both = odeint(Crane(L=lengths), x0, t, method="rk4").x
    for i in range(2):
        alone = odeint(Crane(L=float(lengths[i, 0])), x0, t, method="rk4").x
        torch.testing.assert_close(both[i], alone, rtol=0, atol=1e-14)
    stiffness = torch.tensor([1.0, 4.0], dtype=torch.float64)

    def per_member(t, x):  # stacks a () component with a (2,) one for an unbatched state
        return torch.stack([x[..., 1], -stiffness * x[..., 0]], -1)

    with pytest.raises(InputValidationError, match=r"x0.expand\(B, nx\)"):
        odeint(per_member, x0[:2], t, method="rk4")


@pytest.mark.parametrize("method", ["rk4", "dopri5", "radau_iia", "dae"])
@pytest.mark.parametrize("kind", ["tensor", "numpy"])
def test_a_solution_keeps_its_times_when_the_callers_times_change(method, kind):
    """The solution holds a copy of the output times: changing the tensor or array passed
    (in place, or a layer's buffer by load_state_dict) leaves sol.t and the range sol.at
    accepts as integrated (before: sol.t read the new times, and sol.at(1.5) on [0, 1]
    returned the state at 1)."""
    t = np.array([0.0, 0.5, 1.0]) if kind == "numpy" else torch.tensor([0.0, 0.5, 1.0])
    x0 = torch.ones(2, 1, dtype=torch.float64)
    if method == "dae":
        sol = daeint(DAE, x0, torch.zeros(2, 1, dtype=torch.float64), t)
    else:
        sol = odeint(decay, x0, t, method=method)
    t *= 4.0
    assert sol.t.tolist() == [0.0, 0.5, 1.0]
    if method != "rk4":  # fixed-step rk4 has no dense output
        with pytest.raises(InputValidationError, match="covers"):
            sol.at(torch.tensor([1.5], dtype=torch.float64))


def test_a_layer_solution_keeps_its_times_after_load_state_dict():
    layer = ODELayer(decay, [0.0, 0.5, 1.0], method="rk4")
    sol = layer(torch.ones(1, 2, dtype=torch.float64))
    layer.load_state_dict({"t": torch.tensor([0.0, 2.0, 4.0], dtype=torch.float64)})
    assert layer.t.tolist() == [0.0, 2.0, 4.0] and sol.t.tolist() == [0.0, 0.5, 1.0]
