"""Collocation tableaus (notes §7.4, eq. 7.41-7.44) against closed forms and theory.

Typos found in the notes while writing these tests:
- eq. 7.42 defines P_s on [-1, 1]; the collocation grid of eq. 7.43 must use the shifted
  polynomial P_s(2 tau - 1) on [0, 1] (checked in ``test_gauss_nodes_are_shifted_roots``).
- eq. 7.41 writes ``a_ji = L_i(tau_j)``: consistent with the RK convention ``a_ij = L_j(c_i)``
  (row = stage), which ``test_rows_are_stage_quadratures`` checks.
- eq. 7.28 calls the Lagrange polynomials "orthogonal"; that holds for Gauss and Radau nodes
  (the quadrature is exact for the degree 2s-2 product) but not for a general grid.
- §7.4 states the order 2s of Gauss-Legendre without the simplifying assumptions B, C, D that
  prove it; test_tableau.py checks Butcher's theorem on the classical implicit families.
"""

from math import factorial, sqrt

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.polynomial import legendre as npleg
from scipy.special import roots_jacobi, roots_legendre

from integrators import (
    ButcherTableau,
    TableauError,
    collocation_output_weights,
    gauss_legendre,
    radau_iia,
    tableau,
)
from integrators.errors import InputValidationError

STAGES = [1, 2, 3, 4, 5]
MANY_STAGES = list(range(1, 21))


def pade(k, j, z):
    """The (k, j) Padé approximant of exp(z) from its closed form (numerator degree k)."""
    num = sum(
        factorial(k + j - i)
        * factorial(k)
        / (factorial(k + j) * factorial(i) * factorial(k - i))
        * z**i
        for i in range(k + 1)
    )
    den = sum(
        factorial(k + j - i)
        * factorial(j)
        / (factorial(k + j) * factorial(i) * factorial(j - i))
        * (-z) ** i
        for i in range(j + 1)
    )
    return num / den


@pytest.mark.parametrize("s", STAGES)
def test_order_conditions_hold_exactly_to_the_claimed_order(s):
    g, r = gauss_legendre(s), radau_iia(s)
    assert g.order == 2 * s and g.satisfies_order(2 * s)
    assert not g.satisfies_order(2 * s + 1)
    assert r.order == 2 * s - 1 and r.satisfies_order(2 * s - 1)
    assert not r.satisfies_order(2 * s)


@pytest.mark.parametrize("s", MANY_STAGES)
def test_orders_of_many_stages_are_proved_by_simplifying_assumptions(s):
    """Gauss: B(2s), C(s), D(s); Radau IIA: B(2s-1), C(s), D(s-1) (Butcher 1964), for s up to
    20, where the rooted trees of order 2s number in the millions. Independent truth for the
    coefficients: scipy's Gauss-Legendre and Gauss-Jacobi nodes (Radau IIA interior nodes are
    the roots of the Jacobi polynomial P^(1,0)_(s-1)) and the Pade form of R(z)."""
    g, r = gauss_legendre(s), radau_iia(s)
    assert g.order == 2 * s and g.simplifying_assumptions() == (2 * s, s, s)
    assert r.order == 2 * s - 1 and r.simplifying_assumptions() == (2 * s - 1, s, s - 1)
    np.testing.assert_allclose(g.c, (roots_legendre(s)[0] + 1) / 2, rtol=0, atol=1e-14)
    if s > 1:
        interior = (roots_jacobi(s - 1, 1.0, 0.0)[0] + 1) / 2
        np.testing.assert_allclose(r.c[:-1], interior, rtol=0, atol=1e-14)
    z = np.array([-3.0, -0.5 + 2j, 1.5j, 0.7])
    np.testing.assert_allclose(g.stability_function(z), pade(s, s, z), rtol=1e-11)
    np.testing.assert_allclose(r.stability_function(z), pade(s - 1, s, z), rtol=1e-11)


@pytest.mark.parametrize("s", MANY_STAGES)
def test_one_order_too_many_is_rejected_for_many_stages(s):
    """Radau IIA is not order 2s, Gauss not 2s + 1. For Radau IIA, the monomial form of the
    failing equation, sum_i b_i c_i^(2s-1) = 1/(2s), misses by only 6e-12 at s = 10 and 5e-24
    at s = 20 (60-digit arithmetic), under the 1e-10 tolerance and under rounding, so it would
    wrongly pass; the Legendre form used by the tableau misses by 0.21 and 0.14."""
    r = radau_iia(s)
    with pytest.raises(
        TableauError, match=rf"claims order {2 * s} .* only up to order {2 * s - 1}"
    ):
        ButcherTableau(r.A, r.b, c=r.c, order=2 * s)
    g = gauss_legendre(s)
    with pytest.raises(TableauError, match=rf"only up to order {2 * s}\b"):
        ButcherTableau(g.A, g.b, c=g.c, order=2 * s + 1)


@settings(max_examples=40, deadline=None)
@given(
    s=st.integers(min_value=1, max_value=20),
    radau=st.booleans(),
    where=st.tuples(st.floats(0, 1, exclude_max=True), st.floats(0, 1, exclude_max=True)),
    sign=st.sampled_from([-1.0, 1.0]),
)
def test_collocation_tableau_with_one_coefficient_off_by_1e_6_is_rejected(s, radau, where, sign):
    tab = radau_iia(s) if radau else gauss_legendre(s)
    i, j = int(where[0] * s), int(where[1] * s)
    A = np.array(tab.A)
    A[i, j] += sign * 1e-6
    if not (radau and s == 1):  # any a_11 keeps order 1 (implicit Euler's claim) valid
        with pytest.raises(TableauError, match=rf"claims order {tab.order}\b"):
            ButcherTableau(A, tab.b, order=tab.order)  # c = row sums of the perturbed A
    with pytest.raises(TableauError, match=rf"c\[{i}\]"):
        ButcherTableau(A, tab.b, c=tab.c, order=tab.order)


def vandermonde_collocation(nodes):
    """Collocation tableau of ``nodes`` from C(s) and B(s) solved as Vandermonde systems."""
    s = len(nodes)
    k = np.arange(s)
    V = nodes[:, None] ** k  # V[j, k] = c_j^k
    A = np.linalg.solve(V.T, (nodes[:, None] ** (k + 1) / (k + 1)).T).T
    b = np.linalg.solve(V.T, 1.0 / (k + 1))
    return A, b


@settings(max_examples=40, deadline=None)
@given(
    gaps=st.lists(st.floats(min_value=0.08, max_value=1.0), min_size=2, max_size=5),
)
def test_random_collocation_order_equals_rooted_tree_order(gaps):
    """Any collocation method with B(p) has order p (C(s) and D(p - s) hold). The order the
    tableau reports equals the rooted-tree order and the bound min(p, q + r + 1, 2q + 2)."""
    nodes = np.cumsum(gaps)[:-1] / np.sum(gaps)  # distinct nodes in (0, 1)
    A, b = vandermonde_collocation(nodes)
    tab = ButcherTableau(A, b)
    p, q, r = tab.simplifying_assumptions()
    s = nodes.size
    assert s <= p <= 2 * s and q == s
    assert tab.order == p == min(p, q + r + 1, 2 * q + 2)
    assert tab.rooted_tree_order(min(p + 1, 9)) == p


@pytest.mark.parametrize("s", [6, 7])
def test_high_stage_counts_still_verify(s):
    assert gauss_legendre(s).order == 2 * s
    assert radau_iia(s).order == 2 * s - 1


@pytest.mark.parametrize("s", STAGES)
def test_nodes_are_row_sums_and_lie_in_the_unit_interval(s):
    for tab in (gauss_legendre(s), radau_iia(s)):
        np.testing.assert_allclose(tab.A.sum(axis=1), tab.c, rtol=0, atol=1e-14)
        assert np.all(tab.c > 0) and np.all(tab.c <= 1) and np.all(np.diff(tab.c) > 0)
    r = radau_iia(s)
    assert r.c[-1] == 1.0
    np.testing.assert_allclose(r.A[-1], r.b, rtol=0, atol=1e-15)  # stiffly accurate


@pytest.mark.parametrize("s", STAGES)
def test_gauss_nodes_are_shifted_roots(s):
    c = gauss_legendre(s).c
    coef = np.zeros(s + 1)
    coef[s] = 1.0
    np.testing.assert_allclose(npleg.legval(2 * c - 1, coef), 0.0, atol=1e-13)
    # the unshifted polynomial of eq. 7.42 (a typo for the [0, 1] grid) does not vanish there
    if s >= 2:
        assert np.max(np.abs(npleg.legval(c, coef))) > 1e-3
    radau_coef = np.zeros(s + 1)
    radau_coef[s], radau_coef[s - 1] = 1.0, -1.0
    np.testing.assert_allclose(npleg.legval(2 * radau_iia(s).c - 1, radau_coef), 0, atol=1e-13)


@pytest.mark.parametrize("s", STAGES)
def test_rows_are_stage_quadratures(s):
    """a_ij = int_0^{c_i} l_j: row i integrates polynomials of degree < s over [0, c_i]."""
    for tab in (gauss_legendre(s), radau_iia(s)):
        for q in range(s):
            np.testing.assert_allclose(tab.A @ tab.c**q, tab.c ** (q + 1) / (q + 1), atol=1e-14)
            np.testing.assert_allclose(tab.b @ tab.c**q, 1.0 / (q + 1), atol=1e-14)


def test_closed_form_tableaus_for_one_and_two_stages():
    g1, r1 = gauss_legendre(1), radau_iia(1)
    np.testing.assert_allclose(g1.A, tableau("implicit_midpoint").A)
    np.testing.assert_allclose(g1.b, [1.0])
    np.testing.assert_allclose(r1.A, tableau("implicit_euler").A)
    r3 = sqrt(3) / 6
    g2 = gauss_legendre(2)
    np.testing.assert_allclose(g2.c, [0.5 - r3, 0.5 + r3], atol=1e-15)
    np.testing.assert_allclose(g2.A, [[0.25, 0.25 - r3], [0.25 + r3, 0.25]], atol=1e-15)
    np.testing.assert_allclose(g2.b, [0.5, 0.5], atol=1e-15)
    r2 = radau_iia(2)
    np.testing.assert_allclose(r2.c, [1 / 3, 1.0], atol=1e-15)
    np.testing.assert_allclose(r2.A, [[5 / 12, -1 / 12], [3 / 4, 1 / 4]], atol=1e-15)
    np.testing.assert_allclose(r2.b, [3 / 4, 1 / 4], atol=1e-15)


def test_three_stage_radau_matches_its_closed_form():
    s6 = sqrt(6)
    r = radau_iia(3)
    np.testing.assert_allclose(r.c, [(4 - s6) / 10, (4 + s6) / 10, 1.0], atol=1e-15)
    expected = [
        [(88 - 7 * s6) / 360, (296 - 169 * s6) / 1800, (-2 + 3 * s6) / 225],
        [(296 + 169 * s6) / 1800, (88 + 7 * s6) / 360, (-2 - 3 * s6) / 225],
        [(16 - s6) / 36, (16 + s6) / 36, 1 / 9],
    ]
    np.testing.assert_allclose(r.A, expected, atol=1e-15)


@pytest.mark.parametrize("s", STAGES)
def test_stability_on_the_imaginary_axis_and_at_infinity(s):
    y = np.linspace(-50, 50, 401)
    g, r = gauss_legendre(s), radau_iia(s)
    np.testing.assert_allclose(np.abs(g.stability_function(1j * y)), 1.0, atol=1e-11)
    assert np.all(np.abs(r.stability_function(1j * y)) <= 1.0 + 1e-12)
    assert abs(r.stability_at_infinity()) < 1e-11
    assert abs(abs(g.stability_at_infinity()) - 1.0) < 1e-10
    left = -np.logspace(-2, 3, 50)[:, None] + 1j * np.linspace(-30, 30, 21)[None, :]
    assert np.all(np.abs(g.stability_function(left)) <= 1.0 + 1e-12)  # A-stable
    assert np.all(np.abs(r.stability_function(left)) <= 1.0 + 1e-12)


@pytest.mark.parametrize("s", STAGES)
def test_stability_functions_are_pade_approximants(s):
    rng = np.random.default_rng(s)
    z = rng.normal(size=20) * 3 + 1j * rng.normal(size=20) * 3
    np.testing.assert_allclose(gauss_legendre(s).stability_function(z), pade(s, s, z), rtol=1e-11)
    np.testing.assert_allclose(radau_iia(s).stability_function(z), pade(s - 1, s, z), rtol=1e-11)


@pytest.mark.parametrize("s", STAGES)
def test_dense_output_reproduces_b_and_a(s):
    for tab in (gauss_legendre(s), radau_iia(s)):
        np.testing.assert_allclose(collocation_output_weights(tab, [1.0])[0], tab.b, atol=1e-15)
        np.testing.assert_allclose(collocation_output_weights(tab, tab.c), tab.A, atol=1e-15)
        np.testing.assert_allclose(collocation_output_weights(tab, [0.0]), 0.0, atol=0)


@settings(max_examples=25, deadline=None)
@given(
    s=st.integers(min_value=1, max_value=5),
    theta=st.floats(min_value=0.0, max_value=1.0),
    coefs=st.lists(st.floats(-5, 5), min_size=5, max_size=5),
)
def test_dense_output_integrates_polynomials_exactly(s, theta, coefs):
    """sum_j w_j(theta) q(c_j) = int_0^theta q for deg q <= s - 1 (eq. 7.44)."""
    q = np.polynomial.Polynomial(coefs[:s])
    for tab in (gauss_legendre(s), radau_iia(s)):
        w = collocation_output_weights(tab, [theta])[0]
        exact = q.integ()(theta) - q.integ()(0.0)
        assert abs(w @ q(tab.c) - exact) <= 1e-13 * (1 + np.abs(coefs).sum())


def test_dense_output_in_torch_matches_numpy_and_differentiates_to_the_interpolant():
    tab = radau_iia(4)
    theta = torch.linspace(0, 1, 7, dtype=torch.float64, requires_grad=True)
    w = collocation_output_weights(tab, theta)
    np.testing.assert_allclose(
        w.detach().numpy(), collocation_output_weights(tab, theta.detach().numpy()), atol=1e-15
    )
    # d/dtheta of sum_j w_j(theta) K_j is the interpolating polynomial sum_j K_j l_j(theta):
    # for K_j = q(c_j) with deg q < s it equals q(theta).
    K = torch.tensor(tab.c, dtype=torch.float64) ** 3 - 2.0
    (grad,) = torch.autograd.grad((w @ K).sum(), theta)
    np.testing.assert_allclose(grad.numpy(), theta.detach().numpy() ** 3 - 2.0, atol=1e-13)
    w32 = collocation_output_weights(tab, torch.tensor([[0.5]], dtype=torch.float32))
    assert w32.dtype == torch.float32 and w32.shape == (1, 1, 4)


def test_lagrange_polynomials_orthogonal_only_for_gauss_type_nodes():
    """Eq. 7.28 holds for Gauss/Radau grids (quadrature exact to degree 2s-2), not in general."""
    from integrators.collocation import lagrange_basis

    xi, w = np.polynomial.legendre.leggauss(12)
    xi, w = (xi + 1) / 2, w / 2
    for nodes, orthogonal in [
        (gauss_legendre(4).c, True),
        (radau_iia(4).c, True),
        (np.array([0.0, 1 / 3, 2 / 3, 1.0]), False),
    ]:
        basis = lagrange_basis(torch.tensor(nodes), torch.tensor(xi)).numpy()
        gram = basis.T @ (w[:, None] * basis)
        off = gram - np.diag(np.diag(gram))
        assert (np.abs(off).max() < 1e-14) == orthogonal


def test_errors():
    with pytest.raises(InputValidationError, match="stages"):
        gauss_legendre(0)
    with pytest.raises(InputValidationError):
        radau_iia(2.5)
    with pytest.raises(TableauError, match="not a collocation"):
        collocation_output_weights(tableau("heun"), [0.5])
    with pytest.raises(TableauError, match="repeated nodes"):
        collocation_output_weights(ButcherTableau([[0.5, 0.0], [0.0, 0.5]], [0.5, 0.5]), [0.5])
