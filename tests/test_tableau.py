"""Tests of integrators/tableau.py against independent truth (notes §6.3-6.5, §7.1).

Truth used here: the number of rooted trees per order (OEIS A000081), the truncated
exponential series of eq. (6.41), closed-form stability functions, the 2-stage order
conditions of eq. (6.39), and a direct stage-by-stage evaluation of one Runge-Kutta step
on the test equation x' = lambda x (eq. 6.40).

Typos found in the notes while writing these tests:
* §6.3.1, "Henn's RK2" (Heun's method): the tableau lists c_2 = 1/2 next to a_21 = 1; the
  consistent node is c_2 = a_21 = 1 (see ``test_notes_heun_typo_is_rejected``).
* §6.5, the Dormand-Prince tableau: the notes say "both steps x_{k+1} and x^_{k+1} are of
  order o = 5"; the embedded row b^ (5179/57600, ...) is only order 4
  (see ``test_dopri5_fsal_and_embedded_order``).
* Eq. (6.41) gives R(z) as the exponential series truncated at the order o; that holds for
  explicit methods with s = o stages only (s <= 4). Dormand-Prince (7 stages, order 5) has the
  extra term z^6 / 600 (see ``test_dopri5_stability_polynomial``).
* §7.4 states the order 2s of the Gauss-Legendre collocation method but not Butcher's
  simplifying assumptions B(p), C(q), D(r) that prove it (order >= min(p, q + r + 1, 2q + 2),
  order <= p); ``test_simplifying_assumptions_of_classical_implicit_methods`` checks the
  theorem on the families tabulated in Hairer & Wanner, *Solving ODEs II*, §IV.5.
"""

from __future__ import annotations

import importlib
import math
import warnings

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from integrators import (
    TABLEAU_NAMES,
    ButcherTableau,
    TableauError,
    gauss_legendre,
    odeint,
    radau_iia,
    tableau,
)

TABLEAU_MODULE = importlib.import_module("integrators.tableau")  # the package exports tableau()

EXPLICIT_NAMES = [n for n in TABLEAU_NAMES if tableau(n).is_explicit]
CLAIMED_ORDER = {
    "euler": 1,
    "midpoint": 2,
    "heun": 2,
    "ralston": 2,
    "kutta3": 3,
    "rk4": 4,
    "rk38": 4,
    "dopri5": 5,
    "implicit_euler": 1,
    "implicit_midpoint": 2,
}
RNG = np.random.default_rng(20240611)


def random_complex(n: int, radius: float = 3.0) -> np.ndarray:
    return radius * (RNG.uniform(-1, 1, n) + 1j * RNG.uniform(-1, 1, n))


def direct_rk_step(tab: ButcherTableau, z: complex) -> complex:
    """x_1 for x_0 = 1 on x' = lambda x with lambda dt = z, stage by stage (eq. 6.26).

    Explicit tableaus evaluate K_i = z (1 + sum_{j<i} a_ij K_j) in order; implicit ones solve
    the (linear) stage equations. Returns x_1 = 1 + sum_i b_i K_i (dt absorbed into z).
    """
    s = tab.stages
    if tab.is_explicit:
        K = np.zeros(s, dtype=complex)
        for i in range(s):
            K[i] = z * (1.0 + tab.A[i, :i] @ K[:i])
    else:
        K = np.linalg.solve(np.eye(s) - z * tab.A, z * np.ones(s))
    return 1.0 + tab.b @ K


# ------------------------------------------------------------------ rooted trees
def test_number_of_rooted_trees_per_order_is_a000081():
    counts = [len(tableau("rk4").order_residuals(p)) for p in range(1, 9)]
    assert counts == [1, 1, 2, 4, 9, 20, 48, 115]


@settings(max_examples=20, deadline=None)
@given(st.integers(min_value=2, max_value=6), st.integers(min_value=0, max_value=2**31 - 1))
def test_bushy_and_tall_tree_conditions_are_among_the_residuals(p, seed):
    """For any tableau the order-p residuals contain b.c^(p-1) - 1/p (bushy tree) and
    b.A^(p-2).c - 1/p! (tall tree): the two trees whose conditions have closed forms."""
    rng = np.random.default_rng(seed)
    s = 4
    A = np.tril(rng.normal(size=(s, s)), -1)
    b = rng.normal(size=s)
    b[-1] = 1.0 - b[:-1].sum()  # consistent weights (order >= 1), as every tableau must have
    tab = ButcherTableau(A, b)
    res = tab.order_residuals(p)
    bushy = b @ tab.c ** (p - 1) - 1.0 / p
    tall = b @ np.linalg.matrix_power(A, p - 2) @ tab.c - 1.0 / math.factorial(p)
    assert np.min(np.abs(res - bushy)) < 1e-12
    assert np.min(np.abs(res - tall)) < 1e-12


# ----------------------------------------------------------- catalogued orders
@pytest.mark.parametrize("name", TABLEAU_NAMES)
def test_catalogued_tableau_has_its_order_and_not_the_next(name):
    tab = tableau(name)
    p = CLAIMED_ORDER[name]
    assert tab.order == p
    assert tab.satisfies_order(p)
    for q in range(1, p + 1):
        assert np.max(np.abs(tab.order_residuals(q))) < 1e-13
    assert not tab.satisfies_order(p + 1)
    # At least one condition of order p + 1 fails by a clear margin, not by rounding.
    assert np.max(np.abs(tab.order_residuals(p + 1))) > 1e-4


def butcher_bound(p, q, r):
    """Order proved by B(p), C(q), D(r) (Butcher 1964)."""
    return min(p, q + r + 1, 2 * q + 2)


SMALL_COLLOCATION = [(f"gauss_legendre_{s}", gauss_legendre(s)) for s in (1, 2, 3, 4)] + [
    (f"radau_iia_{s}", radau_iia(s)) for s in (1, 2, 3, 4)
]


@pytest.mark.parametrize(
    "name, tab",
    [(n, tableau(n)) for n in TABLEAU_NAMES] + SMALL_COLLOCATION,
    ids=list(TABLEAU_NAMES) + [n for n, _ in SMALL_COLLOCATION],
)
def test_reported_order_equals_rooted_tree_order(name, tab):
    """The order found from the simplifying assumptions (plus trees in the gap they leave)
    equals the order found from all rooted trees alone; for collocation methods the
    assumptions settle it without any tree."""
    p, q, r = tab.simplifying_assumptions()
    trees = tab.rooted_tree_order(tab.order + 1)
    assert tab.order == trees
    assert butcher_bound(p, q, r) <= trees <= p
    if name.startswith(("gauss", "radau", "implicit")):
        assert butcher_bound(p, q, r) == trees == p
    if tab.b_err is not None:
        assert tab.embedded_order == tab.rooted_tree_order(tab.embedded_order + 1, tab.b_err)


def _lobatto_and_radau_ia():
    sqrt6 = np.sqrt(6.0)
    return {
        # name: (A, b, (p, q, r), order); Hairer & Wanner II, Tables IV.5.3-IV.5.8
        "radau_ia_2": ([[1 / 4, -1 / 4], [1 / 4, 5 / 12]], [1 / 4, 3 / 4], (3, 1, 2), 3),
        "radau_ia_3": (
            [
                [1 / 9, (-1 - sqrt6) / 18, (-1 + sqrt6) / 18],
                [1 / 9, (88 + 7 * sqrt6) / 360, (88 - 43 * sqrt6) / 360],
                [1 / 9, (88 + 43 * sqrt6) / 360, (88 - 7 * sqrt6) / 360],
            ],
            [1 / 9, (16 + sqrt6) / 36, (16 - sqrt6) / 36],
            (5, 2, 3),
            5,
        ),
        "lobatto_iiia_3": (
            [[0, 0, 0], [5 / 24, 1 / 3, -1 / 24], [1 / 6, 2 / 3, 1 / 6]],
            [1 / 6, 2 / 3, 1 / 6],
            (4, 3, 1),
            4,
        ),
        # q = 1: here 2q + 2 = 4 is the binding bound
        "lobatto_iiib_3": (
            [[1 / 6, -1 / 6, 0], [1 / 6, 1 / 3, 0], [1 / 6, 5 / 6, 0]],
            [1 / 6, 2 / 3, 1 / 6],
            (4, 1, 3),
            4,
        ),
        "lobatto_iiic_2": ([[1 / 2, -1 / 2], [1 / 2, 1 / 2]], [1 / 2, 1 / 2], (2, 1, 1), 2),
        "lobatto_iiic_3": (
            [[1 / 6, -1 / 3, 1 / 6], [1 / 6, 5 / 12, -1 / 12], [1 / 6, 2 / 3, 1 / 6]],
            [1 / 6, 2 / 3, 1 / 6],
            (4, 2, 2),
            4,
        ),
    }


@pytest.mark.parametrize("name", list(_lobatto_and_radau_ia()))
def test_simplifying_assumptions_of_classical_implicit_methods(name):
    A, b, pqr, order = _lobatto_and_radau_ia()[name]
    tab = ButcherTableau(A, b, order=order, name=name)
    assert tab.simplifying_assumptions() == pqr
    assert butcher_bound(*pqr) == order == tab.rooted_tree_order(order + 1)


@settings(max_examples=40, deadline=None)
@given(
    st.integers(min_value=1, max_value=4),
    st.booleans(),
    st.integers(min_value=0, max_value=2**31 - 1),
)
def test_butcher_bound_brackets_the_rooted_tree_order(s, explicit, seed):
    """For any consistent tableau, min(p, q + r + 1, 2q + 2) <= order <= p, and the reported
    order is the rooted-tree order. Nodes are drawn from a few rational values so that some
    draws satisfy higher conditions."""
    rng = np.random.default_rng(seed)
    A = rng.choice([0.0, 0.25, 0.5, -0.5, 1.0 / 3.0, 1.0], size=(s, s))
    if explicit:
        A = np.tril(A, -1)
    b = rng.choice([0.0, 0.25, 0.5, 1.0 / 6.0, 2.0 / 3.0], size=s)
    b[-1] = 1.0 - b[:-1].sum()
    tab = ButcherTableau(A, b)
    p, q, r = tab.simplifying_assumptions()
    trees = tab.rooted_tree_order(2 * s + 1)
    assert butcher_bound(p, q, r) <= trees <= p
    assert tab.order == trees


@pytest.mark.parametrize("name", TABLEAU_NAMES)
def test_stability_function_matches_a_direct_step(name):
    tab = tableau(name)
    z = random_complex(25, radius=1.5)
    expected = np.array([direct_rk_step(tab, zi) for zi in z])
    np.testing.assert_allclose(tab.stability_function(z), expected, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("name", [n for n in EXPLICIT_NAMES if tableau(n).stages <= 4])
def test_explicit_stability_function_is_truncated_exponential(name):
    """Eq. (6.41): R(z) = sum_{k=0}^{o} z^k / k! for explicit methods with s = o <= 4."""
    tab = tableau(name)
    assert tab.stages == tab.order
    z = random_complex(50)
    series = sum(z**k / math.factorial(k) for k in range(tab.order + 1))
    np.testing.assert_allclose(tab.stability_function(z), series, rtol=1e-12, atol=1e-12)
    # and a 2-D array keeps its shape
    assert tab.stability_function(z.reshape(5, 10)).shape == (5, 10)


def test_dopri5_stability_polynomial():
    """R(z) of Dormand-Prince = degree-5 Taylor polynomial + z^6 / 600 (not eq. 6.41 as is).

    The coefficients of R are recovered numerically by a discrete Fourier transform of R
    sampled at the 64th roots of unity (exact for a polynomial of degree < 64).
    """
    tab = tableau("dopri5")
    z = np.exp(2j * np.pi * np.arange(64) / 64)
    coeffs = np.fft.fft(tab.stability_function(z)) / 64
    taylor = [1 / math.factorial(k) for k in range(6)]
    np.testing.assert_allclose(coeffs[:6].real, taylor, atol=1e-14)
    assert coeffs[6].real == pytest.approx(1 / 600, rel=1e-12)
    assert coeffs[6].real != pytest.approx(1 / 720, rel=1e-3)  # not the exponential's term
    np.testing.assert_allclose(np.abs(coeffs[7:]), 0.0, atol=1e-14)
    zr = random_complex(40)
    poly = sum(zr**k / math.factorial(k) for k in range(6)) + zr**6 / 600
    np.testing.assert_allclose(tab.stability_function(zr), poly, rtol=1e-12, atol=1e-12)


def test_implicit_stability_closed_forms_and_limits_at_infinity():
    z = random_complex(30)
    np.testing.assert_allclose(
        tableau("implicit_euler").stability_function(z), 1 / (1 - z), rtol=1e-13
    )
    np.testing.assert_allclose(
        tableau("implicit_midpoint").stability_function(z), (1 + z / 2) / (1 - z / 2), rtol=1e-13
    )
    assert tableau("implicit_euler").stability_at_infinity() == pytest.approx(0.0, abs=1e-15)
    assert tableau("implicit_midpoint").stability_at_infinity() == pytest.approx(-1.0, abs=1e-15)
    # consistent with R evaluated far out on the negative real axis
    assert abs(tableau("implicit_midpoint").stability_function(-1e9) + 1) < 1e-8
    with pytest.raises(TableauError, match="singular A"):
        tableau("rk4").stability_at_infinity()


def test_stability_function_is_inf_where_stage_system_is_singular():
    # I - z A is singular for implicit Euler at z = 1 (the pole of 1/(1 - z)).
    assert np.isinf(tableau("implicit_euler").stability_function(1.0))


# ------------------------------------------------------------ structure flags
def test_dopri5_fsal_and_embedded_order():
    """Notes §6.5 claim both Dormand-Prince rows are order 5: the embedded row is order 4."""
    tab = tableau("dopri5")
    assert tab.is_fsal
    assert tab.order == 5
    assert tab.embedded_order == 4
    assert tab.satisfies_order(4, weights=tab.b_err)
    assert not tab.satisfies_order(5, weights=tab.b_err)
    np.testing.assert_allclose(tab.error_weights, tab.b - tab.b_err)
    # eq. (6.45): last row of A equals b, c_7 = 1, so K_7 of step k is K_1 of step k+1
    np.testing.assert_array_equal(tab.A[-1], tab.b)
    assert tab.c[-1] == pytest.approx(1.0, abs=1e-15)
    for name in ("euler", "rk4", "rk38", "kutta3", "implicit_midpoint"):
        assert not tableau(name).is_fsal
        assert tableau(name).embedded_order is None
        assert tableau(name).error_weights is None


def test_explicit_detection():
    """A method is explicit iff a_ij = 0 for all j >= i (notes §6.3.1)."""
    for name in ("euler", "midpoint", "heun", "ralston", "kutta3", "rk4", "rk38", "dopri5"):
        assert tableau(name).is_explicit
    for name in ("implicit_euler", "implicit_midpoint"):
        assert not tableau(name).is_explicit
    upper = ButcherTableau([[0.0, 0.5], [0.5, 0.0]], [0.5, 0.5])  # a_12 != 0
    diag = ButcherTableau([[0.0, 0.0], [0.5, 0.5]], [0.5, 0.5])  # a_22 != 0
    assert not upper.is_explicit and not upper.is_diagonally_implicit
    assert not diag.is_explicit and diag.is_diagonally_implicit
    # the trapezoidal rule (implicit, order 2) found without a claimed order
    assert diag.order == 2


# ------------------------------------------------------------------ validation
def test_notes_heun_typo_is_rejected():
    """The notes print Heun's tableau with c_2 = 1/2 beside a_21 = 1: c_i != sum_j a_ij."""
    with pytest.raises(TableauError, match=r"c\[1\]"):
        ButcherTableau([[0, 0], [1, 0]], [0.5, 0.5], c=[0, 0.5])
    fixed = ButcherTableau([[0, 0], [1, 0]], [0.5, 0.5], c=[0, 1])
    assert fixed.order == 2


@pytest.mark.parametrize(
    "kwargs, pattern",
    [
        (dict(A=[[0.0, 0.0]], b=[1.0]), "square"),
        (dict(A=[[0.0]], b=[0.5, 0.5]), "length"),
        (dict(A=[[0.0, 0], [0.5, 0]], b=[0.0, 1.0], c=[0.0]), "length"),
        (dict(A=[[0.0, 0], [np.nan, 0]], b=[0.0, 1.0]), "non-finite"),
        (dict(A=[[0.0]], b=[[1.0]]), "dimension"),
        (dict(A=[["a"]], b=[1.0]), "numeric"),
        (dict(A=[[0.0, 0], [0.5, 0]], b=[0.0, 1.0], b_err=[1.0]), "length"),
        (dict(A=[[0.0, 0], [0.5, 0]], b=[0.0, np.inf]), "b contains non-finite"),
        (dict(A=[[0.0, 0], [0.5, 0]], b=[0.0, 1.0], b_err=[np.nan, 1.0]), "b_err contains"),
        (dict(A=[[0.0, 0], [0.5, 0]], b=[0.0, 1.0], c=[0.0, -np.inf]), "c contains"),
    ],
)
def test_malformed_tableaus_raise(kwargs, pattern):
    with pytest.raises(TableauError, match=pattern):
        ButcherTableau(**kwargs)


def test_wrong_claimed_order_raises():
    heun = tableau("heun")
    with pytest.raises(TableauError, match="claims order 3 .* only up to order 2 "):
        ButcherTableau(heun.A, heun.b, order=3)
    rk4 = tableau("rk4")
    # the message quotes the failing condition's own residual: sum b c^4 - 1/5 = 5/24 - 1/5
    with pytest.raises(
        TableauError, match=r"claims order 5 .* only up to order 4 .*misses by 8\.33e-03"
    ):
        ButcherTableau(rk4.A, rk4.b, order=5)
    # one perturbed coefficient breaks order 4 (a_32 = 1/2 -> 0.51: sum b c = 0.5 + 0.01 / 3)
    A = rk4.A.copy()
    A[2, 1] = 0.51
    with pytest.raises(
        TableauError, match=r"claims order 4 .* only up to order 1 .*misses by 3\.33e-03"
    ):
        ButcherTableau(A, rk4.b, order=4)
    assert ButcherTableau(rk4.A, rk4.b, order=4).order == 4
    assert ButcherTableau(rk4.A, rk4.b, order=3).order == 3  # a weaker claim is accepted


@pytest.mark.parametrize("claim", [0, -1, 2.5, True, "2"])
def test_claimed_order_must_be_a_positive_integer(claim):
    with pytest.raises(TableauError, match="order must be an integer >= 1"):
        ButcherTableau(tableau("heun").A, tableau("heun").b, order=claim)


def test_order_beyond_the_tree_limit_is_not_claimed_unproved(monkeypatch):
    """Simplifying assumptions prove order 3 for RK4 (C(1), D(1)); the gap up to B(4) is closed
    by rooted trees, and only up to MAX_TREE_ORDER. With that limit at 3, order 4 is
    unverifiable: a claim is rejected and the computed order is the proved lower bound."""
    rk4 = tableau("rk4")
    assert rk4.simplifying_assumptions() == (4, 1, 1)
    monkeypatch.setattr(TABLEAU_MODULE, "MAX_TREE_ORDER", 3)
    with pytest.raises(
        TableauError,
        match="claims order 4, which could be verified only up to "
        "order 3: .* B\\(4\\), C\\(1\\), D\\(1\\)",
    ):
        ButcherTableau(rk4.A, rk4.b, order=4)
    assert ButcherTableau(rk4.A, rk4.b).order == 3


def test_inconsistent_weights_are_rejected_with_their_sum():
    """sum b_i = 1.2: on x' = 1 every step advances 1.2 dt, an error of 0.2 T that no step
    size removes (order 0). It used to be accepted as an order-0 tableau."""
    with pytest.raises(TableauError, match=r"weights b sum to 1\.2\d*, not 1.*inconsistent"):
        ButcherTableau([[0.0, 0.0], [0.5, 0.0]], [0.2, 1.0])
    with pytest.raises(TableauError, match=r"weights b sum to 1\.2"):
        ButcherTableau([[0.5]], [1.2])  # implicit
    with pytest.raises(TableauError, match=r"weights b_err sum to 0\.9"):
        ButcherTableau([[0.0, 0.0], [1.0, 0.0]], [0.5, 0.5], b_err=[0.9, 0.0])


@pytest.mark.parametrize("tol", [1.0, 1e-5, 0.0, -1.0, float("nan"), 1e-20, "1e-10", True])
def test_tolerance_outside_its_range_is_refused(tol):
    """tol = 1 accepted rk4 with weights summing to 0.9 as an order-4 tableau; the tolerance
    must be a number in [10 eps, 1e-6]."""
    rk4 = tableau("rk4")
    with pytest.raises(TableauError, match=r"tol must be a number from 2\.2e-15 to 1e-06"):
        ButcherTableau(rk4.A, 0.9 * rk4.b, tol=tol)


def test_largest_tolerance_accepts_coefficients_printed_to_seven_digits():
    """rk4 with 1/6, 1/3 printed to 7 digits meets its order conditions to 1e-7: tol = 1e-6
    accepts it as order 4, the default 1e-10 only as order 2 (sum b c = 1/2 exactly)."""
    rk4 = tableau("rk4")
    b = np.round(rk4.b, 7)
    assert ButcherTableau(rk4.A, b, tol=1e-6).order == 4
    assert ButcherTableau(rk4.A, b).order == 2


@settings(max_examples=40, deadline=None)
@given(
    st.lists(st.floats(min_value=-2.0, max_value=2.0), min_size=1, max_size=6),
    st.floats(min_value=1e-8, max_value=10.0),
    st.sampled_from([-1.0, 1.0]),
    st.booleans(),
)
def test_weights_off_unit_sum_always_raise(free, offset, sign, explicit):
    s = len(free)
    A = np.tril(np.full((s, s), 0.3), -1 if explicit else 0)
    b = np.array(free)
    b[-1] += 1.0 + sign * offset - b.sum()  # sum b = 1 +- offset
    with pytest.raises(TableauError, match="sum to"):
        ButcherTableau(A, b)
    with pytest.raises(TableauError, match="b_err sum to"):
        ButcherTableau(A, np.full(s, 1.0 / s), b_err=b)


def test_odeint_integrates_only_checked_tableaus():
    """A user tableau reaches odeint only through the constructor's checks, and its checked
    coefficients cannot be replaced or edited afterwards."""
    x0 = torch.zeros(1, 1, dtype=torch.float64)
    t = torch.linspace(0.0, 1.0, 11, dtype=torch.float64)
    with pytest.raises(TableauError, match="sum to 1.2"):
        odeint(lambda tt, x: torch.ones_like(x), x0, t, method=ButcherTableau([[0.0]], [1.2]))
    tab = ButcherTableau([[0.0, 0.0], [1.0, 0.0]], [0.5, 0.5], name="user_heun")
    for attr in ("A", "b", "c", "b_err"):
        with pytest.raises(AttributeError):
            setattr(tab, attr, np.array([0.6, 0.6]))
    with pytest.raises(ValueError):
        tab.b[0] = 0.7
    # x' = 1: an order >= 1 method is exact, x(1) = 1
    sol = odeint(lambda tt, x: torch.ones_like(x), x0, t, method=tab)
    assert abs(float(sol.x[0, -1, 0]) - 1.0) < 1e-14


@settings(max_examples=30, deadline=None)
@given(st.floats(min_value=0.05, max_value=2.0, allow_nan=False))
def test_two_stage_family_of_eq_6_39_is_exactly_order_2(c2):
    """b1 + b2 = 1, b2 c2 = 1/2, a21 = c2 (eq. 6.39) gives order 2 and never order 3."""
    b2 = 0.5 / c2
    tab = ButcherTableau([[0.0, 0.0], [c2, 0.0]], [1.0 - b2, b2], order=2)
    assert tab.order == 2
    assert not tab.satisfies_order(3)
    # the tall tree of order 3 always fails: b^T A c = 0 != 1/6
    assert np.max(np.abs(tab.order_residuals(3))) >= 1 / 6 - 1e-12
    z = random_complex(5)
    np.testing.assert_allclose(tab.stability_function(z), 1 + z + z**2 / 2, rtol=1e-12)


@settings(max_examples=30, deadline=None)
@given(st.floats(min_value=0.05, max_value=2.0), st.floats(min_value=0.05, max_value=2.0))
def test_two_stage_family_violating_eq_6_39_is_order_1(c2, b2):
    """Consistent (b1 + b2 = 1) but b2 c2 != 1/2: only order 1."""
    if abs(b2 * c2 - 0.5) < 1e-3:
        return
    tab = ButcherTableau([[0.0, 0.0], [c2, 0.0]], [1.0 - b2, b2])
    assert tab.order == 1
    with pytest.raises(TableauError):
        ButcherTableau([[0.0, 0.0], [c2, 0.0]], [1.0 - b2, b2], order=2)


def test_tableau_is_read_only_and_unknown_names_are_listed():
    tab = tableau("rk4")
    with pytest.raises(ValueError):
        tab.A[0, 0] = 1.0
    with pytest.raises(TableauError, match="rk4"):
        tableau("rk5")


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_tensors_round_trip(dtype):
    tab = tableau("dopri5")
    A, b, c, e = tab.tensors(dtype)
    assert A.dtype == b.dtype == c.dtype == e.dtype == dtype
    np.testing.assert_allclose(
        A.double().numpy(), tab.A, rtol=1e-6 if dtype == torch.float32 else 0
    )
    np.testing.assert_allclose(e.double().numpy(), tab.b - tab.b_err, atol=1e-7)
    assert tableau("rk4").tensors(dtype)[3] is None
    fresh = ButcherTableau(tab.A, tab.b)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no "non-writable NumPy array" warning from torch
        A_fresh = fresh.tensors(dtype)[0]
    A_fresh[1, 0] = 5.0  # a copy: the read-only tableau itself is unchanged
    assert fresh.A[1, 0] == 0.2
