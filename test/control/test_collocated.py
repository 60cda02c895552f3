"""Collocated coordinates: input decoupling, theta_u invariance, Jacobians against finite differences."""
import numpy as np
import pytest
import scipy.linalg

from soft_arm_control.collocated import (CollocatedData, build_collocated, equilibrium_jacobian,
                                         evaluate_collocated, full_tensions)
from soft_arm_model import actuation_coordinates, solve_equilibrium

ALL = (0, 1, 2, 3)


def _bent(model, u=(1.2, 0.4, 0.9, 0.3)):
    return solve_equilibrium(model, np.array(u)).q


def _null_selector(model, cm, q_ref):
    """S_u = N^T with N an orthonormal basis of ker B(q_ref)^T: a different, dense theta_u."""
    cd = evaluate_collocated(cm, CollocatedData(cm), q_ref)
    return scipy.linalg.null_space(cd.B.T).T


@pytest.mark.parametrize("friction", [False, True])
def test_input_matrix_is_decoupled(paper_model, rng, friction):
    cm = build_collocated(paper_model, ALL, friction=friction)
    cd = CollocatedData(cm)
    for _ in range(3):
        q = _bent(paper_model) + 0.02 * rng.standard_normal(paper_model.n)
        evaluate_collocated(cm, cd, q)
        decoupled = cd.solve_transposed(cd.B)
        expected = np.vstack([np.eye(4), np.zeros((paper_model.n - 4, 4))])
        assert np.abs(decoupled - expected).max() < 1e-10


def test_actuation_coordinates_are_integrable_without_friction(paper_model, rng):
    """d theta_a/dt = B^T qd: the tendon shortenings are exact coordinates (same quadrature as A)."""
    cm = build_collocated(paper_model, ALL, friction=False)
    cd = CollocatedData(cm)
    q = _bent(paper_model)
    evaluate_collocated(cm, cd, q)
    v = rng.standard_normal(paper_model.n)
    h = 1e-6
    fd = (actuation_coordinates(paper_model, q + h * v, friction=False)
          - actuation_coordinates(paper_model, q - h * v, friction=False)) / (2 * h)
    assert np.allclose(fd, cd.B.T @ v, rtol=1e-6, atol=1e-10)


def test_equilibrium_set_and_feedforward_do_not_depend_on_theta_u(paper_model):
    u = np.array([1.1, 0.3, 0.2, 1.4])
    q_eq = solve_equilibrium(paper_model, u).q
    default = build_collocated(paper_model, ALL)
    dense = build_collocated(paper_model, ALL, selector=_null_selector(paper_model, default, q_eq))
    assert not np.allclose(default.selector, dense.selector)
    for cm in (default, dense):
        cd = evaluate_collocated(cm, CollocatedData(cm), q_eq)
        assert np.abs(cd.G_theta_u).max() < 1e-8 * np.abs(cd.G).max()
        assert np.allclose(cd.u_eq, u, atol=1e-8)
        assert np.allclose(cd.K_theta + cd.F_theta, cd.G_theta)
    # off the equilibrium set (moved along an unactuated direction) both residuals are non-zero
    q_off = q_eq + 0.05 * dense.selector[0]
    for cm in (default, dense):
        cd = evaluate_collocated(cm, CollocatedData(cm), q_off)
        assert np.abs(cd.G_theta_u).max() > 1e-4 * np.abs(cd.G).max()


def test_held_tendons_enter_the_equilibrium(paper_model):
    """With tendons 3 and 4 actuated and 1 and 2 held at 0.3 N, an equilibrium of the full tensions
    has G_theta_u = 0 and u_eq equal to the tensions of 3 and 4."""
    cm = build_collocated(paper_model, (2, 3), held_tension=0.3)
    u = full_tensions(cm, [1.5, 0.7])
    assert np.allclose(u, [0.3, 0.3, 1.5, 0.7])
    q = solve_equilibrium(paper_model, u).q
    cd = evaluate_collocated(cm, CollocatedData(cm), q)
    assert np.allclose(cd.u_eq, [1.5, 0.7], atol=1e-8)
    assert np.abs(cd.G_theta_u).max() < 1e-8 * np.abs(cd.G).max()


@pytest.mark.parametrize("active", [ALL, (2, 3)])
def test_equilibrium_jacobian_matches_finite_differences(paper_model, rng, active):
    cm = build_collocated(paper_model, active, held_tension=0.05)
    cd = CollocatedData(cm)
    q = _bent(paper_model) + 0.03 * rng.standard_normal(paper_model.n)
    evaluate_collocated(cm, cd, q)
    jac = equilibrium_jacobian(cm, cd)
    h = 1e-6
    fd = np.empty_like(jac)
    for j in range(paper_model.n):
        e = np.zeros(paper_model.n)
        e[j] = h
        plus = evaluate_collocated(cm, cd, q + e).G_theta_u.copy()
        minus = evaluate_collocated(cm, cd, q - e).G_theta_u.copy()
        fd[:, j] = (plus - minus) / (2 * h)
    assert np.abs(jac - fd).max() < 1e-5 * np.abs(fd).max()


def test_selector_must_complement_the_input_matrix(paper_model):
    with pytest.raises(ValueError, match="selector must have shape"):
        build_collocated(paper_model, ALL, selector=np.zeros((3, paper_model.n)))
    with pytest.raises(ValueError, match="active tendons"):
        build_collocated(paper_model, (0, 0))
    bad = build_collocated(paper_model, ALL, selector=np.zeros((paper_model.n - 4, paper_model.n)))
    with pytest.raises(ValueError, match="singular"):
        evaluate_collocated(bad, CollocatedData(bad), np.zeros(paper_model.n))


@pytest.mark.parametrize("friction", [False, True])
def test_the_compiled_terms_are_their_definitions(paper_model, rng, friction):
    """B = -A[:, active], J_h = [B^T; S_u], G = F_el - F_g + A held, K_theta = J_h^-T F_el,
    F_theta = J_h^-T (G - F_el), theta_a and the shortenings, as numpy composes them, on a pair of
    actuated tendons with the others held (a dense selector: the inverse is not a selection's)."""
    active = (2, 0)
    base = build_collocated(paper_model, active, held_tension=0.7, friction=friction)
    cm = build_collocated(paper_model, active, held_tension=0.7, friction=friction,
                          selector=_null_selector(paper_model, base, _bent(paper_model)))
    cd = CollocatedData(cm)
    for _ in range(3):
        q = _bent(paper_model) + 0.02 * rng.standard_normal(paper_model.n)
        evaluate_collocated(cm, cd, q)
        arm = cd.arm
        A = arm.A if friction else arm.A0
        B = -A[:, list(active)]
        J_h = np.vstack([B.T, cm.selector])
        G = arm.Fel - arm.Fg + A @ cm.held
        K = np.linalg.solve(J_h.T, arm.Fel)
        F = np.linalg.solve(J_h.T, G - arm.Fel)
        shortening = paper_model.rest_tendon_lengths - arm.Lc
        theta_a = paper_model.rest_theta - arm.theta if friction else shortening
        for got, want in ((cd.B, B), (cd.J_h, J_h), (cd.J_h_inv, np.linalg.inv(J_h)), (cd.G, G),
                          (cd.K_theta, K), (cd.F_theta, F), (cd.G_theta, K + F),
                          (cd.shortening, shortening), (cd.theta_a, theta_a)):
            assert np.abs(got - want).max() <= 1e-10 * max(np.abs(want).max(), 1e-12)
        assert np.array_equal(cd.q, q)
