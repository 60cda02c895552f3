"""Least squares in a box: the minimum (against scipy's BVLS as the oracle), its optimality
conditions, the unconstrained and degenerate cases, and bad input."""
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.optimize import lsq_linear

from soft_arm_control.box_least_squares import box_least_squares


def _problem(seed: int, square: bool):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 7))
    k = n if square else int(rng.integers(1, 8))
    A = rng.normal(size=(k, n)) * 10.0 ** rng.uniform(-3, 3) * 10.0 ** rng.uniform(-1, 1, size=n)
    b = rng.normal(size=k) * 10.0 ** rng.uniform(-2, 2)
    lo = rng.normal(size=n)
    return A, b, lo, lo + rng.uniform(0.0, 2.0, size=n)


def _cost(A, b, u):
    return float(np.sum((A @ u - b) ** 2))


@settings(max_examples=300, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), square=st.booleans())
def test_the_minimum_is_bvls_s_and_inside_the_box(seed, square):
    A, b, lo, hi = _problem(seed, square)
    u = box_least_squares(A, b, lo, hi)
    assert np.all(u >= lo) and np.all(u <= hi)
    oracle = lsq_linear(A, b, bounds=(lo, hi), method="bvls", tol=1e-14).x
    assert _cost(A, b, u) <= _cost(A, b, oracle) + 1e-12 * (_cost(A, b, oracle) + b @ b)


@settings(max_examples=200, deadline=None)
@given(seed=st.integers(0, 2**32 - 1))
def test_the_gradient_points_out_of_the_box_at_the_minimum(seed):
    """Karush-Kuhn-Tucker: zero gradient on a free variable; on a variable at its lower bound the
    gradient is >= 0 and at its upper <= 0 (moving it into the box would raise the cost)."""
    A, b, lo, hi = _problem(seed, square=True)
    u = box_least_squares(A, b, lo, hi)
    g = A.T @ (A @ u - b)
    tol = 1e-8 * (np.linalg.norm(A, 2) ** 2 * (np.linalg.norm(u) + 1.0) + np.linalg.norm(A.T @ b))
    at_lo, at_hi = u <= lo, u >= hi
    free = ~(at_lo | at_hi)
    assert np.all(np.abs(g[free]) <= tol)
    assert np.all(g[at_lo & ~at_hi] >= -tol)
    assert np.all(g[at_hi & ~at_lo] <= tol)


def test_a_solution_inside_the_box_is_the_plain_least_squares():
    rng = np.random.default_rng(3)
    A, b = rng.normal(size=(5, 3)), rng.normal(size=5)
    plain = np.linalg.lstsq(A, b, rcond=None)[0]
    np.testing.assert_allclose(box_least_squares(A, b, plain - 1.0, plain + 1.0), plain, rtol=1e-12)


def test_with_an_identity_a_the_minimum_is_b_clipped_into_the_box():
    b = np.array([2.0, -0.5, -3.0])
    u = box_least_squares(np.eye(3), b, -np.ones(3), np.ones(3))
    np.testing.assert_allclose(u, [1.0, -0.5, -1.0], rtol=0, atol=1e-15)


def test_a_rank_deficient_problem_returns_a_minimiser():
    """Two equal columns: every split of their sum is a minimiser; one inside the box is returned
    with the least-squares cost."""
    A = np.array([[1.0, 1.0], [2.0, 2.0]])
    b = np.array([1.0, 2.0])                    # u0 + u1 = 1 fits exactly
    u = box_least_squares(A, b, np.zeros(2), np.ones(2))
    assert np.all(u >= 0.0) and np.all(u <= 1.0)
    assert _cost(A, b, u) < 1e-24


def test_a_zero_column_leaves_a_small_one_its_own_least_squares():
    """A singular free block sends each pattern to its own least-squares solve: a column 1e7 times
    shorter than the longest is not cut off with the zero one."""
    A = np.diag([1e4, 1e-3, 0.0])
    u = box_least_squares(A, np.array([0.0, 5e-4, 0.0]), -np.ones(3), np.ones(3))
    np.testing.assert_allclose(u[:2], [0.0, 0.5], rtol=0, atol=1e-9)
    assert -1.0 <= u[2] <= 1.0


def test_a_degenerate_box_holds_the_variable():
    u = box_least_squares(np.eye(2), np.array([5.0, 5.0]), np.array([0.3, 0.0]), np.array([0.3, 9.0]))
    np.testing.assert_allclose(u, [0.3, 5.0], rtol=0, atol=1e-14)


@pytest.mark.parametrize("A, b, lo, hi, message", [
    (np.ones(3), np.ones(3), np.zeros(3), np.ones(3), "must be"),
    (np.ones((2, 3)), np.ones(3), np.zeros(3), np.ones(3), "must be"),
    (np.ones((2, 9)), np.ones(2), np.zeros(9), np.ones(9), "9 variables"),
    (np.ones((2, 2)), np.ones(2), np.zeros(3), np.ones(3), "lo and hi"),
    (np.ones((2, 2)), np.ones(2), np.ones(2), np.zeros(2), "lo <= hi"),
    (np.ones((2, 2)), np.ones(2), np.zeros(2), np.array([1.0, np.inf]), "finite"),
    (np.ones((2, 2)), np.array([np.nan, 1.0]), np.zeros(2), np.ones(2), "A and b must be finite"),
    (np.array([[1.0, np.inf], [0.0, 1.0]]), np.ones(2), np.zeros(2), np.ones(2), "A and b must be finite"),
])
def test_bad_input_is_refused_with_the_reason(A, b, lo, hi, message):
    with pytest.raises(ValueError, match=message):
        box_least_squares(A, b, lo, hi)
