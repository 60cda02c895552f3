"""Finite-difference checks of every derivative the model computes."""
import numpy as np
import pytest

from soft_arm_model import ArmData, actuation_coordinates, evaluate, marker_positions, solve_equilibrium
from soft_arm_model.dynamics import CORIOLIS, STATICS

EPS = 1e-6


def _state(model, rng, scale=0.3):
    return rng.normal(size=model.n) * scale, rng.normal(size=model.n)


def _vee(S):
    return np.array([S[2, 1], S[0, 2], S[1, 0]])


@pytest.fixture(params=["paper_model", "full_model", "loaded_model"])
def model(request):
    return request.getfixturevalue(request.param)


def test_body_jacobian_matches_finite_differences(model, rng):
    q, v = _state(model, rng)
    d0 = evaluate(model, ArmData(model), q, level=0, markers=True)
    dp = evaluate(model, ArmData(model), q + EPS * v, level=0, markers=True)
    dm = evaluate(model, ArmData(model), q - EPS * v, level=0, markers=True)
    for R, p, J, Rp, pp, Rm, pm in [(d0.R, d0.p, d0.J, dp.R, dp.p, dm.R, dm.p),
                                    (d0.marker_R, d0.marker_p, d0.marker_J, dp.marker_R, dp.marker_p,
                                     dm.marker_R, dm.marker_p)]:
        for i in range(R.shape[0]):
            w = _vee(R[i].T @ (Rp[i] - Rm[i]) / (2 * EPS))
            lin = R[i].T @ (pp[i] - pm[i]) / (2 * EPS)
            np.testing.assert_allclose(J[i] @ v, np.concatenate([w, lin]), atol=1e-7)


def test_twist_and_jacobian_rate(model, rng):
    q, qd = _state(model, rng)
    d = evaluate(model, ArmData(model), q, qd, level=CORIOLIS)
    Jp = evaluate(model, ArmData(model), q + EPS * qd, level=0).J
    Jm = evaluate(model, ArmData(model), q - EPS * qd, level=0).J
    np.testing.assert_allclose(d.Jd, (Jp - Jm) / (2 * EPS), atol=1e-7)
    np.testing.assert_allclose(d.eta, np.einsum("pij,j->pi", d.J, qd), atol=1e-12)
    np.testing.assert_allclose(d.psi, np.einsum("pij,j->pi", d.Jd, qd), atol=1e-10)
    np.testing.assert_allclose(d.Cqd, d.C @ qd, atol=1e-12 * np.abs(d.Cqd).max() + 1e-15)


def test_mass_matrix_spd_and_mdot_equals_c_plus_ct(model, rng):
    q, qd = _state(model, rng)
    d = evaluate(model, ArmData(model), q, qd, level=CORIOLIS)
    np.testing.assert_allclose(d.M, d.M.T, rtol=0, atol=1e-14 * np.abs(d.M).max())
    assert np.linalg.eigvalsh(d.M).min() > 0
    Mp = evaluate(model, ArmData(model), q + EPS * qd, level=2).M.copy()
    Mm = evaluate(model, ArmData(model), q - EPS * qd, level=2).M.copy()
    Mdot = (Mp - Mm) / (2 * EPS)
    np.testing.assert_allclose(d.C + d.C.T, Mdot, atol=1e-7 * np.abs(Mdot).max())
    assert np.abs(Mdot).max() > 1e-6  # the check is not vacuous


def test_forces_are_gradients_of_energies(model, rng):
    q, _ = _state(model, rng)
    d = evaluate(model, ArmData(model), q, level=STATICS)
    Fg, Fel, Kt = d.Fg.copy(), d.Fel.copy(), d.Kt.copy()
    grad_g = np.zeros(model.n)
    grad_e = np.zeros(model.n)
    dFel = np.zeros((model.n, model.n))
    for b in range(model.n):
        e = np.zeros(model.n)
        e[b] = EPS
        dp = evaluate(model, ArmData(model), q + e, level=STATICS)
        dm = evaluate(model, ArmData(model), q - e, level=STATICS)
        grad_e[b] = (dp.energies[1] - dm.energies[1]) / (2 * EPS)
        grad_g[b] = (dp.energies[2] - dm.energies[2]) / (2 * EPS)
        dFel[:, b] = (dp.Fel - dm.Fel) / (2 * EPS)
    np.testing.assert_allclose(Fg, -grad_g, atol=1e-8 * np.abs(Fg).max())
    np.testing.assert_allclose(Fel, grad_e, atol=1e-8 * np.abs(Fel).max())
    np.testing.assert_allclose(Kt, dFel, atol=1e-6 * np.abs(Kt).max())


def test_actuation_matrix_is_tendon_length_gradient_without_friction(model, rng):
    q, _ = _state(model, rng)
    d = evaluate(model, ArmData(model), q, level=STATICS)
    A0 = d.A0.copy()
    grad = np.zeros_like(A0)
    for b in range(model.n):
        e = np.zeros(model.n)
        e[b] = EPS
        grad[b] = (evaluate(model, ArmData(model), q + e, level=STATICS).Lc
                   - evaluate(model, ArmData(model), q - e, level=STATICS).Lc) / (2 * EPS)
    np.testing.assert_allclose(A0, grad, atol=1e-8 * np.abs(A0).max())
    # with friction the matrix differs (the friction weight is not a gradient)
    assert np.abs(d.A - A0).max() > 1e-4 * np.abs(A0).max()


def test_damping_proportional_to_stiffness_for_incompressible_material(paper_model):
    m = paper_model
    mat = m.config.material
    np.testing.assert_allclose(m.D, 3 * mat.viscosity / mat.youngs_modulus * m.K,
                               atol=1e-12 * np.abs(m.D).max())


def test_actuation_coordinates_are_tendon_shortenings(paper_model, rng):
    m = paper_model
    # straight tendons follow the cone's taper: a straight slanted line at rest; crossed ones longer
    g = m.config.geometry
    slope = 0.6 * (g.tip_radius - g.base_radius) / g.length
    np.testing.assert_allclose(m.rest_tendon_lengths[:2], 0.325 * np.hypot(1, slope), rtol=1e-12)
    assert np.all(m.rest_tendon_lengths[2:] > m.rest_tendon_lengths[0] + 1e-5)
    q, v = _state(m, rng)
    thp = actuation_coordinates(m, q + EPS * v, friction=False)
    thm = actuation_coordinates(m, q - EPS * v, friction=False)
    A0 = evaluate(m, ArmData(m), q, level=STATICS).A0
    np.testing.assert_allclose((thp - thm) / (2 * EPS), -A0.T @ v, atol=1e-8)
    # pulling shortens: theta_a > 0 at the equilibrium under tension, friction-aware one too
    q_eq = solve_equilibrium(m, [2.0, 2.0, 2.0, 2.0]).q
    assert np.all(actuation_coordinates(m, q_eq, friction=False) > 1e-3)
    assert np.all(actuation_coordinates(m, q_eq) > 1e-3)
    np.testing.assert_array_equal(actuation_coordinates(m, np.zeros(m.n)), np.zeros(4))


def test_tip_mass_is_a_point_mass_at_the_tip(model_factory, rng):
    """A tip mass m adds m J^T J (linear rows of the tip's body Jacobian) to M, its weight
    m J^T R^T g to F_g, m g.p to the potential and nothing to the elastic or tendon terms."""
    m_tip = 0.013
    bare, loaded = model_factory(), model_factory(tip_mass=m_tip)
    q, qd = _state(bare, rng)
    d0 = evaluate(bare, ArmData(bare), q, qd, level=CORIOLIS, markers=True)
    d1 = evaluate(loaded, ArmData(loaded), q, qd, level=CORIOLIS, markers=True)
    assert bare.marker_X[-1] == bare.length
    Jl, R = d0.marker_J[-1][3:], d0.marker_R[-1]
    np.testing.assert_allclose(d1.M - d0.M, m_tip * Jl.T @ Jl, atol=1e-12 * np.abs(d1.M).max())
    np.testing.assert_allclose(d1.Fg - d0.Fg, m_tip * Jl.T @ (R.T @ bare.gravity),
                               atol=1e-12 * np.abs(d1.Fg).max())
    np.testing.assert_allclose(d1.energies[2] - d0.energies[2],
                               -m_tip * bare.gravity @ d0.marker_p[-1], rtol=1e-10)
    np.testing.assert_array_equal(d1.Fel, d0.Fel)
    np.testing.assert_array_equal(d1.A, d0.A)
    assert abs(loaded.lumped_mass[:, 3].sum() - bare.lumped_mass[:, 3].sum() - m_tip) < 1e-15
    # the hanging arm stretches under the tip weight: the tip drops by m g int dX / (E A(X)) =
    # m g L / (E pi r_b r_t) on the cone (small strain; the basis approximates 1 / A(X))
    g, E = bare.config.geometry, bare.config.material.youngs_modulus
    drop = m_tip * 9.81 * g.length / (E * np.pi * g.base_radius * g.tip_radius)
    z0 = marker_positions(bare, solve_equilibrium(bare, np.zeros(4)).q)[-1]
    z1 = marker_positions(loaded, solve_equilibrium(loaded, np.zeros(4)).q)[-1]
    np.testing.assert_allclose(z0[2] - z1[2], drop, rtol=0.03)
    np.testing.assert_allclose(z1[:2], z0[:2], atol=1e-9)


def test_the_strain_basis_is_the_legendre_polynomials_and_their_derivatives():
    """The recurrence that builds the basis against numpy's Legendre series, order by order, and
    each derivative against a central difference."""
    from numpy.polynomial import legendre
    from soft_arm_model.model import _legendre
    for s in np.linspace(-1.0, 1.0, 9):
        P, dP = _legendre(s, 8)
        for j in range(9):
            unit = np.eye(9)[j][:j + 1]
            assert P[j] == pytest.approx(legendre.legval(s, unit), abs=1e-14)
            h = 1e-6
            central = (_legendre(s + h, 8)[0][j] - _legendre(s - h, 8)[0][j]) / (2 * h)
            assert dP[j] == pytest.approx(central, abs=1e-7)
    assert _legendre(0.3, 0)[0].tolist() == [1.0]
