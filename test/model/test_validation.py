"""Validation of the model against references built independently of it."""
import numpy as np
import pytest
from scipy.linalg import expm

from soft_arm_model import ArmData, evaluate, solve_equilibrium, tip_frame
from soft_arm_model.model import R_BASE
from soft_arm_model.references import (euler_bernoulli_tip_deflection, kirchhoff_cantilever_tip,
                                       tendon_load_tip)

NO_GRAVITY = {"gravity": [0.0, 0.0, 0.0]}


def _hat(xi):
    k, g = xi[:3], xi[3:]
    H = np.zeros((4, 4))
    H[:3, :3] = [[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]]
    H[:3, 3] = g
    return H


def test_uniform_rod_one_straight_tendon_lies_on_exact_arc(model_factory):
    r, L, E, frac, u = 0.01, 0.38, 1e5, 0.5, 1.0
    m = model_factory(**NO_GRAVITY, **{
        "geometry.base_radius": r, "geometry.tip_radius": r, "material.axial_law": "linear",
        "material.youngs_modulus": E,
        "tendons.names": ["t"], "tendons.start_angle_deg": [90.0], "tendons.end_angle_deg": [90.0],
        "tendons.end": [L], "tendons.offset_fraction": [frac], "tendons.friction": [0.0],
        "discretisation.division_ends": [L], "discretisation.legendre_order": [1],
        "discretisation.gauss_points": [4], "markers.positions": [L]})
    eq = solve_equilibrium(m, [u])
    I, A, d = np.pi * r ** 4 / 4, np.pi * r ** 2, frac * r
    # tendon at 90 deg: section-frame offset (0, d, 0); bending about the section z axis
    xi = np.array([0.0, 0.0, u * d / (E * I), 1.0 - u / (E * A), 0.0, 0.0])
    g0 = np.eye(4)
    g0[:3, :3] = R_BASE
    tip = (g0 @ expm(_hat(xi) * L))[:3, 3]
    np.testing.assert_allclose(tip_frame(m, eq.q).p, tip, atol=1e-6)
    assert np.linalg.norm(tip - [0, 0, -L]) > 0.1  # a large, non-trivial deflection


def _cantilever_model(make_model, E, orders, gauss,
                      modes=("torsion", "bending_y", "bending_z", "axial")):
    over = {"material.youngs_modulus": E, "gravity": [-9.81, 0.0, 0.0],
            "discretisation.legendre_order": orders, "discretisation.gauss_points": gauss}
    for mode in ("torsion", "bending_y", "bending_z", "axial", "shear_y", "shear_z"):
        over[f"discretisation.modes.{mode}"] = mode in modes
    return make_model(**over)


def test_euler_bernoulli_small_deflection_of_stiff_cone(model_factory):
    m = _cantilever_model(model_factory, 1e9, [4, 3], [10, 6])
    w_tip = euler_bernoulli_tip_deflection(m.config)
    tip = tip_frame(m, solve_equilibrium(m, [0.0] * 4).q).p
    assert w_tip > 1e-5
    assert abs(-tip[0] - w_tip) / w_tip < 1e-3


def test_large_deflection_matches_kirchhoff_bvp(model_factory):
    m = _cantilever_model(model_factory, 1.5e5, [5, 3], [10, 6], modes=("bending_y", "bending_z"))
    axial_ref, deflection_ref = kirchhoff_cantilever_tip(m.config)
    tip = tip_frame(m, solve_equilibrium(m, [0.0] * 4).q).p
    assert deflection_ref < -0.1  # a genuinely large deflection
    np.testing.assert_allclose([-tip[2], tip[0]], [axial_ref, deflection_ref], atol=5e-4)


# ---- tendon-only loads: the pointwise exact reference -------------------------------------------

def _tip_error(m, u):
    tip = tip_frame(m, solve_equilibrium(m, u, friction=False).q).p
    return np.linalg.norm(tip - tendon_load_tip(m.config, u, R_BASE))


@pytest.mark.parametrize("u", [[2.0, 0, 0, 0], [0, 0, 2.0, 0], [0, 0, 2.0, 2.0], [1.0, 0, 2.0, 0]],
                         ids=["straight", "crossed", "crossed-pair", "mixed"])
def test_tendon_loads_converge_to_pointwise_reference(model_factory, u):
    errors = []
    for order in (1, 2, 3, 5):
        m = model_factory(**NO_GRAVITY, **{"discretisation.legendre_order": [order, 0],
                                           "discretisation.gauss_points": [order + 6, 3]})
        errors.append(_tip_error(m, u))
    assert errors[-1] < 2e-4, errors
    assert errors[-1] < errors[0] / 10, errors


def test_basis_without_break_at_tendon_end_does_not_converge(model_factory):
    u = [0, 0, 2.0, 0]
    errors = []
    for order in (3, 5, 7):
        m = model_factory(**NO_GRAVITY, **{
            "discretisation.division_ends": [0.38], "discretisation.legendre_order": [order],
            "discretisation.gauss_points": [order + 6],
            "discretisation.allow_tendon_end_inside_division": True})
        errors.append(_tip_error(m, u))
    assert min(errors) > 1e-3, errors  # stalls at millimetres whatever the order


# ---- symmetry and routing, friction --------------------------------------------------------------

def _total_twist(m, q):
    return sum(q[i] for i, lab in enumerate(m.coordinate_labels) if ".torsion.P0" in lab)


def test_crossed_tendons_twist_in_opposite_directions_and_cancel(paper_model):
    m = paper_model
    q3 = solve_equilibrium(m, [0, 0, 3.0, 0]).q
    q4 = solve_equilibrium(m, [0, 0, 0, 3.0]).q
    q34 = solve_equilibrium(m, [0, 0, 3.0, 3.0]).q
    t3, t4, t34 = _total_twist(m, q3), _total_twist(m, q4), _total_twist(m, q34)
    assert abs(t3) > 0.2 and np.sign(t3) == -np.sign(t4)
    assert abs(t3 + t4) < 1e-8 * abs(t3)             # mirror images
    assert abs(t34) < 1e-9
    p3, p4 = tip_frame(m, q3).p, tip_frame(m, q4).p
    np.testing.assert_allclose(p3 * [-1, 1, 1], p4, atol=1e-9)  # mirror x -> -x
    assert abs(tip_frame(m, q34).p[0]) < 1e-9


def test_friction_lowers_transmitted_load_monotonically(paper_model, model_factory):
    m = paper_model
    q = solve_equilibrium(m, [3.0, 0, 3.0, 0]).q
    d = evaluate(m, ArmData(m), q, level=1)
    for k in range(m.n_tendons):
        on = (m.tendon_active[k] > 0)
        weight = np.exp(-m.friction_mu[k] * d.wrap[k, on])
        assert np.all(np.diff(weight) <= 1e-15) and weight[-1] < 0.99
    tips = []
    for mu in (0.0, 0.1, 0.2, 0.4):
        mm = model_factory(**{"tendons.friction": [mu] * 4})
        tips.append(np.linalg.norm(tip_frame(mm, solve_equilibrium(mm, [3.0, 0, 0, 0]).q).p
                                   - [0, 0, -0.38]))
    assert np.all(np.diff(tips) < 0), tips


def test_zero_friction_recovers_frictionless_model(model_factory, rng):
    m = model_factory(**{"tendons.friction": [0.0] * 4})
    q = rng.normal(size=m.n) * 0.3
    d = evaluate(m, ArmData(m), q, level=1)
    assert np.array_equal(d.A, d.A0)
    assert np.array_equal(d.theta, d.Lc)


def test_paper_arm_converges_over_the_whole_tension_range(paper_model):
    """0-5 N on every combination of tendons: every equilibrium found, stretch stays positive."""
    from soft_arm_model.workspace import sample_workspace
    ws = sample_workspace(paper_model, [0.0, 2.5, 5.0])
    assert ws.converged.all()
    data = ArmData(paper_model)
    stretch = min(evaluate(paper_model, data, q, level=1).xi[paper_model.w > 0, 3].min() for q in ws.q)
    assert 0.5 < stretch < 0.95  # some, limited, axial compression
    assert ws.tip[:, 2].max() > -0.05  # the tip reaches up towards the base plane
