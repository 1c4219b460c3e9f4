"""Implicit Runge-Kutta for stiff ODEs (notes §7.1-7.4): linear algebra, orders, stiff
benchmarks against independent references, IFT gradients, batching and statuses."""

import functools
import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.integrate import solve_ivp
from scipy.linalg import expm

from integrators import (
    SemiExplicitDAE,
    Status,
    batch_jacobian,
    daeint,
    gauss_legendre,
    odeint,
    radau_iia,
    solve_implicit_ode,
)
from integrators._irk_linalg import StageLinearSolver, _kron
from integrators.errors import InputValidationError
from integrators.inputs import bind_rhs
from integrators.radau import embedded_weights
from sysid.zoo import StiffLinear, StiffVanDerPol, VanDerPol

pytestmark = pytest.mark.usefixtures("float64_default")


def logistic_rhs(t, x):
    """x1' = x1 (1 - x1), x2' = -x1 x2: smooth, nonlinear, closed form below."""
    return torch.stack([x[..., 0] * (1 - x[..., 0]), -x[..., 0] * x[..., 1]], -1)


def logistic_exact(t, x0):
    grow = 1 + x0[..., 0:1] * (torch.exp(t) - 1)
    return torch.stack([x0[..., 0:1] * torch.exp(t) / grow, x0[..., 1:2] / grow], -1)


X0 = torch.tensor([[0.2, 1.0], [0.6, -0.5]], dtype=torch.float64)


# --------------------------------------------------------------------------- linear algebra
@pytest.mark.parametrize(
    "tab", [radau_iia(1), radau_iia(3), radau_iia(5), gauss_legendre(2), gauss_legendre(3)]
)
def test_transformed_solve_equals_full_kronecker_solve(tab):
    """The eigen-split real/complex solves give the solution of (I (x) E + h A (x) G) dW = -R."""
    gen = torch.Generator().manual_seed(0)
    p, B = 3, 4
    E = torch.eye(p) + 0.1 * torch.randn(B, p, p, generator=gen)
    G = torch.randn(B, p, p, generator=gen)
    h = 0.05 + torch.rand(B, generator=gen)
    R = torch.randn(B, tab.stages, p, generator=gen)
    solver = StageLinearSolver(tab.A, torch.float64, "cpu")
    assert solver.mode == "transformed"
    factors, singular = solver.factorize(E, G, h)
    assert not singular.any()
    dW = solver.solve(factors, R, h)
    A = torch.as_tensor(np.array(tab.A))
    big = _kron(torch.eye(tab.stages), E) + h[:, None, None] * _kron(A, G)
    ref = -torch.linalg.solve(big, R.reshape(B, -1, 1)).reshape(R.shape)
    torch.testing.assert_close(dW, ref, rtol=1e-10, atol=1e-10)


def test_dense_small_system_path_pivots_and_flags_singular_members():
    """For s p <= 24 the Newton matrix J is inverted once and each solve is one matmul. In a
    batch of 64, a member whose J needs row pivoting (E a permutation, G = 0) still matches
    the direct solve of (I (x) E + h A (x) G) dW = -R, the real-block solve of the error
    estimate matches (gamma/h E + G)^{-1}, and only the member with E = G = 0 is flagged
    singular."""
    tab = radau_iia(3)
    gen = torch.Generator().manual_seed(1)
    B, p = 64, 4
    E = torch.eye(p) + 0.1 * torch.randn(B, p, p, generator=gen)
    G = torch.randn(B, p, p, generator=gen)
    E[0], G[0] = torch.eye(p)[[1, 0, 3, 2]], 0.0
    h = 0.05 + torch.rand(B, generator=gen)
    R = torch.randn(B, 3, p, generator=gen)
    solver = StageLinearSolver(tab.A, torch.float64, "cpu")
    solver.want_real_block = True
    factors, singular = solver.factorize(E, G, h)
    assert factors[0] == "dense" and not singular.any()
    A = torch.as_tensor(np.array(tab.A))
    big = _kron(torch.eye(3), E) + h[:, None, None] * _kron(A, G)
    ref = -torch.linalg.solve(big, R.reshape(B, -1, 1)).reshape(R.shape)
    torch.testing.assert_close(solver.solve(factors, R, h), ref, rtol=1e-10, atol=1e-10)
    gamma, _ = embedded_weights(tab)
    rhs = torch.randn(B, p, generator=gen)
    real_block = gamma / h[:, None, None] * E + G
    torch.testing.assert_close(
        solver.solve_real_block(factors, rhs), torch.linalg.solve(real_block, rhs)
    )
    E[3], G[3] = 0.0, 0.0
    _, singular = solver.factorize(E, G, h)
    assert singular.tolist() == [i == 3 for i in range(B)]


@pytest.mark.parametrize("stages, p", [(1, 3), (3, 2), (5, 4)])
def test_real_block_inverse_read_off_the_full_inverse(stages, p):
    """The error filter's (gamma/h E + G)^{-1} is taken from J^{-1} (no second inverse); it
    equals the direct inverse, also for a singular E (DAE-like) and stiff G."""
    tab = radau_iia(stages)
    gen = torch.Generator().manual_seed(stages)
    B = 8
    E = torch.eye(p) + 0.1 * torch.randn(B, p, p, generator=gen)
    E[:2, -1, :] = 0.0  # algebraic row: E singular
    G = 1e4 * torch.randn(B, p, p, generator=gen)
    h = 1e-3 + torch.rand(B, generator=gen)
    solver = StageLinearSolver(np.array(tab.A), torch.float64, "cpu")
    solver.want_real_block = True
    factors, singular = solver.factorize(E, G, h)
    assert factors[0] == "dense" and not singular.any()
    gamma, _ = embedded_weights(tab)
    direct = torch.linalg.inv(gamma / h[:, None, None] * E + G)
    torch.testing.assert_close(factors[2], direct, rtol=1e-9, atol=1e-9 * direct.abs().max())


@pytest.mark.parametrize("tab", [radau_iia(1), radau_iia(3), gauss_legendre(2)])
def test_large_blocks_use_the_transformed_lu_path(tab):
    """s p > 24: per-eigenvalue LU of the real / complex blocks, same solution as the full
    solve."""
    gen = torch.Generator().manual_seed(2)
    B, p = 3, 25
    E = torch.eye(p) + 0.1 * torch.randn(B, p, p, generator=gen)
    G = torch.randn(B, p, p, generator=gen)
    h = 0.05 + torch.rand(B, generator=gen)
    R = torch.randn(B, tab.stages, p, generator=gen)
    solver = StageLinearSolver(tab.A, torch.float64, "cpu")
    factors, singular = solver.factorize(E, G, h)
    assert factors[0] == "transformed" and not singular.any()
    A = torch.as_tensor(np.array(tab.A))
    big = _kron(torch.eye(tab.stages), E) + h[:, None, None] * _kron(A, G)
    ref = -torch.linalg.solve(big, R.reshape(B, -1, 1)).reshape(R.shape)
    torch.testing.assert_close(solver.solve(factors, R, h), ref, rtol=1e-10, atol=1e-10)


def _vdp5(t, x):
    """Van der Pol with mu = 5."""
    return torch.stack([x[..., 1], 5 * (1 - x[..., 0] ** 2) * x[..., 1] - x[..., 0]], -1)


@pytest.mark.parametrize("batch", [None, 3])
def test_adaptive_radau_with_the_full_linear_solver_equals_the_default(batch):
    """linear_solver="full" (one LU of the s n x s n matrix plus the error filter's real
    block) takes the default solver's steps to rounding, on an ODE (against scipy's Radau)
    and on a DAE (against its closed form), unbatched and batched."""
    t = torch.linspace(0.0, 2.0, 5)
    scale = torch.tensor(1.0) if batch is None else torch.linspace(0.8, 1.0, batch)[:, None]
    x0 = torch.tensor([2.0, 0.0]) * scale
    kw = dict(method="radau_iia", rtol=1e-10, atol=1e-10, host_loop=False)
    ref = odeint(_vdp5, x0, t, **kw)
    full = odeint(_vdp5, x0, t, linear_solver="full", **kw)
    assert full.stats.extra["linear_solver"] == "full"
    assert torch.equal(full.stats.n_steps, ref.stats.n_steps)
    torch.testing.assert_close(full.x, ref.x, rtol=1e-12, atol=1e-12)
    for x0_i, x_i in zip(x0.reshape(-1, 2), full.x.reshape(-1, len(t), 2), strict=True):
        sp = solve_ivp(
            lambda tt, y: _vdp5(tt, torch.as_tensor(y)).numpy(),
            (0.0, 2.0),
            x0_i.numpy(),
            method="Radau",
            rtol=1e-12,
            atol=1e-12,
            t_eval=t.numpy(),
        )
        np.testing.assert_allclose(x_i.numpy(), sp.y.T, rtol=0, atol=1e-7)

    # x' = -z x, 0 = z - x^2: x = x0 / sqrt(1 + 2 x0^2 t), z = x^2
    dae = SemiExplicitDAE(lambda t, x, z: -z * x, lambda t, x, z: z - x**2)
    x0 = torch.ones(1) * scale
    dkw = dict(rtol=1e-10, atol=1e-10)
    ref = daeint(dae, x0, x0**2, t, **dkw)
    full = daeint(dae, x0, x0**2, t, linear_solver="full", **dkw)
    assert torch.equal(full.stats.n_steps, ref.stats.n_steps)
    torch.testing.assert_close(full.x, ref.x, rtol=1e-12, atol=1e-12)
    exact = x0[..., None, :] / torch.sqrt(1 + 2 * x0[..., None, :] ** 2 * t[:, None])
    torch.testing.assert_close(full.x, exact, rtol=1e-8, atol=1e-8)
    torch.testing.assert_close(full.z, exact**2, rtol=1e-8, atol=1e-8)


def _stiff_forced(t, x):
    """x0' = -1000 (x0 - cos t), x1' = x0 - x1 (stiffness ratio 1000)."""
    forcing = torch.cos(torch.as_tensor(t, dtype=x.dtype)).reshape(-1)[0]
    return torch.stack([-1000.0 * (x[..., 0] - forcing), x[..., 0] - x[..., 1]], -1)


@pytest.mark.parametrize("stages", [13, 15])
def test_adaptive_radau_with_many_stages_takes_the_full_solver_and_meets_scipy(stages):
    """Radau IIA with s >= 13 stages (whose A is not diagonalised well enough for the
    transformed solve, and whose determinant, 3e-17 at s = 13, is tiny although A is well
    conditioned) runs adaptively on the full factorisation with the error filter's real block,
    for an ODE (against scipy's Radau at rtol 1e-12) and a DAE (against its closed form)."""
    t = torch.linspace(0.0, 1.0, 5, dtype=torch.float64)
    x0 = torch.tensor([0.0, 1.0], dtype=torch.float64)
    kw = dict(method="radau_iia", stages=stages, rtol=1e-10, atol=1e-12)
    sol = odeint(_stiff_forced, x0, t, **kw)
    assert sol.stats.extra["linear_solver"] == "full"
    assert int(sol.status) == 0
    sp = solve_ivp(
        lambda tt, y: [-1000.0 * (y[0] - np.cos(tt)), y[0] - y[1]],
        (0.0, 1.0),
        x0.numpy(),
        method="Radau",
        rtol=1e-12,
        atol=1e-14,
        t_eval=t.numpy(),
    )
    np.testing.assert_allclose(sol.x.numpy(), sp.y.T, rtol=0, atol=1e-9)

    # x' = -z x, 0 = z - x^2: x = x0 / sqrt(1 + 2 x0^2 t), z = x^2
    dae = SemiExplicitDAE(lambda t, x, z: -z * x, lambda t, x, z: z - x**2)
    x0 = torch.tensor([[1.0], [0.5]], dtype=torch.float64)
    dsol = daeint(dae, x0, x0**2, t, stages=stages, rtol=1e-10, atol=1e-12)
    assert dsol.stats.extra["linear_solver"] == "full"
    exact = x0[..., None, :] / torch.sqrt(1 + 2 * x0[..., None, :] ** 2 * t[:, None])
    torch.testing.assert_close(dsol.x, exact, rtol=1e-9, atol=1e-9)
    torch.testing.assert_close(dsol.z, exact**2, rtol=1e-9, atol=1e-9)


def test_radau3_error_estimate_matches_radau5_constants():
    """Our Vandermonde-derived embedded weights e reproduce Hairer-Wanner/scipy's for s = 3:
    scipy uses f0 + Z^T E / h with Z = h A K, i.e. e = A^T E / gamma."""
    tab = radau_iia(3)
    gamma, e = embedded_weights(tab)
    s6 = 6**0.5
    E = np.array([-13 - 7 * s6, -13 + 7 * s6, -1]) / 3
    assert gamma == pytest.approx(3 + 3 ** (2 / 3) - 3 ** (1 / 3), rel=1e-13)
    np.testing.assert_allclose(e, np.array(tab.A).T @ E / gamma, rtol=1e-12)


@pytest.mark.parametrize("s", [1, 3, 5])
def test_embedded_method_has_order_s(s):
    """x_hat = x_k + h(gamma0 f(x_k) + sum (b + e)_i K_i) integrates t^(q-1) exactly, q <= s."""
    tab = radau_iia(s)
    gamma, e = embedded_weights(tab)
    c, bhat = np.array(tab.c), np.array(tab.b) + e
    for q in range(1, s + 1):
        assert bhat @ c ** (q - 1) + (1 / gamma) * (q == 1) == pytest.approx(1 / q, abs=1e-12)
    assert bhat @ c**s != pytest.approx(1 / (s + 1), abs=1e-6)


# ------------------------------------------------------------------------------- orders
def rotation_rhs(t, x):
    """x' = w(x) [x2, -x1] with w = 1 + |x|^2: nonlinear, |x| is conserved, so the exact
    solution is a rotation by the angle w(x0) t."""
    w = 1 + x.square().sum(-1, keepdim=True)
    return w * torch.stack([x[..., 1], -x[..., 0]], -1)


def rotation_exact(t_end, x0):
    w = 1 + x0.square().sum(-1)
    c, s = torch.cos(w * t_end), torch.sin(w * t_end)
    return torch.stack([c * x0[:, 0] + s * x0[:, 1], -s * x0[:, 0] + c * x0[:, 1]], -1)


def _errors(method, s, steps):
    """Global errors at the final time for the step counts ``steps``."""
    logistic = s == 1  # order 1-2: the mild logistic problem is in the asymptotic regime
    t_end = 1.0 if logistic else 10.0
    x0 = X0 if logistic else torch.tensor([[1.0, 0.0], [0.3, -0.4]])
    rhs = logistic_rhs if logistic else rotation_rhs
    exact = logistic_exact(torch.tensor(t_end), x0)[:, 0] if logistic else rotation_exact(t_end, x0)
    errs = []
    for N in steps:
        t = torch.linspace(0, t_end, N + 1)
        sol = solve_implicit_ode(
            rhs, x0, t, method, stages=s, adaptive=False, rtol=1e-14, atol=1e-14
        )
        assert sol.success
        errs.append(float((sol.x[:, -1] - exact).abs().max()))
    return errs


@pytest.mark.parametrize(
    "method,s,steps",
    [
        ("gauss_legendre", 1, (16, 32)),
        ("gauss_legendre", 2, (40, 80)),
        ("gauss_legendre", 3, (40, 80)),
        ("gauss_legendre", 4, (20, 40)),
        ("gauss_legendre", 5, (20, 40)),
        ("radau_iia", 1, (64, 128)),
        ("radau_iia", 2, (80, 160)),
        ("radau_iia", 3, (40, 80)),
        ("radau_iia", 4, (40, 80)),
        ("radau_iia", 5, (20, 40)),
    ],
)
def test_observed_order_of_collocation_methods(method, s, steps):
    """Fixed-step global error slope: 2s for Gauss-Legendre, 2s-1 for Radau IIA (notes §7.3)."""
    e1, e2 = _errors(method, s, steps)
    assert e2 > 1e-11, "the finer run must stay above round-off"
    order = math.log2(e1 / e2)
    expected = 2 * s if method == "gauss_legendre" else 2 * s - 1
    assert abs(order - expected) <= 0.2, (order, expected, e1, e2)


# ------------------------------------------------------------------------- stiff problems
def test_stiff_linear_system_adaptive_vs_matrix_exponential():
    """Notes eq. 6.42 (eigenvalues -200 +- 2000i and +-5i) against expm (closed form)."""
    plant = StiffLinear(eps=5e-4).requires_grad_(False)  # forward only: no IFT pass
    x0 = torch.tensor([[1.0, 0.0, 0.5, -0.5]])
    t = torch.linspace(0, 0.5, 6)
    sol = solve_implicit_ode(plant, x0, t, "radau_iia", rtol=1e-7, atol=1e-9)
    exact = plant.exact(t, x0).detach()
    assert sol.success
    assert float((sol.x.detach() - exact).abs().max()) < 2e-6
    # dt = 0.01 puts the fast eigenvalues at |lambda dt| = 20: RK4 explodes, Radau IIA is
    # accurate once the fast transient (unresolved, but damped: L-stability) has decayed
    t_fixed = torch.linspace(0, 0.5, 51)
    exact_fixed = plant.exact(t_fixed, x0).detach()
    rk4 = odeint(plant, x0, t_fixed, method="rk4")
    radau = solve_implicit_ode(plant, x0, t_fixed, "radau_iia", adaptive=False)
    assert not bool(torch.isfinite(rk4.x).all()) or float(rk4.x.abs().max()) > 1e6
    assert float((radau.x.detach() - exact_fixed)[..., 10:, :].abs().max()) < 1e-6


def test_stiff_van_der_pol_eps_1e6_to_requested_tolerance(stiff_vdp_reference):
    """y1' = y2, y2' = ((1 - y1^2) y2 - y1) / eps, eps = 1e-6, y0 = (2, 0), t in [0, 2], at
    rtol = atol = 1e-4: relative error of y(2) against scipy's Radau at 1e-12 within 0.1 rtol
    (measured 9.9e-3 rtol; the tighter tolerances are tested below)."""
    eps, rtol = 1e-6, 1e-4
    sol = solve_implicit_ode(
        StiffVanDerPol(eps).requires_grad_(False),
        torch.tensor([[2.0, 0.0]]),
        torch.tensor([0.0, 2.0]),
        "radau_iia",
        rtol=rtol,
        atol=rtol,
    )
    ref = stiff_vdp_reference(eps, 2.0)
    assert sol.success
    rel = np.abs(sol.x[0, -1].numpy() - ref) / np.abs(ref)
    assert rel.max() < 0.1 * rtol, rel / rtol
    # the factorisation and the Jacobian are reused across steps
    assert sol.stats.n_jac_evals < int(sol.stats.n_steps[0])
    assert int(sol.stats.n_newton_iters[0]) >= int(sol.stats.n_steps[0])


def robertson(t, y):
    y1, y2, y3 = y[..., 0], y[..., 1], y[..., 2]
    return torch.stack(
        [-0.04 * y1 + 1e4 * y2 * y3, 0.04 * y1 - 1e4 * y2 * y3 - 3e7 * y2**2, 3e7 * y2**2], -1
    )


def test_robertson_kinetics_against_scipy_bdf():
    """Robertson at rtol = 1e-6, atol = 1e-10 against scipy's BDF at 1e-12: every component
    at t = 0.4, 4, 40 within rtol relative (measured 1.0e-7 = 0.10 rtol, y3 at t = 4)."""
    t = torch.tensor([0.0, 0.4, 4.0, 40.0])
    sol = solve_implicit_ode(
        robertson, torch.tensor([[1.0, 0.0, 0.0]]), t, "radau_iia", rtol=1e-6, atol=1e-10
    )
    ref = solve_ivp(
        lambda t, y: robertson(t, torch.tensor(y)).numpy(),
        (0, 40),
        [1.0, 0.0, 0.0],
        method="BDF",
        rtol=1e-12,
        atol=1e-16,
        t_eval=t.numpy(),
    ).y.T
    assert sol.success
    rel = np.abs(sol.x[0].numpy() - ref) / (np.abs(ref) + 1e-12)
    assert rel[1:].max() < 1e-6, rel
    # the linear invariant y1 + y2 + y3 = 1 is kept by every RK method
    assert float((sol.x.sum(-1) - 1).abs().max()) < 1e-12


# ---------------------------------------------- stiff problems to the requested tolerance
# Each adaptive run goes through both Radau IIA drivers: the vectorised torch step loop
# (host_loop=False) and the default ("auto": the numpy host loop on the CPU, "host, one
# trajectory" for a single float64 trajectory). They take the same steps
# (tests/test_radau_host.py), so the bounds below hold for both with the same margin.
DRIVERS = [pytest.param(False, id="torch_driver"), pytest.param("auto", id="default_driver")]


def _driver_name(host_loop, batch):
    return "torch" if host_loop is False else ("host, one trajectory" if batch == 1 else "host")


@functools.cache
def _stiff_vdp_tight(rtol, host_loop, max_iter=None):
    """Adaptive Radau IIA (s = 3) on y1' = y2, y2' = ((1 - y1^2) y2 - y1) / eps, eps = 1e-6,
    y(0) = (2, 0), t in [0, 2] at rtol = atol = ``rtol`` (cached: several tests read one run)."""
    options = {} if max_iter is None else {"max_iter": max_iter}
    return solve_implicit_ode(
        StiffVanDerPol(1e-6).requires_grad_(False),
        torch.tensor([[2.0, 0.0]], dtype=torch.float64),
        torch.tensor([0.0, 2.0], dtype=torch.float64),
        "radau_iia",
        rtol=rtol,
        atol=rtol,
        host_loop=host_loop,
        **options,
    )


@pytest.mark.parametrize("host_loop", DRIVERS)
@pytest.mark.parametrize("rtol", [1e-6, 1e-8])
def test_stiff_van_der_pol_meets_tight_tolerances(rtol, host_loop, stiff_vdp_reference):
    """Stiff Van der Pol (eps = 1e-6, the stiff scaling of eq. 6.43), rtol = atol = 1e-6 and
    1e-8: the relative error of y(2) against scipy's Radau at rtol = atol = 1e-12 (conftest
    fixture) is at most 0.05 rtol in each component (measured 7.4e-3 rtol at 1e-6 and
    3.0e-3 rtol at 1e-8, on both drivers: margins 6.7x and 16x)."""
    sol = _stiff_vdp_tight(rtol, host_loop)
    assert sol.success
    assert sol.stats.extra["driver"] == _driver_name(host_loop, 1)
    ref = stiff_vdp_reference(1e-6, 2.0)
    rel = np.abs(sol.x[0, -1].numpy() - ref) / np.abs(ref)
    assert rel.max() <= 0.05 * rtol, rel / rtol


def _robertson_np(t, y):
    y1, y2, y3 = y
    return [-0.04 * y1 + 1e4 * y2 * y3, 0.04 * y1 - 1e4 * y2 * y3 - 3e7 * y2**2, 3e7 * y2**2]


def _robertson_jac_np(t, y):
    y1, y2, y3 = y
    return [
        [-0.04, 1e4 * y3, 1e4 * y2],
        [0.04, -1e4 * y3 - 6e7 * y2, -1e4 * y2],
        [0.0, 6e7 * y2, 0.0],
    ]


@functools.cache
def _robertson_reference(times: tuple) -> np.ndarray:
    """scipy BDF with the analytic Jacobian at rtol = 1e-13, atol = 1e-20 (agrees with scipy's
    Radau at the same tolerances to 3e-12 relative): (len(times), 3)."""
    out = solve_ivp(
        _robertson_np,
        (times[0], times[-1]),
        [1.0, 0.0, 0.0],
        method="BDF",
        jac=_robertson_jac_np,
        rtol=1e-13,
        atol=1e-20,
        t_eval=np.array(times),
    )
    assert out.success
    return out.y.T


@pytest.mark.parametrize("host_loop", DRIVERS)
def test_robertson_kinetics_to_rtol_1e9(host_loop):
    """Robertson's kinetics y1' = -0.04 y1 + 1e4 y2 y3, y2' = 0.04 y1 - 1e4 y2 y3 - 3e7 y2^2,
    y3' = 3e7 y2^2, y(0) = (1, 0, 0), at rtol = 1e-9, atol = 1e-14 (y2 peaks at 3.7e-5, so
    atol is ~3e-10 of the small component): every component at t = 0.4, 4 and 40 within rtol
    relative of the scipy reference (measured 1.2e-10 = 0.12 rtol, y3 at t = 0.4: margin
    8.6x); mass y1 + y2 + y3 = 1 kept to rounding."""
    times = (0.0, 0.4, 4.0, 40.0)
    sol = solve_implicit_ode(
        robertson,
        torch.tensor([[1.0, 0.0, 0.0]]),
        torch.tensor(times),
        "radau_iia",
        rtol=1e-9,
        atol=1e-14,
        host_loop=host_loop,
    )
    assert sol.success and sol.stats.extra["driver"] == _driver_name(host_loop, 1)
    ref = _robertson_reference(times)
    rel = np.abs(sol.x[0, 1:].numpy() - ref[1:]) / np.abs(ref[1:])
    assert rel.max() <= 1e-9, rel
    assert float((sol.x.sum(-1) - 1).abs().max()) < 1e-13


def _stiff_linear_matrix() -> np.ndarray:
    """M = V D V^-1, D = blocks [[-1, 1], [-1, -1]] (eigenvalues -1 +- i), -1e3, -1e5, with a
    fixed non-orthogonal V (cond 2.3): stiffness ratio 1e5, non-normal coupling."""
    V = np.eye(4) + 0.3 * np.random.default_rng(0).standard_normal((4, 4))
    D = np.zeros((4, 4))
    D[:2, :2] = [[-1.0, 1.0], [-1.0, -1.0]]
    D[2, 2], D[3, 3] = -1e3, -1e5
    return V @ D @ np.linalg.inv(V)


@pytest.mark.parametrize("host_loop", DRIVERS)
def test_stiff_linear_system_to_rtol_1e10_against_expm(host_loop):
    """x' = M x with eigenvalues -1 +- i, -1e3, -1e5 (fast transients excited by x0), two
    initial states, rtol = 1e-10, atol = 1e-12: against scipy's expm(M t) x0 at 11 times in
    [0, 1], max |x - x_exact| / (atol + rtol |x_exact|) <= 1 (the tolerance met component-
    wise; measured 0.16 on both drivers: margin 6x)."""
    M = _stiff_linear_matrix()
    Mt = torch.as_tensor(M)
    x0 = np.array([[1.0, 0.0, 0.5, -0.5], [0.2, -1.0, 0.0, 1.0]])
    t = np.linspace(0.0, 1.0, 11)
    sol = solve_implicit_ode(
        lambda t, x: x @ Mt.T,
        torch.as_tensor(x0),
        torch.as_tensor(t),
        "radau_iia",
        rtol=1e-10,
        atol=1e-12,
        host_loop=host_loop,
    )
    assert sol.success and sol.stats.extra["driver"] == _driver_name(host_loop, 2)
    exact = np.stack([x0 @ expm(M * s).T for s in t], 1)
    weighted = np.abs(sol.x.numpy() - exact) / (1e-12 + 1e-10 * np.abs(exact))
    assert weighted.max() <= 1.0, weighted.max()


@pytest.mark.parametrize("host_loop", DRIVERS)
def test_newton_failures_are_rejected_and_retried(host_loop, stiff_vdp_reference):
    """Stiff Van der Pol (eps = 1e-6) at rtol = atol = 1e-4 with max_iter = 2 Newton
    iterations per stage solve (the default is 7): most stage solves cannot converge, each
    failure rejects the step and retries it (fresh Jacobian, then half the step; radau.py),
    and the run still succeeds and meets the tolerance. Rejections: 487 with max_iter = 2
    against 15 by default (asserted > 10x); never more than max_iter iterations per attempt;
    relative error of y(2) against scipy's Radau at 1e-12 within 0.1 rtol for both (measured
    0.017 and 0.010 rtol)."""
    few = _stiff_vdp_tight(1e-4, host_loop, max_iter=2)
    default = _stiff_vdp_tight(1e-4, host_loop)
    assert few.success and default.success
    n_few, n_default = int(few.stats.n_rejected[0]), int(default.stats.n_rejected[0])
    assert n_few > 10 * n_default > 0, (n_few, n_default)
    attempts = int(few.stats.n_steps[0] + few.stats.n_rejected[0])
    assert int(few.stats.n_newton_iters[0]) <= 2 * attempts
    ref = stiff_vdp_reference(1e-6, 2.0)
    for sol in (few, default):
        rel = np.abs(sol.x[0, -1].numpy() - ref) / np.abs(ref)
        assert rel.max() <= 0.1 * 1e-4, rel


# ------------------------------------------------------------- Jacobian / LU reuse
def _stability_matrix(tab, hM: np.ndarray) -> np.ndarray:
    """One step of the tableau on x' = M x: x_{k+1} = R(hM) x_k with the matrix stability
    function R(hM) = I + (b^T (x) hM) (I - A (x) hM)^{-1} (1 (x) I) (eq. 7.11 for implicit
    Euler), by numpy."""
    A, b, n = np.array(tab.A), np.array(tab.b), hM.shape[0]
    big = np.eye(tab.stages * n) - np.kron(A, hM)
    ones = np.kron(np.ones((tab.stages, 1)), np.eye(n))
    return np.eye(n) + np.kron(b[None, :], hM) @ np.linalg.solve(big, ones)


@pytest.mark.parametrize(
    "method, stages",
    [
        ("implicit_euler", None),
        ("implicit_midpoint", None),
        ("gauss_legendre", 2),
        ("gauss_legendre", 3),
        ("radau_iia", 3),
        ("radau_iia", 5),
    ],
)
def test_fixed_step_linear_system_factorises_once(method, stages):
    """x' = M x (constant Jacobian; eigenvalues -1, -1e2, -1e4, non-normal), fixed steps. The
    promise of integrators/_irk_fixed.py: the Newton matrix is reused while the stage solve
    converges in two iterations or contracts fast and the step size is unchanged. On 200
    uniform steps: 1 Jacobian and 1 factorisation (before the fix of the reuse rule: up to 75
    of each for Radau IIA s = 5, where a rate of round-off over round-off counted as slow);
    on a grid of two step sizes (100 + 100 steps): 1 Jacobian, 2 factorisations. The states
    equal the exact discrete map x_{k+1} = R(h M) x_k to 1e-12 relative."""
    from integrators.methods import resolve_method

    V = np.eye(3) + 0.3 * np.random.default_rng(0).standard_normal((3, 3))
    M = V @ np.diag([-1.0, -1e2, -1e4]) @ np.linalg.inv(V)
    Mt = torch.as_tensor(M)
    x0 = np.array([[1.0, -0.5, 2.0], [0.0, 1.0, 0.3]])
    tab = resolve_method(method).tableau(stages)
    uniform = np.linspace(0.0, 1.0, 201)
    two_sizes = np.concatenate([np.linspace(0.0, 0.5, 101), np.linspace(0.5, 1.5, 101)[1:]])
    for grid, n_lu in ((uniform, 1), (two_sizes, 2)):
        sol = solve_implicit_ode(
            lambda t, x: x @ Mt.T,
            torch.as_tensor(x0),
            torch.as_tensor(grid),
            method,
            stages=stages,
            adaptive=False,
            rtol=1e-10,
            atol=1e-12,
        )
        assert sol.success and sol.stats.n_steps.tolist() == [200, 200]
        assert (sol.stats.n_jac_evals, sol.stats.n_factorizations) == (1, n_lu)
        x, xs = x0, [x0]
        for k in range(len(grid) - 1):
            x = x @ _stability_matrix(tab, M * (grid[k + 1] - grid[k])).T
            xs.append(x)
        exact = np.stack(xs, 1)
        assert np.abs(sol.x.numpy() - exact).max() <= 1e-12 * np.abs(exact).max()


@pytest.mark.parametrize("host_loop", DRIVERS)
@pytest.mark.parametrize("rtol", [1e-6, 1e-8])
def test_adaptive_radau_reuses_jacobians_and_factorisations(rtol, host_loop):
    """integrators/radau.py: the Jacobian is re-evaluated only when Newton failed or needed
    more than two iterations and contracted slowly; the factorisation is kept when the step
    would grow by less than 20 %. On stiff Van der Pol (eps = 1e-6, the runs of the accuracy
    test above): fewer Jacobians than steps / 3 (measured 0.22 and 0.18 of the steps at 1e-6
    and 1e-8) and fewer factorisations than 0.85 steps (measured 0.74 and 0.68); every
    Jacobian is factorised (n_jac <= n_lu)."""
    sol = _stiff_vdp_tight(rtol, host_loop)
    steps = int(sol.stats.n_steps[0])
    n_jac, n_lu = sol.stats.n_jac_evals, sol.stats.n_factorizations
    assert n_jac < steps / 3, (n_jac, steps)
    assert n_lu < 0.85 * steps, (n_lu, steps)
    assert n_jac <= n_lu


# ----------------------------------------------------------------------------- gradients
class Damped(torch.nn.Module):
    def __init__(self):
        super().__init__()
        self.k = torch.nn.Parameter(torch.tensor([2.0, 0.5]))

    def forward(self, t, x):
        k = self.k
        return torch.stack(
            [x[..., 1], -k[0] * x[..., 0] - k[1] * x[..., 1] * (1 + x[..., 0] ** 2)], -1
        )


@pytest.mark.parametrize("adaptive", [False, True])
def test_ift_gradients_match_central_differences(adaptive, central_difference):
    model = Damped()
    x0 = torch.tensor([[1.0, 0.3]], requires_grad=True)
    t = torch.tensor([0.0, 1.5])
    tol = 1e-12 if not adaptive else 1e-10

    def loss(x0_):
        sol = solve_implicit_ode(
            model, x0_, t, "radau_iia", adaptive=adaptive, substeps=8, rtol=tol, atol=tol
        )
        return sol.x[..., -1, :].pow(2).sum()

    gx, gk = torch.autograd.grad(loss(x0), (x0, model.k))
    fd_k = central_difference(lambda: loss(x0), model.k)
    fd_x = central_difference(lambda: loss(x0), x0)
    rel_tol = 1e-6 if not adaptive else 1e-5  # adaptive FD also moves the step sequence
    assert float((gk - fd_k).abs().max() / gk.abs().max()) < rel_tol
    assert float((gx - fd_x).abs().max() / gx.abs().max()) < rel_tol


def _radau_accepted_steps(sol):
    """Start times and sizes (numpy) of the accepted steps of a one-trajectory adaptive Radau
    IIA solution. Not public: read from the dense-output records
    (``integrators._irk_dense.StepRecords``) that ``sol.interpolant`` closes over; record 0 is
    the initial point, and a start of +inf marks a driver iteration in which the sample did
    not advance (a rejection)."""
    cells = sol.interpolant.__code__.co_freevars, sol.interpolant.__closure__
    records = dict(zip(*cells, strict=True))["records"].cell_contents

    def first(v):
        v = v.detach().cpu().numpy() if isinstance(v, torch.Tensor) else np.asarray(v)
        return float(v.reshape(-1)[0])

    start = np.array([first(v) for v in records.t0[1:]])
    h = np.array([first(v) for v in records.h[1:]])
    keep = np.isfinite(start)
    return start[keep], h[keep]


def test_adaptive_radau_gradients_equal_fixed_grid_gradients_and_central_differences(
    central_difference, accepted_grid, same_values_and_gradients
):
    """IFT gradients of adaptive Radau IIA (s = 3) at rtol = atol = 1e-10 on Van der Pol
    (eq. 6.43, mu an nn.Parameter, = 1), x0 = (2, 0), loss L = x1(2) + x2(2) + x1(2)^2,
    with respect to x0 and mu, on both drivers. Central differences of an adaptive solver
    also move its step sequence, so the finite-difference truth is taken on the same steps:
    (a) Radau IIA at fixed steps on exactly the accepted step times (468 steps on each
    driver) gives the same x(T) to 1e-12 relative (measured 1.4e-15); (b) the adaptive
    IFT gradients equal its gradients to 1e-10 relative (measured 6e-15: step sizes are not
    differentiated, notes eq. 3.40 / 8.24 per step); (c) those equal central differences of
    the fixed-grid run (default driver's grid) to 1e-6 relative (the acceptance bound;
    measured 2e-9)."""
    model = VanDerPol(1.0)
    x0 = torch.tensor([[2.0, 0.0]], requires_grad=True)
    t_end, opts = 2.0, dict(rtol=1e-10, atol=1e-10)

    def loss(x_end):
        return x_end.sum() + x_end[0] ** 2

    n_steps = []
    for host_loop in (False, "auto"):
        sol = solve_implicit_ode(
            model, x0, torch.tensor([0.0, t_end]), "radau_iia", host_loop=host_loop, **opts
        )
        assert sol.success
        start, h = _radau_accepted_steps(sol)
        n_steps.append(len(start))
        grid = accepted_grid(start, h, int(sol.stats.n_steps[0]), t_end)
        fixed = solve_implicit_ode(model, x0, grid, "radau_iia", adaptive=False, **opts)
        assert fixed.success and int(fixed.stats.n_steps[0]) == len(start)
        g_fixed = same_values_and_gradients(sol.x[0, -1], fixed.x[0, -1], loss, (x0, model.mu))
    assert n_steps[0] == n_steps[1]  # the drivers take the same steps (to rounding)

    def fixed_loss():
        with torch.no_grad():
            x_end = solve_implicit_ode(model, x0, grid, "radau_iia", adaptive=False, **opts)
            return loss(x_end.x[0, -1])

    for param, g in zip((x0, model.mu), g_fixed, strict=True):
        fd = central_difference(fixed_loss, param)
        assert float((g - fd).abs().max() / g.abs().max()) < 1e-6


def _graph_size(newton_tol):
    """Number of autograd nodes and bytes of tensors saved in the graph of x(T)."""
    model = Damped()
    x0 = torch.tensor([[1.0, 0.0]], requires_grad=True)
    sol = solve_implicit_ode(
        model,
        x0,
        torch.linspace(0, 1, 5),
        "gauss_legendre",
        adaptive=False,
        substeps=4,
        newton_tol=newton_tol,
        max_iter=30,
        rtol=1e-10,
        atol=1e-10,
    )
    out = sol.x[..., -1, :].sum()
    seen, stack, saved = set(), [out.grad_fn], 0
    while stack:
        node = stack.pop()
        if node is None or node in seen:
            continue
        seen.add(node)
        for name in dir(node):
            if name.startswith("_saved_"):
                value = getattr(node, name)
                if isinstance(value, torch.Tensor):
                    saved += value.numel() * value.element_size()
        stack.extend(fn for fn, _ in node.next_functions)
    out.backward()
    return len(seen), saved, int(sol.stats.n_newton_iters.sum()), model.k.grad.clone()


def test_gradient_graph_does_not_grow_with_newton_iterations():
    loose_nodes, loose_bytes, loose_iters, g_loose = _graph_size(1e-1)
    tight_nodes, tight_bytes, tight_iters, g_tight = _graph_size(1e-8)
    assert tight_iters > loose_iters
    assert tight_nodes == loose_nodes and tight_bytes == loose_bytes
    torch.testing.assert_close(g_loose, g_tight, rtol=1e-5, atol=1e-8)


# ------------------------------------------------------------------------------ batching


def _stiff_vdp_run(eps, x0, t, host_loop):
    """Adaptive Radau IIA on StiffVanDerPol(eps) at rtol = atol = 1e-5 (batch-vs-alone tests),
    on the host or the torch step loop."""
    sol = solve_implicit_ode(
        StiffVanDerPol(eps).requires_grad_(False),
        x0,
        t,
        "radau_iia",
        rtol=1e-5,
        atol=1e-5,
        host_loop=host_loop,
    )
    assert sol.stats.extra["host_loop"] is host_loop
    return sol


@pytest.mark.parametrize("host_loop", [False, True])
def test_batch_invariance_of_adaptive_radau(host_loop):
    """Each member keeps its own steps: same answer and step counts alone and in a batch."""
    eps = torch.tensor([[1e-6], [1e-2], [1.0]])
    x0 = torch.tensor([[2.0, 0.0], [2.0, 0.0], [1.0, 0.5]])
    t = torch.tensor([0.0, 0.2, 0.4])
    batch = _stiff_vdp_run(eps, x0, t, host_loop)
    for i in range(3):
        alone = _stiff_vdp_run(eps[i : i + 1], x0[i : i + 1], t, host_loop)
        torch.testing.assert_close(alone.x[0], batch.x[i], rtol=1e-11, atol=1e-11)
        assert int(alone.stats.n_steps[0]) == int(batch.stats.n_steps[i])
        assert int(alone.stats.n_rejected[0]) == int(batch.stats.n_rejected[i])
    assert int(batch.stats.n_steps[0]) > 3 * int(batch.stats.n_steps[2])


@pytest.mark.parametrize("host_loop", [False, True])
def test_dense_output_of_a_batch_equals_each_member_alone(host_loop):
    """Members of a batch reject and accept different steps (a rejected or idle member's step
    record is skipped by the dense output): sol.at of the batch equals each member's own."""
    eps = torch.tensor([[1e-5], [3e-3], [0.3]])
    x0 = torch.tensor([[2.0, 0.0], [2.0, 0.0], [1.0, 0.5]])
    t = torch.tensor([0.0, 0.5])
    tq = torch.linspace(0.0, 0.5, 23)
    batch = _stiff_vdp_run(eps, x0, t, host_loop)
    assert int(batch.stats.n_rejected.sum()) > 0
    assert len(set(batch.stats.n_steps.tolist())) == 3
    for i in range(3):
        alone = _stiff_vdp_run(eps[i : i + 1], x0[i : i + 1], t, host_loop)
        torch.testing.assert_close(alone.at(tq)[0], batch.at(tq)[i], rtol=1e-11, atol=1e-11)


def _rotation_first_axis_only(t, x):
    """rotation_rhs written for 2-D inputs only (x[:, 0]): wrong for an extra stage dimension."""
    w = 1 + x.square().sum(-1, keepdim=True)
    return w * torch.stack([x[:, 1], -x[:, 0]], -1)


def _rotation_scalar_time(t, x):
    """rotation_rhs that needs a one-element t (float(t)): fails on stacked stage times."""
    return rotation_rhs(t, x) * (1.0 + 0.0 * float(t))


@pytest.mark.parametrize("adaptive, host_loop", [(False, False), (True, False), (True, True)])
def test_stage_stacking_probe_falls_back_for_functions_that_need_it(adaptive, host_loop):
    """All stages are evaluated in one call (stage index as leading batch dimension) only when
    a probe reproduces the stage-by-stage residuals; a function indexing x[:, 0] (wrong
    values when stacked, for a batch of 2 even with the right shape) or calling float(t)
    (raises when stacked) is evaluated stage by stage, with the same results."""
    x0 = torch.tensor([[1.0, 0.0], [0.3, -0.4]])
    t = torch.linspace(0.0, 1.0, 6)
    opts = dict(adaptive=adaptive, substeps=4, rtol=1e-8, atol=1e-10, host_loop=host_loop)
    ref = solve_implicit_ode(rotation_rhs, x0, t, "radau_iia", **opts)
    assert ref.stats.extra["stacked_stages"] and ref.stats.extra["host_loop"] is host_loop
    for fn in (_rotation_first_axis_only, _rotation_scalar_time):
        if fn is _rotation_scalar_time and adaptive:
            continue  # adaptive times are per sample, (*batch, 1): float(t) is not defined
        sol = solve_implicit_ode(fn, x0, t, "radau_iia", **opts)
        assert not sol.stats.extra["stacked_stages"]
        torch.testing.assert_close(sol.x, ref.x, rtol=1e-12, atol=1e-12)
    exact = rotation_exact(1.0, x0)
    assert float((ref.x[:, -1] - exact).abs().max()) < 1e-6


def _forced_rotation(t, x, u):
    """rotation_rhs plus a force u (*batch, 2), elementwise: its stages stack with their
    inputs."""
    return rotation_rhs(t, x) + u


def _forced_rotation_first_axis_only(t, x, u):
    """_forced_rotation written for (batch, nu) inputs (u[:, i]): wrong values, or an error,
    when the stages and their inputs are stacked on a leading axis."""
    u = u.expand(x.shape[0], -1) if u.dim() == 1 else u
    return rotation_rhs(t, x) + torch.stack([u[:, 0], u[:, 1]], -1)


@pytest.mark.parametrize("shared_input", [True, False])
@pytest.mark.parametrize("adaptive, host_loop", [(False, False), (True, False), (True, True)])
def test_stages_stack_with_their_inputs(adaptive, host_loop, shared_input):
    """With an input, the stages and their inputs are evaluated in one stacked call where the
    probe allows it, and give the stage-by-stage results; a model that mixes up the stage and
    batch axes of u is evaluated stage by stage. Fixed steps: samples (T, nu) or
    (*batch, T, nu) held at u_k over each step (eq. 8.34); adaptive steps: a smooth callable
    u(t) (a held input's jumps would make the step control sensitive to rounding), shared or
    scaled per sample."""
    x0 = torch.tensor([[1.0, 0.0], [0.3, -0.4]], dtype=torch.float64)
    t = torch.linspace(0.0, 1.0, 6, dtype=torch.float64)
    scale = torch.ones(()) if shared_input else torch.tensor([[1.0], [-0.5]], dtype=t.dtype)

    def smooth(t):
        t = t if t.dim() else t.reshape(1)
        return scale * torch.cat([torch.sin(3 * t), torch.cos(2 * t)], -1)

    samples = smooth(t[:, None]) if shared_input else smooth(t[:, None, None]).movedim(0, -2)
    u = smooth if adaptive else samples  # held samples: (T, 2) or (2, T, 2)
    opts = dict(method="radau_iia", rtol=1e-10, atol=1e-12, host_loop=host_loop)
    opts = opts if adaptive else dict(opts, adaptive=False, substeps=4)
    sol = odeint(_forced_rotation, x0, t, u=u, **opts)
    ref = odeint(_forced_rotation_first_axis_only, x0, t, u=u, **opts)
    assert sol.stats.extra["stacked_stages"] and not ref.stats.extra["stacked_stages"]
    assert sol.stats.extra["host_loop"] is ref.stats.extra["host_loop"] is host_loop
    torch.testing.assert_close(sol.x, ref.x, rtol=1e-12, atol=1e-12)
    assert sol.stats.n_f_evals == ref.stats.n_f_evals
    if adaptive:  # independent truth: scipy's DOP853 at 1e-13 on the same forced system
        for b in range(2):

            def rhs(tt, xx, b=b):
                x_t = torch.as_tensor(xx, dtype=t.dtype)[None]
                u_b = smooth(torch.tensor([[tt]], dtype=t.dtype)).expand(2, 2)[b]
                return _forced_rotation(None, x_t, u_b).numpy()[0]

            truth = solve_ivp(
                rhs, (0.0, 1.0), x0[b].numpy(), "DOP853", t_eval=t.numpy(), rtol=1e-13, atol=1e-13
            ).y.T
            assert np.abs(sol.x[b].numpy() - truth).max() < 1e-10  # measured 7e-12


@pytest.mark.parametrize("adaptive", [False, True])
def test_unbatched_state_equals_a_batch_of_one(adaptive):
    """x0 of shape (n,) (no batch dimension): same numbers and statuses as (1, n), with the
    exact rotation as reference."""
    t = torch.linspace(0.0, 1.0, 5)
    x0 = torch.tensor([1.0, 0.0])
    opts = dict(adaptive=adaptive, substeps=4, rtol=1e-8, atol=1e-10)
    alone = solve_implicit_ode(rotation_rhs, x0, t, "radau_iia", **opts)
    batch = solve_implicit_ode(rotation_rhs, x0[None], t, "radau_iia", **opts)
    assert alone.x.shape == (5, 2) and alone.status.shape == ()
    torch.testing.assert_close(alone.x, batch.x[0], rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(alone.at(t[1:3]), batch.at(t[1:3])[0], rtol=1e-12, atol=1e-12)
    assert int(alone.stats.n_steps) == int(batch.stats.n_steps[0])
    assert float((alone.x[-1] - rotation_exact(1.0, x0[None])[0]).abs().max()) < 1e-6


@pytest.mark.parametrize("adaptive", [False, True])
def test_grad_mode_does_not_change_the_solution(adaptive):
    """With autograd on (IFT graph attached) or off, the numbers are the same."""
    mu = torch.tensor(1.5, requires_grad=True)

    def vdp(t, x):
        return torch.stack([mu * (1 - x[..., 1] ** 2) * x[..., 0] - x[..., 1], x[..., 0]], -1)

    x0 = torch.tensor([[0.5, 1.0], [1.0, -0.5]])
    t = torch.linspace(0.0, 2.0, 11)
    opts = dict(adaptive=adaptive, rtol=1e-7, atol=1e-9)
    with_grad = solve_implicit_ode(vdp, x0, t, "radau_iia", **opts)
    with torch.no_grad():
        without = solve_implicit_ode(vdp, x0, t, "radau_iia", **opts)
    assert with_grad.x.requires_grad and not without.x.requires_grad
    torch.testing.assert_close(with_grad.x.detach(), without.x, rtol=0, atol=0)
    assert with_grad.stats.n_steps.tolist() == without.stats.n_steps.tolist()


@settings(max_examples=6, deadline=None)
@given(lam=st.floats(-1e5, -1e-2), x0=st.floats(-3, 3))
def test_linear_test_equation_any_stiffness(lam, x0):
    """x' = lam x (eq. 6.40) for any stiffness: adaptive Radau IIA meets its tolerance."""
    t = torch.tensor([0.0, 0.3, 1.0])
    sol = solve_implicit_ode(
        lambda t, x: lam * x, torch.tensor([[x0]]), t, "radau_iia", rtol=1e-8, atol=1e-10
    )
    exact = x0 * torch.exp(lam * t)
    assert sol.success
    assert float((sol.x[0, :, 0] - exact).abs().max()) < 1e-7 * (1 + abs(x0))


# --------------------------------------------------------------------- dense output, misc
@pytest.mark.parametrize("adaptive", [False, True])
def test_dense_output_of_collocation_polynomial(adaptive):
    t = torch.linspace(0, 1, 5)
    sol = solve_implicit_ode(
        logistic_rhs, X0, t, "radau_iia", adaptive=adaptive, substeps=8, rtol=1e-9, atol=1e-9
    )
    tq = torch.tensor([0.13, 0.5, 0.77, 1.0])
    exact = logistic_exact(tq[:, None], X0[:, None, :]).squeeze(-2)
    assert float((sol.at(tq) - exact).abs().max()) < 1e-6
    torch.testing.assert_close(sol.at(t), sol.x, rtol=1e-12, atol=1e-12)


def test_zero_order_hold_input_is_held_over_each_step():
    """x' = -x + u with u held (eq. 8.34): one 3-stage Gauss step per interval (order 6,
    dt = 0.25) matches the exact discretisation to ~1e-8 even at the input jump."""
    t = torch.linspace(0, 2, 9)
    u = torch.where(t < 1, 1.0, -2.0)[:, None]
    rhs = bind_rhs(lambda t, x, u: -x + u, u, t)
    sol = solve_implicit_ode(
        rhs,
        torch.tensor([[0.5]]),
        t,
        "gauss_legendre",
        stages=3,
        adaptive=False,
        rtol=1e-13,
        atol=1e-13,
    )
    x = 0.5
    exact = [x]
    for k in range(8):
        dt = float(t[k + 1] - t[k])
        x = float(u[k]) + (x - float(u[k])) * math.exp(-dt)
        exact.append(x)
    torch.testing.assert_close(sol.x[0, :, 0], torch.tensor(exact), rtol=1e-8, atol=1e-8)


def test_odeint_dispatch_and_float32():
    t = torch.linspace(0, 1, 5)
    direct = solve_implicit_ode(logistic_rhs, X0, t, "gauss_legendre", adaptive=False)
    via = odeint(logistic_rhs, X0, t, method="gauss_legendre")
    torch.testing.assert_close(direct.x, via.x)
    sol32 = solve_implicit_ode(
        logistic_rhs, X0.float(), t.float(), "radau_iia", rtol=1e-5, atol=1e-6
    )
    assert sol32.x.dtype == torch.float32 and sol32.success
    exact = logistic_exact(torch.tensor(1.0), X0)[:, 0]
    assert float((sol32.x[:, -1].double() - exact).abs().max()) < 1e-4


def test_status_and_messages_for_failures():
    # finite escape time of x' = x^2 at t = 1: the sample stops, the other one finishes
    x0 = torch.tensor([[1.0], [-1.0]])
    sol = solve_implicit_ode(lambda t, x: x**2, x0, torch.tensor([0.0, 2.0]), "radau_iia")
    assert sol.status[0] != Status.SUCCESS and sol.status[1] == Status.SUCCESS
    assert any("sample (0,)" in m and "t = 1" in m for m in sol.messages), sol.messages
    torch.testing.assert_close(sol.x[1, -1], torch.tensor([-1 / 3]), rtol=1e-5, atol=1e-6)
    few = solve_implicit_ode(
        StiffVanDerPol(1e-6).requires_grad_(False),
        torch.tensor([[2.0, 0.0]]),
        torch.tensor([0.0, 2.0]),
        "radau_iia",
        max_steps=5,
    )
    assert few.status[0] == Status.MAX_STEPS and "max_steps" in few.messages[0]
    # a fixed implicit Euler step far too long for x' = x^2 from x0 = 1: no root of the stage
    # equation x1 = 1 + 2 x1^2 exists, Newton must fail and say so
    bad = solve_implicit_ode(
        lambda t, x: x**2,
        torch.tensor([[1.0]]),
        torch.tensor([0.0, 2.0]),
        "implicit_euler",
        adaptive=False,
    )
    assert bad.status[0] == Status.NEWTON_FAILED
    assert "did not converge" in bad.messages[0]


@pytest.mark.parametrize("method, stages", [("implicit_euler", None), ("radau_iia", 3)])
def test_fixed_step_falls_back_to_damped_newton_when_simplified_newton_diverges(method, stages):
    """x' = x (1 - x), x0 = 0.1, dt = 1: the Jacobian frozen at x0 gives a simplified-Newton
    contraction factor of about 2.2, so only the damped exact-Newton fallback (Theorem 4)
    solves the step. Implicit Euler's step solves x1 = x0 + x1 (1 - x1), i.e. x1^2 = 0.1."""
    x0 = torch.tensor([0.1])
    t = torch.tensor([0.0, 1.0, 2.0])
    sol = odeint(lambda t, x: x * (1 - x), x0, t, method=method, stages=stages, adaptive=False)
    assert sol.success
    if method == "implicit_euler":
        torch.testing.assert_close(sol.x[1, 0], torch.tensor(0.1**0.5), rtol=1e-9, atol=0)
    else:  # order 5 at dt = 1: close to the logistic closed form
        exact = 0.1 * torch.exp(t) / (1 - 0.1 + 0.1 * torch.exp(t))
        torch.testing.assert_close(sol.x[:, 0], exact, rtol=2e-3, atol=0)


# ------------------------------------------------------------ batch-speed paths (same results)
def _pendulum_family(t, x):
    """x1' = x2, x2' = -w^2 sin(x1) - x1^3 x2 with a per-member w (batch of 3)."""
    w = torch.tensor([[0.5], [1.0], [2.0]])
    return torch.cat(
        [x[..., 1:2], -(w**2) * torch.sin(x[..., 0:1]) - x[..., 0:1] ** 3 * x[..., 1:2]], -1
    )


def test_stacked_jacobian_equals_row_by_row_and_central_differences():
    """One backward pass over q stacked copies (unit cotangents e_i) gives the same Jacobian
    as q backward passes, to the last bit, and both match central differences (also for a map
    with more inputs than outputs, as for the implicit residual F(K, X))."""
    v = torch.tensor([[0.3, -0.2], [1.1, 0.4], [-0.7, 2.0]])
    fun = lambda x: _pendulum_family(0.0, x)  # noqa: E731
    rows = batch_jacobian(fun, v, strategy="rows")[1]
    stacked = batch_jacobian(fun, v, strategy="stacked", outputs=2)[1]
    assert torch.equal(rows, stacked)
    d = 1e-6
    fd = torch.stack(
        [(fun(v + d * e) - fun(v - d * e)) / (2 * d) for e in torch.eye(2)], -1
    )  # (batch, q, d)
    torch.testing.assert_close(stacked, fd, rtol=1e-7, atol=1e-8)

    def implicit(kx):  # F(K, X) = K - f(X): 4 inputs, 2 outputs
        return kx[..., :2] - _pendulum_family(0.0, kx[..., 2:])

    kx = torch.cat([torch.ones(3, 2), v], -1)
    J = batch_jacobian(implicit, kx, strategy="stacked")[1]
    assert torch.equal(J, batch_jacobian(implicit, kx, strategy="rows")[1])
    torch.testing.assert_close(J[..., :2], torch.eye(2).expand(3, 2, 2))
    torch.testing.assert_close(J[..., 2:], -fd, rtol=1e-7, atol=1e-8)


def test_stacked_jacobian_probe_falls_back_for_functions_that_need_it():
    """StageSystem uses the stacked Jacobian only after it reproduced the row-by-row one; a
    function indexing x[:, 0] (mixes stack copies and batch) keeps the row-by-row Jacobian
    (its solutions are compared in the stage-stacking probe test above)."""
    from integrators._irk_system import StageSystem

    v = torch.tensor([[1.0, 0.0], [0.3, -0.4]])
    d = 1e-6
    fd = torch.stack(
        [
            (rotation_rhs(0.0, v + d * e) - rotation_rhs(0.0, v - d * e)) / (2 * d)
            for e in torch.eye(2)
        ],
        -1,
    )
    good = StageSystem("ode", 2, 0, (rotation_rhs,), has_input=False)
    bad = StageSystem("ode", 2, 0, (_rotation_first_axis_only,), has_input=False)
    for system, expect in ((good, True), (bad, False)):
        for _ in range(2):  # probe, then the cached decision
            E, G, _, _ = system.blocks(torch.tensor(0.0), v, v, v[..., :0], None)
            torch.testing.assert_close(G, -fd, rtol=1e-7, atol=1e-8)
        assert system.stack_jacobian == {2: expect}


def test_small_kronecker_products_by_one_matrix_product_are_exact():
    """The explicit-inverse path builds A (x) G and I (x) E by one GEMM with a 0/1-pattern
    matrix: identical to the broadcast Kronecker product."""
    tab = radau_iia(3)
    solver = StageLinearSolver(np.array(tab.A), torch.float64, "cpu")
    G = torch.randn(4, 5, 2, 2, generator=torch.Generator().manual_seed(3))
    E = torch.randn(4, 5, 2, 2, generator=torch.Generator().manual_seed(4))
    IE, AG = solver.prepare(E, G)
    A = torch.as_tensor(np.array(tab.A))
    assert torch.equal(AG, _kron(A, G))
    assert torch.equal(IE, _kron(torch.eye(3, dtype=A.dtype), E))


def test_stage_extrapolation_matrix_is_the_lagrange_basis():
    """L[i, j] = l_j(1 + c_i r) (eq. 7.27 basis at the next step's nodes), per member ratio."""
    from integrators._irk_dense import extrapolation_matrix
    from integrators.collocation import lagrange_basis

    c = np.array(radau_iia(3).c)
    ratio = np.array([0.5, 1.0, 3.0])
    L = extrapolation_matrix(c, ratio)
    tau = torch.as_tensor(1.0 + c * ratio[:, None])
    ref = lagrange_basis(torch.as_tensor(c), tau)
    np.testing.assert_allclose(L, ref.numpy(), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(extrapolation_matrix(c, 1.0), ref[1].numpy(), atol=1e-12)


IMPLICIT_DRIVERS = {
    "host (one trajectory or batched)": dict(method="radau_iia"),
    "torch": dict(method="radau_iia", host_loop=False),
    "fixed radau": dict(method="radau_iia", adaptive=False, substeps=20),
    "gauss": dict(method="gauss_legendre", substeps=20),
}


@pytest.mark.parametrize("driver", IMPLICIT_DRIVERS)
@pytest.mark.parametrize("batch", [(), (2, 3)])
def test_tensor_tolerances_per_component_and_sample(driver, batch):
    """``rtol``/``atol`` tensors broadcast to the states (*batch, n): a 0-dim tensor gives the
    float's run; adaptive runs measure each component against its own tolerance and give
    each sample its own steps, so a tight entry tightens its component, and a tight sample
    leaves the others' runs as they were (x' = -x, exact x(1) = e^-1 x0); a shape that does
    not broadcast is refused by name, and a problem with algebraic states takes one
    tolerance per sample. Fixed-step runs accept every shape (it scales Newton's test)."""
    kw = IMPLICIT_DRIVERS[driver]
    x0 = torch.ones(*batch, 2, dtype=torch.float64)
    t = torch.tensor([0.0, 1.0], dtype=torch.float64)

    def decay(t, x):
        return -x

    def error(rtol):
        sol = odeint(decay, x0, t, rtol=rtol, atol=1e-14, **kw)
        return (sol.x[..., -1, :] - math.exp(-1.0)).abs()

    loose = error(1e-4)
    torch.testing.assert_close(error(torch.tensor(1e-4)), loose, rtol=0, atol=0)
    per_component = error(torch.tensor([1e-4, 1e-10]))
    if kw.get("adaptive", True) and kw["method"] == "radau_iia":  # error-controlled
        # each component is measured against its own tolerance in the error norm
        assert bool((per_component[..., 1] < 1e-8).all()) and bool((loose > 1e-7).all())
        if batch:
            per_sample = torch.full((*batch, 1), 1e-4, dtype=torch.float64)
            per_sample[0] = 1e-10
            errors = error(per_sample)
            assert bool((errors[0] < 1e-8).all())
            torch.testing.assert_close(errors[1], loose[1], rtol=0, atol=0)
    with pytest.raises(InputValidationError, match=r"rtol of shape \(5,\) does not broadcast"):
        error(torch.full((5,), 1e-6))
    dae = SemiExplicitDAE(lambda t, x, z: -x + 0 * z, lambda t, x, z: z - x)
    z0 = torch.ones(*batch, 1, dtype=torch.float64)
    with pytest.raises(InputValidationError, match="one tolerance per sample"):
        daeint(dae, x0[..., :1], z0, t, rtol=torch.tensor([1e-6, 1e-8]), **kw)
