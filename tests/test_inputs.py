"""Inputs bound to a model (integrators.inputs): zero-order hold (notes eq. 8.34), linear
interpolation and callables, checked against exact discretisations and scipy.signal."""

import numpy as np
import pytest
import scipy.linalg
import scipy.signal
import torch

from integrators import (
    CollocationInput,
    InputValidationError,
    bind_rhs,
    gauss_legendre,
    odeint,
    radau_iia,
)

A = np.array([[0.0, 1.0], [-4.0, -0.4]])
B = np.array([[0.0, 0.5], [1.0, 0.0]])


def linear_plant(t, x, u):
    return x @ torch.as_tensor(A).T + u @ torch.as_tensor(B).T


def zoh_exact(x0, u, t):
    """Exact discretisation x_{k+1} = Ad x_k + Bd u_k per interval (augmented expm)."""
    n, nu = B.shape
    xs = [x0]
    for k in range(len(t) - 1):
        M = np.zeros((n + nu, n + nu))
        M[:n, :n], M[:n, n:] = A, B
        E = scipy.linalg.expm(M * (t[k + 1] - t[k]))
        xs.append(E[:n, :n] @ xs[-1] + E[:n, n:] @ u[k])
    return np.stack(xs)


def linear_exact(x0, u, t):
    """Exact discretisation of a linearly interpolated input, u = u_k + (t - t_k) s_k on
    interval k: x_{k+1} = E11 x_k + E12 u_k + E13 s_k from the exponential of the augmented
    matrix [[A, B, 0], [0, 0, I], [0, 0, 0]] (the input and its slope as extra states)."""
    n, nu = B.shape
    xs = [x0]
    for k in range(len(t) - 1):
        dt = t[k + 1] - t[k]
        M = np.zeros((n + 2 * nu, n + 2 * nu))
        M[:n, :n], M[:n, n : n + nu], M[n : n + nu, n + nu :] = A, B, np.eye(nu)
        E = scipy.linalg.expm(M * dt)
        slope = (u[k + 1] - u[k]) / dt
        xs.append(E[:n, :n] @ xs[-1] + E[:n, n : n + nu] @ u[k] + E[:n, n + nu :] @ slope)
    return np.stack(xs)


def test_zoh_matches_exact_discretisation_on_nonuniform_grid():
    rng = np.random.default_rng(0)
    t = np.cumsum(np.concatenate([[0.0], rng.uniform(0.05, 0.3, 15)]))
    u = rng.standard_normal((len(t), 2))
    x0 = np.array([1.0, -0.5])
    exact = zoh_exact(x0, u, t)
    errors = []
    for m in (10, 40):
        sol = odeint(linear_plant, torch.tensor(x0), torch.tensor(t), u=torch.tensor(u), substeps=m)
        errors.append(np.abs(sol.x.numpy() - exact).max())
    # RK4 converges with order 4 to the exact discretisation only if every stage of interval k
    # (also c_i = 1) uses u_k; a lookup of u_{k+1} at t_{k+1} would leave an O(h) error.
    assert errors[1] < 1e-8
    assert abs(np.log(errors[0] / errors[1]) / np.log(4) - 4) <= 0.15


def test_zoh_matches_scipy_cont2discrete_and_dlsim():
    dt = 0.1
    t = np.arange(0, 3.0 + dt / 2, dt)
    u = np.sin(np.arange(len(t)))[:, None] * np.array([[1.0, -2.0]])
    x0 = np.array([0.3, 0.0])
    Ad, Bd, _, _, _ = scipy.signal.cont2discrete((A, B, np.eye(2), np.zeros((2, 2))), dt)
    _, _, xd = scipy.signal.dlsim((Ad, Bd, np.eye(2), np.zeros((2, 2)), dt), u, x0=x0)
    for method, atol in (("rk4", 1e-7), ("dopri5", 1e-9)):
        sol = odeint(
            linear_plant,
            torch.tensor(x0),
            torch.tensor(t),
            u=torch.tensor(u),
            substeps=10,
            method=method,
            adaptive=False,
        )
        np.testing.assert_allclose(sol.x.numpy(), xd, rtol=0, atol=atol)


def test_linear_interpolation_matches_scipy_lsim():
    dt = 0.05
    t = np.arange(0, 4.0 + dt / 2, dt)
    u = np.stack([np.sign(np.sin(2 * t)), np.cos(5 * t)], axis=-1)
    x0 = np.array([0.0, 1.0])
    _, _, xref = scipy.signal.lsim((A, B, np.eye(2), np.zeros((2, 2))), u, t, X0=x0, interp=True)
    errors = []
    for m in (4, 16):
        sol = odeint(
            linear_plant,
            torch.tensor(x0),
            torch.tensor(t),
            u=torch.tensor(u),
            interpolation="linear",
            substeps=m,
        )
        errors.append(np.abs(sol.x.numpy() - xref).max())
    assert errors[1] < 1e-10
    assert abs(np.log(errors[0] / errors[1]) / np.log(4) - 4) <= 0.15


ADAPTIVE_DRIVERS = {
    "dopri5": dict(method="dopri5"),
    "radau, host": dict(method="radau_iia"),
    "radau, torch": dict(method="radau_iia", host_loop=False),
}


@pytest.mark.parametrize("driver", ADAPTIVE_DRIVERS)
@pytest.mark.parametrize("interpolation", ["zoh", "linear"])
@pytest.mark.parametrize("batch", [(), (3,)])
def test_adaptive_steps_end_at_the_samples_of_an_input(driver, interpolation, batch):
    """A sampled input jumps (zero-order hold) or kinks (linear interpolation) at its sample
    times: adaptive steps end there, and the stages of a step hold the step's sample up to
    its right end, so the run meets its tolerance against the exact discretisations on a
    non-uniform grid (matrix exponentials augmented by the held input, or by the input and
    its slope): within 5 tol (stepping across the samples missed tolerance 1e-6 by 10-100
    times). The steps land on the sample times: at least one per interval."""
    rng = np.random.default_rng(4)
    t = np.cumsum(np.concatenate([[0.0], rng.uniform(0.2, 0.6, 8)]))
    u = rng.standard_normal((*batch, len(t), 2)) * 2
    x0 = np.array([1.0, -0.5])
    exact_run = zoh_exact if interpolation == "zoh" else linear_exact
    exact = np.stack([exact_run(x0, ui, t) for ui in u.reshape(-1, len(t), 2)])
    for tol in (1e-6, 1e-9):
        sol = odeint(
            linear_plant,
            torch.tensor(x0).expand(*batch, 2),
            torch.tensor(t),
            u=torch.tensor(u),
            interpolation=interpolation,
            rtol=tol,
            atol=tol,
            **ADAPTIVE_DRIVERS[driver],
        )
        error = np.abs(sol.x.numpy().reshape(exact.shape) - exact).max()
        assert error <= 5 * tol, (tol, error)
        assert int(sol.stats.n_steps.min()) >= len(t) - 1
        if driver == "dopri5" and interpolation == "zoh":
            # f(t0), the initial-step probe, 6 per attempt (FSAL), and K_1 again only at
            # each of the len(t) - 2 inner samples, where the held input jumps
            attempts = sol.stats.n_steps + sol.stats.n_rejected
            assert torch.equal(sol.stats.n_f_evals, 2 + 6 * attempts + len(t) - 2)


def test_callable_input_matches_closed_form():
    """x' = -x + u(t), u(t) = sin(3t): x = (x0 + 0.3) e^{-t} + (sin 3t - 3 cos 3t) / 10."""
    t = torch.linspace(0, 3, 31, dtype=torch.float64)
    x0 = torch.tensor([[1.0], [2.0]], dtype=torch.float64)
    sol = odeint(lambda t, x, u: -x + u, x0, t, u=lambda t: torch.sin(3 * t).reshape(1), substeps=8)
    tn = t.numpy()
    exact = (x0.numpy()[:, None] + 0.3) * np.exp(-tn)[:, None] + (
        (np.sin(3 * tn) - 3 * np.cos(3 * tn)) / 10
    )[:, None]
    np.testing.assert_allclose(sol.x.numpy(), exact, rtol=0, atol=1e-8)


def test_per_sample_inputs_equal_separate_runs():
    rng = np.random.default_rng(1)
    t = torch.linspace(0, 2, 21, dtype=torch.float64)
    u = torch.tensor(rng.standard_normal((3, 21, 2)))
    x0 = torch.tensor(rng.standard_normal((3, 2)))
    for interpolation in ("zoh", "linear"):
        batched = odeint(linear_plant, x0, t, u=u, interpolation=interpolation, substeps=2)
        for i in range(3):
            single = odeint(linear_plant, x0[i], t, u=u[i], interpolation=interpolation, substeps=2)
            torch.testing.assert_close(batched.x[i], single.x, rtol=0, atol=1e-14)


@pytest.mark.parametrize("interpolation", ["zoh", "linear"])
def test_time_lookup_matches_numpy(interpolation):
    """rhs(t, x) looks inputs up by time: shared 0-dim times and per-sample (*batch, 1)."""
    t_grid = torch.tensor([0.0, 0.5, 1.5, 2.0], dtype=torch.float64)
    samples = torch.tensor([[1.0], [3.0], [-1.0], [2.0]], dtype=torch.float64)
    rhs = bind_rhs(lambda t, x, u: u.expand_as(x), samples, t_grid, interpolation=interpolation)
    queries = np.array([-0.3, 0.0, 0.2, 0.5, 1.0, 1.5, 1.99, 2.0, 2.5])
    if interpolation == "linear":
        expected = np.interp(queries, t_grid.numpy(), samples[:, 0].numpy())
    else:  # right-continuous hold; first/last sample held outside the grid
        idx = np.clip(np.searchsorted(t_grid.numpy(), queries, side="right") - 1, 0, 3)
        expected = samples[idx, 0].numpy()
    x = torch.zeros(len(queries), 1, dtype=torch.float64)
    per_sample = rhs(torch.tensor(queries)[:, None], x)
    np.testing.assert_allclose(per_sample[:, 0].numpy(), expected, rtol=0, atol=1e-15)
    for q, e in zip(queries, expected, strict=True):
        shared = rhs(torch.tensor(q, dtype=torch.float64), torch.zeros(2, 1, dtype=torch.float64))
        np.testing.assert_allclose(shared[:, 0].numpy(), [e, e], rtol=0, atol=1e-15)
    # per-sample samples (*batch, T, nu) with per-sample times
    batch_samples = torch.stack([samples, 2 * samples])
    rhs_b = bind_rhs(lambda t, x, u: u, batch_samples, t_grid, interpolation=interpolation)
    out = rhs_b(torch.tensor([[0.2], [1.0]], dtype=torch.float64), torch.zeros(2, 1))
    np.testing.assert_allclose(out[:, 0].numpy(), [expected[2], 2 * expected[4]], atol=1e-15)


def test_input_validation_errors():
    t = torch.linspace(0, 1, 5, dtype=torch.float64)
    f = lambda t, x, u: -x + u  # noqa: E731
    with pytest.raises(InputValidationError, match="T = len"):
        bind_rhs(f, torch.zeros(4, 1), t)
    with pytest.raises(InputValidationError, match="T = len"):
        bind_rhs(f, torch.zeros(5), t)
    with pytest.raises(InputValidationError, match="interpolation"):
        bind_rhs(f, torch.zeros(5, 1), t, interpolation="cubic")
    bad = torch.zeros(2, 5, 1, dtype=torch.float64)
    bad[1, 3, 0] = float("nan")
    with pytest.raises(InputValidationError, match=r"time index 3, sample index \(1,\)"):
        bind_rhs(f, bad, t)
    with pytest.raises(InputValidationError, match="time index 2"):
        odeint(f, torch.zeros(1), t, u=torch.tensor([[0.0], [1.0], [float("inf")], [0.0], [0.0]]))
    with pytest.raises(InputValidationError, match="broadcast"):
        odeint(f, torch.zeros(3, 1), t, u=torch.zeros(2, 5, 1))


# ------------------------------------------- inputs by collocation polynomials (eq. 8.32)
@pytest.mark.parametrize("nodes", ["radau", "legendre", (0.0, 0.3, 0.6, 1.0)])
def test_collocation_input_interpolates_a_piecewise_cubic(nodes):
    """With q = 4 nodes the polynomial of eq. 8.32 through the values of a cubic at the node
    times is that cubic (a different one per interval, numpy.polyval as truth); the values at
    the node times are the coefficients; lookups are right-continuous at grid points (the
    next interval at tau = 0) and hold the end values outside the grid; per-sample times and
    batched coefficients agree with the shared-time lookup."""
    t = torch.tensor([0.0, 0.5, 1.5, 2.0], dtype=torch.float64)
    rng = np.random.default_rng(2)
    cubics = rng.standard_normal((3, 4))  # numpy.polyval coefficients per interval
    u_nodes = np.array(nodes) if not isinstance(nodes, str) else None
    if isinstance(nodes, str):  # the schemes of CasADi's collocation_points(4, scheme)
        u_nodes = (radau_iia(4) if nodes == "radau" else gauss_legendre(4)).c
    grid = t.numpy()
    node_times = grid[:-1, None] + np.diff(grid)[:, None] * u_nodes  # (3, 4)
    coef = np.stack([np.polyval(cubics[k], node_times[k]) for k in range(3)])[..., None]
    u = CollocationInput(torch.tensor(coef), t, nodes)
    for k in range(3):
        for time in np.linspace(grid[k], grid[k + 1], 7)[:-1]:
            got = u(torch.tensor(time, dtype=torch.float64))
            np.testing.assert_allclose(got.numpy(), [np.polyval(cubics[k], time)], atol=1e-13)
        inner = u_nodes < 1.0  # a node at tau = 1 is looked up in the next interval
        got = u(torch.tensor(node_times[k, inner])[:, None])
        np.testing.assert_allclose(got[:, 0].numpy(), coef[k, inner, 0], rtol=0, atol=1e-13)
    at_grid = u(torch.tensor(0.5, dtype=torch.float64)).numpy()
    np.testing.assert_allclose(at_grid, [np.polyval(cubics[1], 0.5)], rtol=0, atol=1e-13)
    ends = u(torch.tensor([[-1.0], [2.0], [3.0]], dtype=torch.float64))[:, 0].numpy()
    np.testing.assert_allclose(
        ends, [np.polyval(cubics[0], 0.0)] + 2 * [np.polyval(cubics[2], 2.0)]
    )
    batched = CollocationInput(torch.tensor(np.stack([coef, -coef])), t, nodes)
    got = batched(torch.tensor([[0.7], [1.7]], dtype=torch.float64))[:, 0].numpy()
    np.testing.assert_allclose(got, [np.polyval(cubics[1], 0.7), -np.polyval(cubics[2], 1.7)])


def test_collocation_input_validation_errors():
    t = torch.linspace(0, 1, 5, dtype=torch.float64)
    with pytest.raises(InputValidationError, match="T-1 = 4 intervals"):
        CollocationInput(torch.zeros(5, 2, 1), t)
    with pytest.raises(InputValidationError, match="unknown nodes"):
        CollocationInput(torch.zeros(4, 2, 1), t, "chebyshev")
    with pytest.raises(InputValidationError, match="q = 2"):
        CollocationInput(torch.zeros(4, 2, 1), t, (0.0, 0.5, 1.0))
    with pytest.raises(InputValidationError, match=r"in \[0, 1\]"):
        CollocationInput(torch.zeros(4, 2, 1), t, (0.0, 1.5))
    with pytest.raises(InputValidationError, match="distinct"):
        CollocationInput(torch.zeros(4, 2, 1), t, (0.5, 0.5))
    with pytest.raises(InputValidationError, match="strictly increasing"):
        CollocationInput(torch.zeros(4, 2, 1), t.flip(0))
    bad = torch.zeros(4, 2, 1)
    bad[2, 1, 0] = float("nan")
    with pytest.raises(InputValidationError, match="time index 2"):
        CollocationInput(bad, t)
