"""Second derivatives through the implicit solvers (``create_graph=True``): Hessians of the
discrete solution with respect to the initial state and a parameter, for every driver of
``odeint``'s implicit methods, for ``daeint`` and for ``newton``.

Truths: the closed form of ``x' = -p x^3``, ``x(T) = x0 / sqrt(1 + 2 p x0^2 T)`` (differentiated
by autograd on the formula itself) for the adaptive runs at tight tolerances, and central
finite differences of the solver's own first derivative (first-order IFT gradients, checked
elsewhere) for the fixed-step runs, whose discrete solution differs from the closed form.
"""

from __future__ import annotations

import math

import pytest
import torch

from integrators import ImplicitODE, SemiExplicitDAE, daeint
from integrators.implicit import solve_implicit_ode
from integrators.newton import newton

T = 1.0
P = 0.8
X0 = [0.7, 1.1, 0.4]
ADAPTIVE = dict(rtol=1e-10, atol=1e-12)


def _x0(batch):
    x0 = torch.tensor(X0, dtype=torch.float64)
    return x0[:1] if batch is None else x0[:batch, None]


def _hessian(final, x0, p):
    """Hessian (k + 1, k + 1) of ``final(x0, p).sum()`` over ``(x0.flatten(), p)``."""
    x0 = x0.detach().clone().requires_grad_(True)
    p = torch.tensor(p, dtype=torch.float64, requires_grad=True)
    g = torch.autograd.grad(final(x0, p).sum(), (x0, p), create_graph=True)
    g = torch.cat([g[0].reshape(-1), g[1].reshape(1)])
    rows = [torch.autograd.grad(gi, (x0, p), retain_graph=True) for gi in g]
    return torch.stack([torch.cat([r[0].reshape(-1), r[1].reshape(1)]) for r in rows])


def _fd_hessian(final, x0, p, eps=1e-5):
    """Central differences of the first-order gradient of ``final(x0, p).sum()``."""

    def grad(theta):
        x0v = theta[:-1].reshape(x0.shape).clone().requires_grad_(True)
        pv = theta[-1].clone().requires_grad_(True)
        g = torch.autograd.grad(final(x0v, pv).sum(), (x0v, pv))
        return torch.cat([g[0].reshape(-1), g[1].reshape(1)])

    theta = torch.cat([x0.reshape(-1), torch.tensor([p], dtype=torch.float64)])
    cols = []
    for j in range(theta.numel()):
        e = torch.zeros_like(theta)
        e[j] = eps
        cols.append((grad(theta + e) - grad(theta - e)) / (2 * eps))
    return torch.stack(cols, dim=1)


def _exact(x0, p):
    return x0 / torch.sqrt(1 + 2 * p * x0**2 * T)


def _ode_final(options, driver=None):
    t = torch.linspace(0.0, T, 3, dtype=torch.float64)

    def final(x0, p):
        sol = solve_implicit_ode(lambda tt, x: -p * x**3, x0, t, **options)
        assert sol.success
        if driver is not None:
            assert sol.stats.extra["driver"] == driver
        return sol.x[..., -1, :]

    return final


@pytest.mark.parametrize("batch", [None, 3])
@pytest.mark.parametrize("host_loop", [False, True])
def test_adaptive_radau_hessian_matches_closed_form(batch, host_loop):
    """Adaptive Radau IIA on every driver (torch; host batched; host one trajectory): the
    Hessian over (x0, p) equals the closed form's to 1e-6 (the IFT with only first-order
    corrections was off by about 1 % here, e.g. d2x/dx0^2 -0.768 for -0.761)."""
    driver = "torch" if not host_loop else "host" if batch else "host, one trajectory"
    final = _ode_final(dict(method="radau_iia", host_loop=host_loop, **ADAPTIVE), driver)
    x0 = _x0(batch)
    H = _hessian(final, x0, P)
    H_exact = _hessian(_exact, x0, P)
    torch.testing.assert_close(H, H_exact, rtol=1e-6, atol=1e-8)


@pytest.mark.parametrize("batch", [None, 3])
@pytest.mark.parametrize(
    "options",
    [
        dict(method="gauss_legendre", substeps=2),
        dict(method="radau_iia", adaptive=False, substeps=2),
        dict(method="implicit_euler", substeps=2),
    ],
    ids=["gauss", "radau-fixed", "implicit-euler"],
)
def test_fixed_step_hessian_matches_differences_of_the_gradient(options, batch):
    """Fixed steps h = 0.25 (large, so the second-order terms of the stage solve matter):
    the Hessian over (x0, p) of the discrete solution equals central differences of its
    gradient to 1e-6 (the difference error is about 1e-9)."""
    final = _ode_final(options, "torch")
    x0 = _x0(batch)
    H = _hessian(final, x0, P)
    torch.testing.assert_close(H, _fd_hessian(final, x0, P), rtol=1e-6, atol=1e-8)


@pytest.mark.parametrize("kind", ["semi", "implicit"])
@pytest.mark.parametrize("adaptive", [True, False])
def test_daeint_hessian(kind, adaptive):
    """``x' = -z, 0 = z - p x^3`` (semi-explicit) and ``x' + p x^3 = 0`` (implicit ODE): the
    Hessian of x(T) over (x0, p) (batch of 3); adaptive against the closed form, Gauss-Legendre
    fixed steps against differences of the gradient. For the DAE also z(T) = p x(T)^3."""
    t = torch.linspace(0.0, T, 3, dtype=torch.float64)
    options = ADAPTIVE if adaptive else dict(method="gauss_legendre", substeps=2)

    def solve(x0, p):
        if kind == "semi":
            problem = SemiExplicitDAE(lambda tt, x, z: -z, lambda tt, x, z: z - p * x**3)
            return daeint(problem, x0, torch.zeros_like(x0), t, adaptive=adaptive, **options)
        problem = ImplicitODE(lambda tt, xd, x: xd + p * x**3)
        return daeint(problem, x0, None, t, adaptive=adaptive, **options)

    def final_x(x0, p):
        sol = solve(x0, p)
        assert sol.success
        return sol.x[..., -1, :]

    finals = [(final_x, _exact)]
    if kind == "semi":
        finals.append(
            (lambda x0, p: solve(x0, p).z[..., -1, :], lambda x0, p: p * _exact(x0, p) ** 3)
        )
    x0 = _x0(3)
    for final, exact in finals:
        H = _hessian(final, x0, P)
        truth = _hessian(exact, x0, P) if adaptive else _fd_hessian(final, x0, P)
        torch.testing.assert_close(H, truth, rtol=1e-6, atol=1e-8)


def test_daeint_initial_algebraic_state_hessian():
    """z(t0) comes from the consistent-initialisation Newton solve (``newton`` with x0 as an
    argument): for ``0 = z - p x^3`` it is ``p x0^3``, so d2 z(t0) / dx0^2 = 6 p x0."""
    problem = SemiExplicitDAE(lambda tt, x, z: -z, lambda tt, x, z: z - P * x**3)
    t = torch.linspace(0.0, T, 3, dtype=torch.float64)
    x0 = _x0(3).requires_grad_(True)
    sol = daeint(problem, x0, torch.zeros_like(x0), t, **ADAPTIVE)
    (g,) = torch.autograd.grad(sol.z[..., 0, :].sum(), x0, create_graph=True)
    torch.testing.assert_close(g, 3 * P * x0.detach() ** 2)
    (h,) = torch.autograd.grad(g.sum(), x0)
    torch.testing.assert_close(h, 6 * P * x0.detach())


def test_newton_hessian_matches_differences_of_the_gradient():
    """Root of ``x^3 + p x^2 + a x - b = 0`` (a, b arguments, p a closure parameter): the
    Hessian over (a, b, p) of the sum of the roots equals central differences of the
    first-order IFT gradient (previously a raw autograd error about once_differentiable)."""
    p0 = 0.5

    def roots(a, b, p):
        res = newton(
            lambda x, a, b: x**3 + p * x**2 + a[..., None] * x - b[..., None],
            torch.zeros(2, 1, dtype=torch.float64),
            a,
            b,
            params=[p],
        )
        assert bool(res.converged.all())
        return res.x.sum()

    def grad(theta, create_graph=False):
        loss = roots(theta[:2], theta[2:4], theta[4])
        return torch.autograd.grad(loss, theta, create_graph=create_graph)[0]

    theta = torch.tensor([1.5, 2.0, 0.7, 1.3, p0], dtype=torch.float64, requires_grad=True)
    g = grad(theta, create_graph=True)
    H = torch.stack([torch.autograd.grad(gi, theta, retain_graph=True)[0] for gi in g])
    eps = 1e-5
    cols = []
    for j in range(5):
        e = torch.zeros(5, dtype=torch.float64)
        e[j] = eps
        plus = grad((theta.detach() + e).requires_grad_(True))
        minus = grad((theta.detach() - e).requires_grad_(True))
        cols.append((plus - minus) / (2 * eps))
    torch.testing.assert_close(H, torch.stack(cols, dim=1), rtol=1e-6, atol=1e-8)
    assert not math.isclose(float(H.abs().max()), 0.0)
