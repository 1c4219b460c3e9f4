"""Newton methods (notes §3): convergence rates, damping, IFT gradients, minimisation.

Reference values come from closed forms (cube roots, the asymptotic rates of Theorems 3 and 6),
scipy.optimize (fsolve, least_squares) and central finite differences.
"""

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.optimize import fsolve, least_squares

from integrators import ConvergenceError, InputValidationError
from integrators.jacobians import batch_jacobian
from integrators.newton import NewtonStatus, minimize, newton

F64 = torch.float64


def cube(x, a):
    return x**3 - a


def vector_phi(x, p):
    """x1^2 + x2^2 = p1, exp(x1) + x2 = p2 (a circle cut by an exponential)."""
    x1, x2 = x[..., 0], x[..., 1]
    return torch.stack([x1**2 + x2**2 - p[..., 0], torch.exp(x1) + x2 - p[..., 1]], -1)


def vector_root(p):
    def f(z):
        return [z[0] ** 2 + z[1] ** 2 - p[0], np.exp(z[0]) + z[1] - p[1]]

    return fsolve(f, [1.0, -1.0], xtol=1e-14)


def errors(result, x_star):
    return (result.x_history - x_star).abs().amax(-1)  # (iters + 1, *batch)


def informative(e, floor=1e-13):
    e = e.numpy()
    return e[: np.argmax(e < floor)] if np.any(e < floor) else e


# ---------------------------------------------------------------- convergence rates
def test_full_newton_converges_quadratically_on_a_scalar_problem():
    """Theorem 3 (eq. 3.10): e_{k+1} / e_k^2 -> |phi''/(2 phi')| = 1 / x* for x^3 - 2."""
    a = torch.tensor([[2.0]], dtype=F64)
    res = newton(cube, torch.tensor([[3.0]], dtype=F64), a, return_history=True)
    assert bool(res.converged.all())
    x_star = 2.0 ** (1 / 3)
    e = informative(errors(res, x_star)[:, 0])
    ratios = e[1:] / e[:-1] ** 2
    assert len(ratios) >= 4
    assert np.all(ratios < 2.0)
    assert abs(ratios[-1] - 1 / x_star) < 0.05
    assert abs(float(res.observed_order[0]) - 2.0) < 0.2


def test_full_newton_converges_quadratically_on_a_vector_problem():
    p = torch.tensor([[4.0, 1.0]], dtype=F64)
    x_star = torch.as_tensor(vector_root(p[0].numpy()), dtype=F64)
    res = newton(vector_phi, torch.tensor([[1.0, -1.0]], dtype=F64), p, return_history=True)
    assert bool(res.converged.all())
    torch.testing.assert_close(res.x[0], x_star, rtol=0, atol=1e-12)
    e = informative(errors(res, x_star)[:, 0])
    assert len(e) >= 4
    ratios = e[1:] / e[:-1] ** 2
    assert np.all(ratios < 5.0)
    assert float(res.observed_order[0]) > 1.7


@pytest.mark.parametrize("method", ["full", "damped", "simplified"])
def test_the_jacobian_at_x0_reuses_the_first_evaluation(method):
    """A linear phi(x) = A x - b converges in one step from any x0: the Jacobian at x0 comes
    from the graph of phi's first evaluation, so a solve without gradient recording calls phi
    twice (x0 and x1), and the step is exactly A^{-1} (A x0 - b). A guess broadcast to phi's
    batch (no graph of that shape) takes its Jacobian by a separate evaluation."""
    g = torch.Generator().manual_seed(4)
    A = torch.randn(5, 3, 3, generator=g, dtype=F64) + 4 * torch.eye(3, dtype=F64)
    b = torch.randn(5, 3, generator=g, dtype=F64)
    calls = []

    def phi(x, A, b):
        calls.append(x.shape)
        return (A @ x.unsqueeze(-1)).squeeze(-1) - b

    with torch.no_grad():
        res = newton(phi, torch.ones(5, 3, dtype=F64), A, b, method=method, tol=1e-12)
    assert bool(res.converged.all()) and res.iterations.tolist() == [1] * 5
    assert len(calls) == res.n_phi_evals == 2 and res.n_jac_evals == 1
    torch.testing.assert_close(res.x, torch.linalg.solve(A, b), rtol=1e-13, atol=1e-13)
    calls.clear()
    with torch.no_grad():
        broadcast = newton(phi, torch.ones(3, dtype=F64), A, b, method=method, tol=1e-12)
    assert len(calls) == broadcast.n_phi_evals == 3
    torch.testing.assert_close(broadcast.x, res.x, rtol=1e-13, atol=1e-13)
    # in grad mode one evaluation more, at the solution, looks up what phi reads there
    calls.clear()
    graded = newton(phi, torch.ones(5, 3, dtype=F64), A, b, method=method, tol=1e-12)
    assert len(calls) == graded.n_phi_evals == 3
    torch.testing.assert_close(graded.x, res.x, rtol=0, atol=0)


def test_simplified_newton_converges_linearly_at_the_theorem_6_rate():
    """Frozen M = phi'(x0): the error ratio tends to kappa = |1 - phi'(x*) / M| (eq. 3.47)."""
    a = torch.tensor([[2.0]], dtype=F64)
    res = newton(
        cube,
        torch.tensor([[2.0]], dtype=F64),
        a,
        method="simplified",
        max_iter=200,
        tol=1e-14,
        return_history=True,
    )
    assert bool(res.converged.all()) and res.n_factorizations == 1 and res.n_jac_evals == 1
    x_star = 2.0 ** (1 / 3)
    kappa = 1 - 3 * x_star**2 / 12.0
    e = informative(errors(res, x_star)[:, 0], floor=1e-12)
    ratios = e[1:] / e[:-1]
    np.testing.assert_allclose(ratios[-5:], kappa, rtol=1e-3)
    assert abs(float(res.observed_order[0]) - 1.0) < 0.05
    assert abs(float(res.contraction[0]) - kappa) < 5e-3


def test_scaled_approximate_jacobian_converges_linearly_on_a_vector_problem():
    """M = 1.5 J(x): I - M^{-1} J = I / 3, so every error component shrinks by exactly 1/3."""
    p = torch.tensor([[4.0, 1.0]], dtype=F64)
    x_star = torch.as_tensor(vector_root(p[0].numpy()), dtype=F64)

    def scaled(x, p):
        return 1.5 * batch_jacobian(vector_phi, x, p)[1]

    res = newton(
        vector_phi,
        torch.tensor([[1.0, -1.0]], dtype=F64),
        p,
        jacobian=scaled,
        max_iter=100,
        tol=1e-14,
        return_history=True,
    )
    assert bool(res.converged.all())
    e = informative(errors(res, x_star)[:, 0], floor=1e-11)
    ratios = e[1:] / e[:-1]
    assert len(ratios) > 10
    np.testing.assert_allclose(ratios[-5:], 1 / 3, rtol=2e-2)


def test_simplified_newton_reuses_a_given_factorization():
    a = torch.tensor([[2.0], [3.0]], dtype=F64)
    first = newton(cube, torch.full((2, 1), 1.4, dtype=F64), a, method="simplified", max_iter=100)
    again = newton(
        cube,
        torch.full((2, 1), 1.4, dtype=F64),
        a + 1e-3,
        method="simplified",
        max_iter=100,
        factorization=first.factorization,
    )
    assert again.n_factorizations == 0 and bool(again.converged.all())
    torch.testing.assert_close(again.x, (a + 1e-3) ** (1 / 3), rtol=0, atol=1e-9)


def test_fixed_matrix_as_approximate_jacobian():
    A = torch.tensor([[3.0, 1.0], [1.0, 2.0]], dtype=F64)
    b = torch.tensor([[1.0, -1.0], [2.0, 0.5]], dtype=F64)

    def linear(x, b):
        return x @ A.T - b

    res = newton(linear, torch.zeros(2, 2, dtype=F64), b, jacobian=A)
    assert bool(res.converged.all()) and int(res.iterations.max()) == 1  # linear: one step
    assert res.n_factorizations == 1 and res.n_jac_evals == 1
    torch.testing.assert_close(res.x, torch.linalg.solve(A, b.T).T)


# ------------------------------------------------------------------------- damping
def test_full_steps_diverge_on_arctan_and_damping_rescues_them():
    """Newton on arctan(x) = 0 diverges for |x0| > 1.3917 (the case of notes Fig. 3.2 right);
    Armijo-damped steps (Theorem 4) converge from the same guess."""
    x0 = torch.tensor([[2.0], [-3.0], [0.5]], dtype=F64)
    full = newton(torch.atan, x0, max_iter=8, return_history=True)
    assert not bool(full.converged[:2].any()) and bool(full.converged[2])
    first = full.x_history[:5, 0, 0].abs()
    assert bool(torch.all(first[1:] > first[:-1]))  # |x_k| grows: oscillating divergence
    damped = newton(torch.atan, x0, method="damped", max_iter=50)
    assert bool(damped.converged.all())
    torch.testing.assert_close(damped.x, torch.zeros_like(x0), rtol=0, atol=1e-10)
    assert float(damped.step_sizes[0, 0]) < 1.0  # a reduced step was needed
    assert bool(torch.all(damped.residual_norms[1:, 0] <= damped.residual_norms[:-1, 0]))


def test_batch_with_one_failing_member():
    """x^2 + a = 0 has no real root for a = 1: that member fails, the others converge."""
    a = torch.tensor([[-4.0], [1.0], [-9.0]], dtype=F64)

    def phi(x, a):
        return x**2 + a

    res = newton(phi, torch.ones(3, 1, dtype=F64), a, method="damped", max_iter=40)
    assert res.converged.tolist() == [True, False, True]
    torch.testing.assert_close(res.x[[0, 2]], torch.tensor([[2.0], [3.0]], dtype=F64))
    assert res.status[1] != NewtonStatus.CONVERGED
    assert len(res.messages) == 1 and res.messages[0].startswith("sample 1")
    with pytest.raises(ConvergenceError, match="sample 1"):
        newton(phi, torch.ones(3, 1, dtype=F64), a, method="damped", raise_on_failure=True)


def test_converged_members_stop_changing():
    a = torch.tensor([[8.0], [1000.0]], dtype=F64)
    res = newton(cube, torch.tensor([[2.0], [1.0]], dtype=F64), a, return_history=True)
    assert res.iterations[0] < res.iterations[1]
    k = int(res.iterations[0])
    assert bool(torch.all(res.x_history[k:, 0] == res.x_history[k, 0]))


def test_singular_jacobian_is_flagged():
    res = newton(lambda x: x**2 + 1.0, torch.zeros(2, 1, dtype=F64))
    assert bool(torch.all(res.status == NewtonStatus.SINGULAR))


def test_rows_of_very_different_sizes_are_not_mistaken_for_a_singular_jacobian():
    """phi = (1e9 (x1 - a), 1e-9 (x2 - 2 a)) (two equations in very different units, rows
    swapped in a second run): the Jacobian diag(1e9, 1e-9) is well posed
    once its rows are scaled, so Newton converges to (a, 2 a) with dx/da = (1, 2); a matrix
    singular after row scaling (rows 1e-12 times each other) is still flagged."""

    def phi(x, a):
        return torch.tensor([1e9, 1e-9], dtype=F64) * (x - torch.cat([a, 2 * a], -1))

    a = torch.tensor([[0.5]], dtype=F64, requires_grad=True)
    res = newton(phi, torch.zeros(1, 2, dtype=F64), a)
    assert res.status.tolist() == [NewtonStatus.CONVERGED]
    torch.testing.assert_close(res.x.detach(), torch.tensor([[0.5, 1.0]], dtype=F64))
    res.x.sum().backward()
    assert float(a.grad) == pytest.approx(3.0, rel=1e-12)
    swapped = newton(lambda x, a: phi(x, a).flip(-1), torch.zeros(1, 2, dtype=F64), a.detach())
    assert swapped.status.tolist() == [NewtonStatus.CONVERGED]
    dependent = newton(
        lambda x: (
            torch.stack([x[..., 0] + 2 * x[..., 1], 1e-12 * (x[..., 0] + 2 * x[..., 1])], -1) + 1.0
        ),
        torch.zeros(1, 2, dtype=F64),
    )
    assert dependent.status.tolist() == [NewtonStatus.SINGULAR]


def test_a_non_finite_jacobian_or_residual_is_reported_non_finite_not_singular():
    """A member whose Jacobian is NaN where phi is finite (x^2 - 4 + 0 sqrt(x - 1.5) at
    x = 1, the sqrt branch masked off) or whose residual is NaN at every trial step of the
    damped line search gets NON_FINITE (it was SINGULAR / LINE_SEARCH_FAILED); a finite
    singular Jacobian stays SINGULAR and the healthy member converges to sqrt(2)."""

    def phi(x, c, s):  # x^2 - c, plus 0 sqrt(x - s) whose derivative is NaN for x <= s
        return x**2 - c + 0 * torch.where(x > s, torch.sqrt(x - s), torch.zeros_like(x))

    c = torch.tensor([[4.0], [-1.0], [2.0]], dtype=F64)
    s = torch.tensor([[1.5], [-10.0], [-10.0]], dtype=F64)
    res = newton(phi, torch.tensor([[1.0], [0.0], [1.0]], dtype=F64), c, s)
    assert res.status.tolist() == [
        NewtonStatus.NON_FINITE,
        NewtonStatus.SINGULAR,
        NewtonStatus.CONVERGED,
    ]
    assert res.messages[0].startswith("sample 0: non_finite")
    assert float(res.x[2, 0]) == pytest.approx(2**0.5, rel=1e-10)

    def nan_after_x0(x):  # x - 2 at x0 = 1, NaN everywhere else
        return torch.where(x == 1.0, x - 2.0, torch.full_like(x, float("nan")))

    x0 = torch.ones(1, 1, dtype=F64)
    for method in ("full", "damped"):
        res = newton(nan_after_x0, x0, method=method)
        assert res.status.tolist() == [NewtonStatus.NON_FINITE], method


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        (dict(tol=0.0), "tol = 0 with xtol = 0"),
        (dict(tol=-1.0), "tol must be a finite number >= 0"),
        (dict(tol=float("nan")), "tol must be a finite number >= 0"),
        (dict(divergence_ratio=0.0), "divergence_ratio must be a finite number > 0"),
        (dict(divergence_ratio=-1.0), "divergence_ratio must be a finite number > 0"),
        (dict(max_iter=-1), "max_iter must be an integer >= 0"),
        (dict(max_iter=2.5), "max_iter must be an integer >= 0"),
        (dict(xtol=-1.0), "xtol must be a finite number >= 0"),
        (dict(xtol=float("nan")), "xtol must be a finite number >= 0"),
    ],
)
def test_newton_tolerances_and_limits_are_checked(kwargs, match):
    """Tolerances and limits that would flag every member (tol <= 0 or NaN: MAX_ITER at a
    residual of 4e-16; divergence_ratio <= 0: DIVERGED) or crash later are refused."""
    with pytest.raises(InputValidationError, match=f"newton: {match}"):
        newton(lambda x: x**2 - 2.0, torch.ones(1, 1, dtype=F64), **kwargs)
    res = newton(lambda x: x**2 - 2.0, torch.ones(1, 1, dtype=F64), max_iter=0, xtol=0.0)
    assert res.status.tolist() == [NewtonStatus.MAX_ITER]
    res = newton(lambda x: x**2 - 2.0, torch.ones(1, 1, dtype=F64), tol=0.0, xtol=1e-12)
    assert res.status.tolist() == [NewtonStatus.CONVERGED]
    assert float(res.x[0, 0]) == pytest.approx(2**0.5, rel=1e-15)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        (dict(regularization=float("nan")), "regularization must be a finite number >= 0"),
        (dict(regularization=-1.0), "regularization must be a finite number >= 0"),
        (dict(tol=-1.0), "tol must be a finite number >= 0"),
        (dict(ftol=-1.0), "ftol must be a finite number >= 0"),
        (dict(xtol=float("nan")), "xtol must be a finite number >= 0"),
        (dict(max_iter=-1), "max_iter must be an integer >= 0"),
        (dict(max_backtracks=-1), "max_backtracks must be an integer >= 0"),
        (dict(max_backtracks=1.5), "max_backtracks must be an integer >= 0"),
    ],
)
def test_minimize_tolerances_and_limits_are_checked(kwargs, match):
    with pytest.raises(InputValidationError, match=f"minimize: {match}"):
        minimize(lambda th: ((th - 1.0) ** 2).sum(-1), torch.zeros(1, 2, dtype=F64), **kwargs)


# ------------------------------------------------------------------------ gradients
def test_ift_gradient_matches_finite_differences():
    p = torch.tensor([[4.0, 1.0], [2.0, 0.5], [9.0, 2.0]], dtype=F64, requires_grad=True)
    w = torch.tensor([[0.3, -1.2]], dtype=F64)
    x0 = torch.tensor([[1.0, -1.0]], dtype=F64).expand(3, 2)
    res = newton(vector_phi, x0, p, tol=1e-13)
    assert bool(res.converged.all())
    (g,) = torch.autograd.grad((res.x * w).sum(), p)
    fd = torch.zeros_like(p)
    h = 1e-6
    for j in range(2):
        e = torch.zeros(1, 2, dtype=F64)
        e[0, j] = h
        plus = newton(vector_phi, x0, p.detach() + e, tol=1e-14).x
        minus = newton(vector_phi, x0, p.detach() - e, tol=1e-14).x
        fd[:, j] = ((plus - minus) * w).sum(-1) / (2 * h)
    torch.testing.assert_close(g, fd, rtol=1e-6, atol=1e-9)
    # eq. 3.40 in closed form: dx/dp = -J^{-1} dphi/dp with dphi/dp = -I
    _, J = batch_jacobian(vector_phi, res.x.detach(), p.detach())
    torch.testing.assert_close(g, (torch.linalg.inv(J).transpose(-1, -2) @ w[..., None])[..., 0])


def test_ift_gradient_reaches_closure_parameters_and_not_x0():
    k = torch.nn.Parameter(torch.tensor(2.0, dtype=F64))
    x0 = torch.ones(4, 1, dtype=F64, requires_grad=True)
    a = torch.linspace(1, 4, 4, dtype=F64)[:, None]

    def phi(x, a):
        return k * x**3 - a  # root (a / k)^(1/3)

    res = newton(phi, x0, a, params=[k])
    (gk,) = torch.autograd.grad(res.x.sum(), k)
    exact = (-(1 / 3) * a ** (1 / 3) * k.detach() ** (-4 / 3)).sum()
    torch.testing.assert_close(gk, exact)
    assert torch.autograd.grad(res.x.sum(), x0, allow_unused=True)[0] is None


@pytest.mark.parametrize("jacobian", ["autograd", "given"])
def test_ift_gradient_reaches_every_tensor_phi_reads_without_params(jacobian):
    """Without ``params`` the solve finds what phi reads in its closure: a module parameter
    through a bound method, a plain tensor, and a view of a leaf computed outside phi
    (x^3 = c (s k)^-1 w_0 / w_1 with k, s, w read from the closure), so its root gets every
    gradient plain autograd would give; closed form (w0 / (c s k w1))^(1/3) differentiated by
    autograd (the graph of w, reached by the solve's backward, stays usable). ``params=()``
    keeps only the arguments' gradients; no_grad none."""

    class Gain(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.k = torch.nn.Parameter(torch.tensor(2.0, dtype=F64))

        def residual(self, x, c):
            return c * scale * self.k * x**3 - w[0] / w[1]

    gain = Gain()
    scale = torch.tensor(1.5, dtype=F64, requires_grad=True)
    weights = torch.tensor([3.0, 0.5], dtype=F64, requires_grad=True)
    w = weights * 1.0  # a non-leaf tensor in the closure: gradients reach its leaf
    c = torch.tensor([[1.0], [2.0]], dtype=F64, requires_grad=True)
    options = {}
    if jacobian == "given":  # no autograd Jacobian: the closure is read from an extra call
        options["jacobian"] = lambda x, c: (3 * c * scale * gain.k * x**2).detach()[..., None]
    res = newton(gain.residual, torch.ones(2, 1, dtype=F64), c, tol=1e-14, **options)
    leaves = (c, gain.k, scale, weights)
    got = torch.autograd.grad(res.x.sum(), leaves)
    exact = ((w[0] / w[1]) / (c * scale * gain.k)) ** (1 / 3)
    torch.testing.assert_close(res.x.detach(), exact.detach(), rtol=1e-13, atol=0)
    want = torch.autograd.grad(exact.sum(), leaves)
    for g, e in zip(got, want, strict=True):
        torch.testing.assert_close(g, e, rtol=1e-10, atol=0)

    only_args = newton(gain.residual, torch.ones(2, 1, dtype=F64), c, tol=1e-14, params=())
    g_c, g_k = torch.autograd.grad(only_args.x.sum(), (c, gain.k), allow_unused=True)
    torch.testing.assert_close(g_c, want[0], rtol=1e-10, atol=0)
    assert g_k is None
    with torch.no_grad():
        assert not newton(gain.residual, torch.ones(2, 1, dtype=F64), c).x.requires_grad


@pytest.mark.parametrize("jacobian", ["autograd", "given"])
def test_ift_gradient_reaches_a_tensor_phi_reads_only_near_the_root(jacobian):
    """phi(x) = x - 1 left of 0.5 and x - k right of it (a Python branch): from x0 = 0 the
    first step lands right of 0.5 and the root is x* = k, dx*/dk = 1. The tensors found at x0
    alone missed k (no gradient at all); they are also looked up at the solution."""
    k = torch.tensor(2.0, dtype=F64, requires_grad=True)

    def phi(x):
        return x - 1.0 if float(x.max()) < 0.5 else x - k

    options = {"jacobian": lambda x: torch.ones(1, 1, 1, dtype=F64)} if jacobian == "given" else {}
    res = newton(phi, torch.zeros(1, 1, dtype=F64), **options)
    assert res.status.tolist() == [NewtonStatus.CONVERGED] and float(res.x) == 2.0
    (grad,) = torch.autograd.grad(res.x.sum(), k)
    assert float(grad) == 1.0


@pytest.mark.parametrize("argument", ["derived", "same tensor"])
def test_second_order_ift_with_arguments_computed_from_closure_parameters(argument):
    """x^3 + a x - p^2 - 1 = 0 with a = 2p (or a = p) passed as an argument and p also read
    from the closure (params=[p]): dx/dp under create_graph=True counted the path through a
    twice (-0.429 for 0.0269). First and second derivatives against implicit
    differentiation of the root from numpy.roots: dx/dp = -F_p / F_x and its total
    derivative along the root."""
    c = 2.0 if argument == "derived" else 1.0
    pv = 0.8
    p = torch.tensor(pv, dtype=F64, requires_grad=True)

    def phi(x, a):
        return x**3 + a * x - p * p - 1.0

    def root():
        a = (c * p).reshape(1, 1) if argument == "derived" else p.reshape(1, 1)
        return newton(phi, torch.ones(1, 1, dtype=F64), a, params=[p], tol=1e-14).x.sum()

    (g,) = torch.autograd.grad(root(), p, create_graph=True)
    (h,) = torch.autograd.grad(g, p)
    (gp,) = torch.autograd.grad(root(), p)  # first order alone

    roots = np.roots([1.0, 0.0, c * pv, -(pv * pv + 1.0)])
    xs = float(roots[np.abs(roots.imag) < 1e-12].real[0])
    pt = torch.tensor(pv, dtype=F64, requires_grad=True)
    xt = torch.tensor(xs, dtype=F64, requires_grad=True)
    slope = -(c * xt - 2 * pt) / (3 * xt**2 + c * pt)  # -F_p / F_x
    dp, dx = torch.autograd.grad(slope, (pt, xt))
    torch.testing.assert_close(g.detach(), slope.detach(), rtol=1e-10, atol=0)
    torch.testing.assert_close(gp, slope.detach(), rtol=1e-10, atol=0)
    torch.testing.assert_close(h, dp + dx * slope.detach(), rtol=1e-10, atol=0)


def count_graph_nodes(t):
    seen, stack = set(), [t.grad_fn]
    while stack:
        node = stack.pop()
        if node is None or node in seen:
            continue
        seen.add(node)
        stack.extend(nxt for nxt, _ in node.next_functions)
    return len(seen)


def test_ift_graph_does_not_grow_with_iterations():
    a = torch.tensor([[0.5]], dtype=F64, requires_grad=True)

    def phi(x, a):
        return torch.atan(x) - a

    few = newton(phi, torch.tensor([[0.6]], dtype=F64), a, method="damped")
    many = newton(
        phi, torch.tensor([[1.0]], dtype=F64), a, method="simplified", tol=1e-14, max_iter=500
    )
    assert int(many.iterations[0]) > 3 * int(few.iterations[0])
    assert count_graph_nodes(few.x) == count_graph_nodes(many.x) <= 3
    g_few = torch.autograd.grad(few.x.sum(), a)[0]
    g_many = torch.autograd.grad(many.x.sum(), a)[0]
    torch.testing.assert_close(g_few, g_many)
    torch.testing.assert_close(g_few, 1 + torch.tan(a.detach()) ** 2)  # d tan(a) / da


@settings(max_examples=15, deadline=None)
@given(st.lists(st.floats(0.05, 500.0), min_size=1, max_size=6))
def test_cube_roots_and_their_gradients_for_varied_data(values):
    a = torch.tensor(values, dtype=F64)[:, None].requires_grad_(True)
    res = newton(cube, torch.ones_like(a).detach(), a, method="damped", max_iter=100)
    assert bool(res.converged.all())
    torch.testing.assert_close(res.x, a.detach() ** (1 / 3), rtol=1e-10, atol=0)
    (g,) = torch.autograd.grad(res.x.sum(), a)
    torch.testing.assert_close(g, a.detach() ** (-2 / 3) / 3, rtol=1e-8, atol=0)


def test_float32_works():
    a = torch.tensor([[2.0], [5.0]], dtype=torch.float32)
    res = newton(cube, torch.ones(2, 1), a)
    assert res.x.dtype == torch.float32 and bool(res.converged.all())
    torch.testing.assert_close(res.x, a ** (1 / 3), rtol=1e-5, atol=0)


def test_bad_inputs():
    with pytest.raises(InputValidationError, match="method"):
        newton(cube, torch.ones(1, 1), torch.ones(1, 1), method="secant")
    with pytest.raises(InputValidationError, match="shape"):
        newton(lambda x: x.sum(-1), torch.ones(2, 3))
    with pytest.raises(InputValidationError, match="non-finite"):
        newton(cube, torch.tensor([[float("nan")]]), torch.ones(1, 1))


# ----------------------------------------------------------------------- minimise
def exp_model(theta, t):
    return theta[..., 0:1] * torch.exp(-theta[..., 1:2] * t) + theta[..., 2:3]


@pytest.mark.parametrize("method", ["gauss_newton", "levenberg_marquardt"])
def test_an_unbatched_problem_matches_its_batch_of_one_and_scipy(method):
    """theta (p,) without batch dimensions (0-d statuses and flags) gives the numbers of the
    same problem as a batch of one, and scipy's least-squares optimum."""
    t = torch.linspace(0, 3, 40, dtype=F64)
    noise = torch.randn(40, generator=torch.Generator().manual_seed(3), dtype=F64)
    y = exp_model(torch.tensor([2.0, 1.3, 0.5], dtype=F64), t) + 0.05 * noise

    def residual(theta, t, y):
        return exp_model(theta, t) - y

    start = torch.tensor([1.0, 1.0, 0.0], dtype=F64)
    alone = minimize(residual, start, t, y, method=method)
    batch = minimize(residual, start[None], t, y[None], method=method)
    assert alone.theta.shape == (3,) and alone.converged.shape == ()
    assert bool(alone.converged)
    torch.testing.assert_close(alone.theta, batch.theta[0], rtol=1e-13, atol=1e-14)
    assert int(alone.iterations) == int(batch.iterations[0])
    ref = least_squares(
        lambda q: q[0] * np.exp(-q[1] * t.numpy()) + q[2] - y.numpy(),
        [1.0, 1.0, 0.0],
        xtol=1e-15,
        ftol=1e-15,
        gtol=1e-15,
    )
    np.testing.assert_allclose(alone.theta.numpy(), ref.x, rtol=1e-7, atol=1e-9)


def test_gauss_newton_matches_scipy_least_squares_for_a_batch_of_problems():
    g = torch.Generator().manual_seed(1)
    t = torch.linspace(0, 3, 40, dtype=F64)
    truth = torch.tensor([[2.0, 1.3, 0.5], [1.0, 0.4, -0.2], [3.0, 2.5, 1.0]], dtype=F64)
    y = exp_model(truth, t) + 0.05 * torch.randn(3, 40, generator=g, dtype=F64)

    def residual(theta, t, y):
        return exp_model(theta, t) - y

    res = minimize(
        residual,
        torch.tensor([[1.0, 1.0, 0.0]], dtype=F64).expand(3, 3),
        t,
        y,
        method="gauss_newton",
    )
    assert bool(res.converged.all())
    for i in range(3):
        ref = least_squares(
            lambda q, i=i: q[0] * np.exp(-q[1] * t.numpy()) + q[2] - y[i].numpy(),
            [1.0, 1.0, 0.0],
            xtol=1e-15,
            ftol=1e-15,
            gtol=1e-15,
        )
        np.testing.assert_allclose(res.theta[i].numpy(), ref.x, rtol=1e-7, atol=1e-9)
        np.testing.assert_allclose(float(res.loss[i]), ref.cost, rtol=1e-10)
    th = res.theta
    decay = torch.exp(-th[:, 1:2] * t)
    exact_jac = torch.stack([decay, -th[:, 0:1] * t * decay, torch.ones_like(decay)], -1)
    torch.testing.assert_close(res.J, exact_jac)  # scipy's res.jac is only a finite difference
    assert bool(torch.all(res.loss_history[1:] <= res.loss_history[:-1] + 1e-15))


def test_newton_minimises_rosenbrock_with_line_search():
    def rosenbrock(th):
        return 100 * (th[..., 1] - th[..., 0] ** 2) ** 2 + (1 - th[..., 0]) ** 2

    th0 = torch.tensor([[-1.2, 1.0], [2.0, -1.0], [-0.5, 3.0]], dtype=F64)
    res = minimize(rosenbrock, th0)
    assert bool(res.converged.all())
    torch.testing.assert_close(res.theta, torch.ones(3, 2, dtype=F64), rtol=0, atol=1e-8)
    assert bool(torch.all(res.loss_history[1:] <= res.loss_history[:-1]))  # Theorem 7
    exact_h = torch.tensor([[802.0, -400.0], [-400.0, 200.0]], dtype=F64)
    torch.testing.assert_close(res.hessian, exact_h.expand(3, 2, 2), rtol=1e-6, atol=1e-6)


def test_regularised_gauss_newton_still_converges_on_a_rank_deficient_problem():
    """r = [theta1 + theta2 - 2]: J^T J is singular; alpha I (eq. 3.61) makes steps exist."""

    def residual(theta):
        return (theta[..., 0] + theta[..., 1] - 2.0)[..., None]

    res = minimize(
        residual, torch.zeros(1, 2, dtype=F64), method="gauss_newton", regularization=1e-6
    )
    assert bool(res.converged.all())
    assert abs(float(res.theta.sum()) - 2.0) < 1e-8


class _NumpySquare(torch.autograd.Function):
    """x^2 with a backward that leaves torch: it has no vmap batching rule."""

    @staticmethod
    def forward(ctx, x):
        ctx.save_for_backward(x)
        return x**2

    @staticmethod
    def backward(ctx, grad):
        (x,) = ctx.saved_tensors
        return 2 * x * torch.from_numpy(grad.detach().numpy().copy())


def test_batch_jacobian_falls_back_to_a_component_loop():
    x = torch.tensor([[0.5, -1.5, 2.0], [1.0, 2.0, 3.0]], dtype=F64)
    weights = torch.tensor([1.0, 2.0, 3.0], dtype=F64)
    _, J = batch_jacobian(lambda z: _NumpySquare.apply(z) * weights, x)
    torch.testing.assert_close(J, torch.diag_embed(2 * x * weights))


# ------------------------------------------------------------- Levenberg-Marquardt
class _Huber:
    """Huber's loss with threshold c, as a duck-typed loss of ``minimize`` (the protocol)."""

    def __init__(self, c):
        self.c = c

    def rho(self, r):
        a = r.abs()
        return torch.where(a <= self.c, 0.5 * r * r, self.c * a - 0.5 * self.c**2)

    def psi(self, r):
        return r.clamp(-self.c, self.c)

    def curvature(self, r):
        return torch.clamp(self.c / r.abs(), max=1.0)


def _exp_data(seed, outliers=False):
    g = torch.Generator().manual_seed(seed)
    t = torch.linspace(0, 3, 40, dtype=F64)
    truth = torch.tensor([[2.0, 1.3, 0.5], [1.0, 0.4, -0.2], [3.0, 2.5, 1.0]], dtype=F64)
    y = exp_model(truth, t) + 0.05 * torch.randn(3, 40, generator=g, dtype=F64)
    if outliers:
        y[:, ::7] += 2.0  # gross errors in every 7th sample
    return t, y


def _exp_residual(theta, t, y):
    return exp_model(theta, t) - y


def test_levenberg_marquardt_matches_gauss_newton_and_scipy():
    t, y = _exp_data(1)
    th0 = torch.tensor([[1.0, 1.0, 0.0]], dtype=F64).expand(3, 3)
    lm = minimize(_exp_residual, th0, t, y, method="levenberg_marquardt", xtol=0, ftol=0)
    gn = minimize(_exp_residual, th0, t, y, method="gauss_newton")
    assert bool(lm.converged.all())
    assert lm.damping.shape == (3,) and bool((lm.damping > 0).all())
    torch.testing.assert_close(lm.theta, gn.theta, rtol=1e-7, atol=1e-9)
    for i in range(3):
        ref = least_squares(
            lambda q, i=i: q[0] * np.exp(-q[1] * t.numpy()) + q[2] - y[i].numpy(),
            [1.0, 1.0, 0.0],
            xtol=1e-15,
            ftol=1e-15,
            gtol=1e-15,
        )
        np.testing.assert_allclose(lm.theta[i].numpy(), ref.x, rtol=1e-7, atol=1e-9)
    assert bool(torch.all(lm.loss_history[1:] <= lm.loss_history[:-1]))  # Armijo descent


def test_levenberg_marquardt_with_a_robust_loss_matches_scipy_huber():
    """The loss protocol: a duck-typed Huber loss gives scipy's loss='huber' minimiser."""
    t, y = _exp_data(2, outliers=True)
    c = 0.1
    th0 = torch.tensor([[1.0, 1.0, 0.0]], dtype=F64).expand(3, 3)
    res = minimize(
        _exp_residual, th0, t, y, method="levenberg_marquardt", loss=_Huber(c), xtol=0, ftol=0
    )
    assert bool(res.converged.all())
    for i in range(3):
        ref = least_squares(
            lambda q, i=i: q[0] * np.exp(-q[1] * t.numpy()) + q[2] - y[i].numpy(),
            [1.0, 1.0, 0.0],
            loss="huber",
            f_scale=c,
            xtol=1e-15,
            ftol=1e-15,
            gtol=1e-15,
        )
        np.testing.assert_allclose(res.theta[i].numpy(), ref.x, rtol=1e-6, atol=1e-8)
        np.testing.assert_allclose(float(res.loss[i]), ref.cost, rtol=1e-9)


def test_levenberg_marquardt_never_accepts_an_inadmissible_step():
    """min (theta - 2)^2 restricted to theta < 1: every iterate stays admissible and the
    estimate approaches the boundary from inside."""

    def residual(theta):
        return theta - 2.0

    def admissible(theta):
        return theta[..., 0] < 1.0

    res = minimize(
        residual,
        torch.zeros(4, 1, dtype=F64),
        method="levenberg_marquardt",
        admissible=admissible,
        max_iter=60,
    )
    assert bool(admissible(res.theta).all())
    assert bool((res.theta[..., 0] > 0.99).all())
    assert bool(torch.all(res.loss_history[1:] <= res.loss_history[:-1]))
    free = minimize(residual, torch.zeros(4, 1, dtype=F64), method="levenberg_marquardt")
    torch.testing.assert_close(free.theta, torch.full((4, 1), 2.0, dtype=F64))


def test_levenberg_marquardt_options_are_checked():
    th0 = torch.zeros(1, 3, dtype=F64)
    t, y = _exp_data(3)
    with pytest.raises(InputValidationError, match="levenberg_marquardt"):
        minimize(_exp_residual, th0, t, y, method="gauss_newton", loss=_Huber(1.0))
    with pytest.raises(InputValidationError, match="line_search"):
        minimize(_exp_residual, th0, t, y, method="levenberg_marquardt", line_search=False)
    with pytest.raises(InputValidationError, match="damping"):
        minimize(_exp_residual, th0, t, y, method="levenberg_marquardt", damping=0.0)
    with pytest.raises(InputValidationError, match="levenberg_marquardt"):
        minimize(_exp_residual, th0, t, y, method="lm")


def test_levenberg_marquardt_stops_where_only_rounding_noise_is_left():
    """A residual whose evaluation carries 1e-9 of non-smooth noise (like a long simulation's
    rounding): at the least-squares solution no step decreases the loss while the predicted
    decrease is below the loss' rounding level, which is convergence, found in two
    iterations and a few evaluations instead of growing the damping step by step."""
    g = torch.Generator().manual_seed(0)
    B, m, n = 8, 100, 3
    A = torch.randn(m, n, generator=g, dtype=torch.float64)
    b = torch.randn(B, m, generator=g, dtype=torch.float64)
    w = torch.randn(n, generator=g, dtype=torch.float64)

    def residual(th):
        return th @ A.T - b + 1e-9 * torch.sin(1e9 * (th @ w))[..., None]

    res = minimize(
        residual,
        torch.zeros(B, n, dtype=torch.float64),
        method="levenberg_marquardt",
        jacobian=lambda th: (residual(th), A.expand(*th.shape[:-1], m, n)),
    )
    exact = torch.linalg.lstsq(A, b.T).solution.T
    assert bool(res.converged.all())
    assert torch.allclose(res.theta, exact, atol=1e-6)
    assert int(res.iterations.max()) <= 3
    assert res.n_fun_evals <= 40


def test_levenberg_marquardt_reports_no_minimum_where_damping_stalls_at_a_boundary():
    """An exponential fit whose admissible region (decay rate < 1) excludes the unconstrained
    minimum: trials past the boundary grow the damping until the accepted steps are tiny.
    Such a member stopped as CONVERGED at a point with gradient (-1.24, 0, -0.48) (loss 0.302,
    the best admissible 0.080); a tiny damped step is no sign of a minimum, so a member is
    reported converged only where the gradient vanishes."""
    t = torch.linspace(0, 4, 40, dtype=torch.float64)
    gen = torch.Generator().manual_seed(0)

    def model(th):
        return th[..., 0:1] * torch.exp(-th[..., 1:2] * t) + th[..., 2:3]

    truth = torch.tensor([[2.0, 1.3, 0.5], [1.0, 0.4, -0.2], [3.0, 2.0, 0.1]], dtype=torch.float64)
    y = model(truth) + 0.05 * torch.randn(3, 40, generator=gen, dtype=torch.float64)
    start = torch.tensor([[0.5, 0.5, 0.0]] * 3, dtype=torch.float64)
    res = minimize(
        lambda th: model(th) - y,
        start,
        method="levenberg_marquardt",
        admissible=lambda th: th[..., 1] < 1.0,
    )
    assert not bool(res.converged[0]) and not bool(res.converged[2])
    assert bool(res.converged[1])  # its minimum (rate 0.4) is admissible
    assert float(res.grad[1].abs().max()) < 1e-6


def test_forward_mode_derivatives_are_refused_not_dropped():
    """newton's derivatives are implicit-function-theorem gradients for reverse mode: a dual
    tensor (forward mode, batch_jacobian(strategy='forward')) is refused by name instead of
    leaving the root without a tangent (a derivative of 0 where d sqrt(a)/da = 1/(2 sqrt a));
    reverse-mode strategies give the closed form."""
    from torch.autograd import forward_ad

    def root(a):
        return newton(lambda x, aa: x**2 - aa, torch.ones_like(a), a).x

    a = torch.tensor([[4.0], [9.0]], dtype=torch.float64)
    with forward_ad.dual_level(), pytest.raises(InputValidationError, match="forward-mode"):
        root(forward_ad.make_dual(a, torch.ones_like(a)))
    with pytest.raises(InputValidationError, match="forward-mode"):
        batch_jacobian(root, a, strategy="forward")
    for strategy in ("vmap", "rows"):
        _, J = batch_jacobian(root, a, strategy=strategy)
        torch.testing.assert_close(J.flatten(), 0.5 / a.sqrt().flatten(), rtol=1e-12, atol=0)


# ------------------------------------------------------------------- compaction
class _MemberHuber(_Huber):
    """Huber's loss with one threshold per problem, ``c`` (*batch, 1), for ``compact=True``:
    the methods take ``members`` and use those problems' thresholds."""

    def rho(self, r, members=None):
        return _Huber(self._rows(members)).rho(r)

    def psi(self, r, members=None):
        return _Huber(self._rows(members)).psi(r)

    def curvature(self, r, members=None):
        return _Huber(self._rows(members)).curvature(r)

    def _rows(self, members):
        return self.c if members is None else self.c.reshape(-1, 1)[members]


def _compaction_problem():
    """Exponential fits over a (2, 3) batch whose members need very different iteration
    counts (0 to the budget): one starts near its solution, one far away, one has non-finite
    data (NON_FINITE at the start), and the admissible decay rates (< 1.5) exclude one
    member's minimum (rate 2.5), which creeps along the boundary until the iteration budget
    runs out. Returns ``(residual, jacobian, admissible, theta0, y, calls)``; ``calls``
    collects the number of members each call evaluated."""
    t = torch.linspace(0, 3, 40, dtype=F64)
    truth = torch.tensor(
        [[[2.0, 1.3, 0.5], [1.0, 0.4, -0.2], [3.0, 2.5, 1.0]],
         [[0.5, 0.2, 0.1], [1.5, 1.0, 0.0], [2.0, 0.7, 0.3]]],
        dtype=F64,
    )  # fmt: skip
    g = torch.Generator().manual_seed(4)
    y = exp_model(truth, t) + 0.05 * torch.randn(2, 3, 40, generator=g, dtype=F64)
    y[1, 1, 5] = math.inf
    theta0 = torch.tensor([1.0, 1.0, 0.0], dtype=F64).expand(2, 3, 3).clone()
    theta0[0, 1] = truth[0, 1] + 0.01
    theta0[1, 2] = torch.tensor([8.0, 0.05, -3.0], dtype=F64)
    calls = []

    def rows(x, members):
        return x if members is None else x.reshape(-1, x.shape[-1])[members]

    def residual(theta, y, members=None):
        calls.append(theta.shape[:-1].numel())
        return exp_model(theta, t) - rows(y, members)

    def jacobian(theta, y, members=None):
        r = residual(theta, y, members=members)
        e = torch.exp(-theta[..., 1:2] * t)
        J = torch.stack([e, -theta[..., 0:1] * t * e, torch.ones_like(e)], -1)
        return r, J

    def admissible(theta, members=None):
        return theta[..., 1] < 1.5

    return residual, jacobian, admissible, theta0, y, calls


def _assert_same_fit(a, b):
    for name in ("theta", "loss", "grad", "hessian", "J", "residual", "damping", "loss_history"):
        torch.testing.assert_close(
            getattr(a, name), getattr(b, name), rtol=1e-12, atol=1e-14, equal_nan=True
        )
    assert torch.equal(a.iterations, b.iterations)
    assert torch.equal(a.status, b.status)


def test_compact_levenberg_marquardt_equals_the_full_batch_and_single_fits():
    """compact=True evaluates only the members still iterating (fewer rows in all than the
    full batch) and gives the uncompacted result member by member, and that of each problem
    fitted alone, over a (2, 3) batch with converging, non-finite and stalling members."""
    residual, jacobian, admissible, theta0, y, calls = _compaction_problem()
    loss = _MemberHuber(torch.linspace(0.05, 0.3, 6, dtype=F64).reshape(2, 3, 1))
    kw = dict(method="levenberg_marquardt", loss=loss, admissible=admissible, max_iter=60)
    for jac in (None, jacobian):
        full = minimize(residual, theta0, y, jacobian=jac, **kw)
        evaluated_full = sum(calls)
        calls.clear()
        compact = minimize(residual, theta0, y, jacobian=jac, compact=True, **kw)
        evaluated_compact = sum(calls)
        calls.clear()
        _assert_same_fit(compact, full)
        assert evaluated_compact < 0.7 * evaluated_full
        status = compact.status
        assert status[1, 1] == NewtonStatus.NON_FINITE and status[0, 2] == NewtonStatus.MAX_ITER
        assert int(compact.iterations[0, 1]) < 10 and int(compact.iterations[0, 2]) == 60
        for i in range(2):
            for j in range(3):
                one = minimize(
                    residual,
                    theta0[i, j][None],
                    y[i, j][None],
                    jacobian=jac,
                    compact=True,
                    **{**kw, "loss": _MemberHuber(loss.c[i, j][None])},
                )
                torch.testing.assert_close(
                    one.theta[0], compact.theta[i, j], rtol=1e-12, atol=1e-14, equal_nan=True
                )
                torch.testing.assert_close(
                    one.loss[0], compact.loss[i, j], rtol=1e-12, atol=0, equal_nan=True
                )
                assert int(one.iterations[0]) == int(compact.iterations[i, j])
                assert int(one.status[0]) == int(compact.status[i, j])


@pytest.mark.parametrize("method", ["newton", "gauss_newton"])
def test_compact_newton_and_gauss_newton_equal_the_full_batch(method):
    residual, _, _, theta0, y, calls = _compaction_problem()
    if method == "newton":

        def fun(theta, y, members=None):
            return 0.5 * residual(theta, y, members=members).square().sum(-1)
    else:
        fun = residual
    full = minimize(fun, theta0, y, method=method)
    evaluated_full = sum(calls)
    calls.clear()
    compact = minimize(fun, theta0, y, method=method, compact=True)
    assert sum(calls) < evaluated_full
    for name in ("theta", "loss", "grad", "hessian", "loss_history"):
        torch.testing.assert_close(
            getattr(compact, name), getattr(full, name), rtol=1e-12, atol=1e-14, equal_nan=True
        )
    assert torch.equal(compact.iterations, full.iterations)
    assert torch.equal(compact.status, full.status)


def test_compact_refuses_a_block_jacobian():
    from integrators.block_jacobian import BlockJacobian

    def blocks(theta):
        values = torch.ones(*theta.shape[:-1], 1, 1, 1, dtype=F64)
        columns = torch.zeros(1, 1, dtype=torch.int64)
        return theta - 1.0, BlockJacobian([(values, columns)], 1)

    with pytest.raises(InputValidationError, match="BlockJacobian"):
        minimize(
            lambda th, members=None: th - 1.0,
            torch.zeros(2, 1, dtype=F64),
            method="levenberg_marquardt",
            jacobian=lambda th, members=None: blocks(th),
            compact=True,
        )
