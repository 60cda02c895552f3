"""Closed forms: planar constant-curvature segments driven by one straight tendon, no gravity.

One segment of length L, bending stiffness EI, tendon at distance rho on the section's y axis:
q = kappa L (the bending angle), tendon length L (1 - rho kappa), so theta_a = rho q, the input
matrix B = rho and the equilibrium tension u = EI q / (L rho). A second segment that the tendon does
not span adds an unactuated coordinate q2 with G_theta_u = (EI / L2) q2: the equilibrium set is
q2 = 0, and the tip follows the arc then the straight tangent.
"""
import numpy as np
import pytest
from scipy.optimize import brentq

from soft_arm_control.clik import Clik, ClikGains
from soft_arm_control.collocated import (CollocatedData, build_collocated, equilibrium_jacobian,
                                         evaluate_collocated)
from soft_arm_control.task_space import TaskSpace
from soft_arm_model import build_model, load_arm_config, solve_equilibrium

L, L1, R, FRACTION, E = 0.38, 0.25, 0.01, 0.5, 2.0e5
RHO = FRACTION * R
EI = E * np.pi * R ** 4 / 4


def _model(division_ends, tendon_end):
    n_div = len(division_ends)
    overrides = {
        "geometry.base_radius": R, "geometry.tip_radius": R, "material.youngs_modulus": E,
        "material.axial_law": "linear", "tendons.names": ["t"], "tendons.start_angle_deg": [90.0],
        "tendons.end_angle_deg": [90.0], "tendons.end": [tendon_end],
        "tendons.offset_fraction": [FRACTION], "tendons.friction": [0.0],
        "discretisation.division_ends": division_ends, "discretisation.legendre_order": [0] * n_div,
        "discretisation.gauss_points": [3] * n_div, "gravity": [0.0, 0.0, 0.0],
        "markers.positions": [L],
    }
    for mode in ("torsion", "bending_y", "axial", "shear_y", "shear_z"):
        overrides[f"discretisation.modes.{mode}"] = False
    overrides["discretisation.modes.bending_z"] = True
    return build_model(load_arm_config(overrides=overrides))


@pytest.fixture(scope="module")
def one_segment():
    return _model([L], L)


@pytest.fixture(scope="module")
def two_segments():
    return _model([L1, L], L1)


@pytest.mark.parametrize("angle", [0.2, 0.9, 1.6])
def test_one_segment_collocated_terms(one_segment, angle):
    cm = build_collocated(one_segment, (0,), friction=False)
    cd = evaluate_collocated(cm, CollocatedData(cm), [angle])
    assert cd.B[0, 0] == pytest.approx(RHO, rel=1e-12)
    assert cd.shortening[0] == pytest.approx(RHO * angle, rel=1e-10)
    assert cd.u_eq[0] == pytest.approx(EI * angle / (L * RHO), rel=1e-10)
    eq = solve_equilibrium(one_segment, [EI * angle / (L * RHO)], friction=False)
    assert eq.q[0] == pytest.approx(angle, rel=1e-8)


def test_two_segments_equilibrium_set(two_segments):
    cm = build_collocated(two_segments, (0,), friction=False)
    cd = evaluate_collocated(cm, CollocatedData(cm), [0.7, 0.3])
    assert np.allclose(cm.selector, [[0.0, 1.0]])
    assert cd.u_eq[0] == pytest.approx(EI * 0.7 / (L1 * RHO), rel=1e-10)
    assert cd.G_theta_u[0] == pytest.approx(EI * 0.3 / (L - L1), rel=1e-10)
    assert np.allclose(equilibrium_jacobian(cm, cd), [[0.0, EI / (L - L1)]], rtol=1e-5,
                       atol=1e-6 * EI / (L - L1))


def _tip_y(angle):
    return L1 / angle * (1 - np.cos(angle)) + (L - L1) * np.sin(angle)


def test_two_segments_clik_reaches_the_closed_form(two_segments):
    """The precomputed CLIK on the tip's y coordinate ends on the arc-plus-tangent closed form."""
    angle = 0.8
    cm = build_collocated(two_segments, (0,), friction=False)
    clik = Clik(cm, TaskSpace((0,), (1,)), ClikGains(1.0, 1.0), (0.0, 100.0))
    ref = clik.precompute([_tip_y(angle)], [0.1, 0.0], tol=1e-10)
    assert ref.q == pytest.approx([angle, 0.0], abs=1e-8)
    assert ref.u_ff[0] == pytest.approx(EI * angle / (L1 * RHO), rel=1e-7)
    assert ref.shortening[0] == pytest.approx(RHO * angle, rel=1e-7)
    z_expected = -(L1 / angle * np.sin(angle) + (L - L1) * np.cos(angle))
    x, _ = TaskSpace((0,), (2,)).evaluate(two_segments, ref.q)
    assert x[0] == pytest.approx(z_expected, abs=1e-9)
    # the angle is the root of the closed form for this tip coordinate
    assert brentq(lambda a: _tip_y(a) - _tip_y(angle), 0.1, 1.5) == pytest.approx(angle)
