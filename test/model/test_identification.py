"""Static identification: recovery of the model's own arm and of a structurally different one, the
sensitivities against finite differences, refusal of data that cannot determine the fit."""
from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from soft_arm_model import ArmData, build_model, load_arm_config, solve_equilibrium
from soft_arm_model.identification import (IdentificationError, StaticProblem, StaticSample, _Layout,
                                           observe, identify_static, parameter_vector, staircase,
                                           with_basis_shift)

ZERO = np.array([0.01, -0.02, 0.005, 0.0])          # encoder zeros [m]
# a structurally different arm: E -12 %, density +5 %, uneven friction, offsets, angles,
# and 3 g at the tip
DEG = np.radians


def _different(arm):
    material = replace(arm.material, youngs_modulus=0.88 * arm.material.youngs_modulus,
                       density=1.05 * arm.material.density)
    tendons = tuple(replace(t, friction=f, offset_fraction=o, start_angle=t.start_angle + a0,
                            end_angle=t.end_angle + a1)
                    for t, f, o, a0, a1 in zip(arm.tendons, [0.09, 0.16, 0.12, 0.14], [0.57, 0.64, 0.6, 0.62],
                                               DEG([2, -3, 1, -2]), DEG([-1, 3, 2, -3])))
    return replace(arm, material=material, tendons=tendons, tip_mass=arm.tip_mass + 0.003)


def _samples(arm, tensions, rotation=Rotation.identity(), shift=np.zeros(3), noise=0.0, seed=0):
    """Equilibria of ``arm`` under each tension row, seen by encoders with ZERO and by a mocap
    frame with p_arm = rotation p_mocap + shift, with Gaussian marker noise [m]."""
    model = build_model(arm)
    data = ArmData(model)
    rng = np.random.default_rng(seed)
    out, q, u0 = [], None, None
    for u in tensions:
        eq = solve_equilibrium(model, u, q_start=q, u_start=u0)
        q, u0 = eq.q, u
        p, s, _, _ = observe(model, data, eq.q)
        out.append(StaticSample(u, s + ZERO, (p - shift) @ rotation.as_matrix()
                                + rng.normal(0.0, noise, p.shape)))
    return out


TENSIONS = staircase(4, 0.05, 2.5, steps=2, pairs=[(0, 1), (2, 3), (0, 2), (1, 3)])


def test_the_staircase_loads_and_unloads_each_tendon_and_pair_within_the_limits():
    u = staircase(4, 0.05, 2.5, steps=2, pairs=[(0, 1)])
    assert u.shape == (1 + 5 * 4, 4) and u.min() == 0.05 and u.max() == 2.5
    assert np.array_equal(u[0], u[-1])
    assert np.allclose(u[1:5, 0], [1.275, 2.5, 1.275, 0.05]) and np.all(u[1:5, 1:] == 0.05)
    assert np.all(u[17:21, 0] == u[17:21, 1]) and u[18, 0] == 2.5     # the pair pulls together
    with pytest.raises(ValueError, match="low < high"):
        staircase(4, 2.0, 1.0)


def test_the_fit_returns_the_arm_it_is_given_data_of(paper_model):
    arm = paper_model.config
    fit = identify_static(arm, _samples(arm, TENSIONS), marker_sigma=2e-5, shortening_sigma=2e-6)
    assert fit.arm.material.youngs_modulus == pytest.approx(arm.material.youngs_modulus, rel=5e-3)
    assert fit.arm.material.density == pytest.approx(arm.material.density, rel=5e-3)
    assert abs(fit.arm.tip_mass - arm.tip_mass) < 1e-4
    for t_fit, t in zip(fit.arm.tendons, arm.tendons):
        assert abs(t_fit.friction - t.friction) < 0.005
        assert abs(t_fit.offset_fraction - t.offset_fraction) < 0.005
    assert np.allclose(fit.encoder_zero, ZERO, atol=1e-5)
    assert fit.registration.angle < 1e-3 and np.allclose(fit.registration.translation, 0, atol=1e-4)
    assert np.all(fit.marker_rms < 1e-5)


def test_a_trial_step_without_an_equilibrium_is_refused_not_the_fit(paper_model):
    """On these data (the different arm, the mocap frame in place) the fit's third trial
    step has no equilibrium under the crossed pair's 2.5 N: the trust region shrinks and the fit
    goes on to the arm rather than stopping with an error."""
    arm = paper_model.config
    truth = _different(arm)
    fit = identify_static(arm, _samples(truth, TENSIONS, noise=2e-5), marker_sigma=2e-5,
                          shortening_sigma=2e-6)
    assert abs(fit.arm.material.youngs_modulus / truth.material.youngs_modulus - 1) < 0.01
    assert np.all(fit.marker_rms < 1e-4)


def test_a_fit_started_from_a_fit_on_the_same_basis_stays_within_its_noise(paper_model):
    """The parameter vector of a fit rebuilds the fit's arm; refitting from it on the same basis
    moves no estimate by its standard error (the first fit stopped at its tolerance, the refit goes
    on a little), so the basis shift of a basis that changes nothing adds nothing to speak of."""
    arm = paper_model.config
    samples = _samples(arm, TENSIONS, noise=2e-5)
    fit = identify_static(arm, samples, marker_sigma=2e-5, shortening_sigma=2e-6)
    layout = _Layout(arm)
    rebuilt = layout.arm(parameter_vector(layout, fit))
    assert rebuilt.material.youngs_modulus == pytest.approx(fit.arm.material.youngs_modulus, rel=1e-12)
    assert rebuilt.tendons == fit.arm.tendons and rebuilt.tip_mass == pytest.approx(fit.arm.tip_mass)
    again = identify_static(arm, samples, marker_sigma=2e-5, shortening_sigma=2e-6, start=fit,
                            max_evaluations=3)
    shifted = with_basis_shift(fit, again)
    for name, e in shifted.estimates.items():
        assert e.basis_shift < e.standard_error + 1e-12, name
        assert e.uncertainty < 1.5 * e.standard_error + 1e-12, name


def test_a_different_arm_and_a_misplaced_mocap_frame_are_recovered_with_honest_errors(paper_model):
    """E -12 %, density +5 %, 3 g at the tip, friction 0.09-0.16, offsets 0.57-0.64, angles +-3 deg, the mocap
    frame turned 2 deg and shifted 5 mm, 0.02 mm marker noise (0.2 mm averaged over 100 frames).
    Angles are compared up to their common turn about the axis, the gauge the mocap frame takes
    (the module's docstring); each estimate's error is within 4 standard errors."""
    arm = paper_model.config
    truth = _different(arm)
    axis = np.array([0.3, 0.5, 0.8]) / np.linalg.norm([0.3, 0.5, 0.8])
    rotation = Rotation.from_rotvec(DEG(2.0) * axis)
    shift = np.array([0.005, -0.003, 0.004])
    fit = identify_static(arm, _samples(truth, TENSIONS, rotation, shift, noise=2e-5),
                          marker_sigma=2e-5, shortening_sigma=2e-6)
    est = fit.estimates
    E = truth.material.youngs_modulus
    assert abs(fit.arm.material.youngs_modulus / E - 1) < 0.03
    assert abs(est["youngs_modulus"].value - E) < 4 * est["youngs_modulus"].standard_error + 1e-9 * E
    assert abs(fit.arm.tip_mass - truth.tip_mass) < 3e-4
    assert abs(est["tip_mass"].value - truth.tip_mass) < 4 * est["tip_mass"].standard_error + 1e-7
    turn = np.mean([t.start_angle for t in truth.tendons]) - np.mean([t.start_angle for t in arm.tendons])
    for t_fit, t in zip(fit.arm.tendons, truth.tendons):
        assert abs(t_fit.friction - t.friction) < 0.02
        assert abs(t_fit.offset_fraction - t.offset_fraction) < 0.02
        assert abs(t_fit.start_angle + turn - t.start_angle) < DEG(1.0)
        assert abs(t_fit.end_angle + turn - t.end_angle) < DEG(1.0)
        for group, true in (("friction", t.friction), ("offset_fraction", t.offset_fraction)):
            e = est[f"{group}[{t.name}]"]
            assert abs(e.value - true) < 4 * e.standard_error + 1e-6, (group, t.name)
    # the registration, with the common turn of the tendons given back: the frame within 0.5 deg, 1 mm
    gauge = Rotation.from_rotvec([0.0, 0.0, turn])
    error = (gauge * Rotation.from_matrix(fit.registration.rotation) * rotation.inv()).magnitude()
    assert error < DEG(0.5)
    assert np.linalg.norm(gauge.apply(fit.registration.translation) - shift) < 1e-3
    assert np.allclose(fit.encoder_zero, ZERO, atol=2e-5)


def test_the_sensitivities_agree_with_finite_differences_of_re_solved_equilibria(paper_model):
    """Every column of the implicit-function Jacobian against central differences of the residual
    with every equilibrium solved again."""
    arm = paper_model.config
    samples = _samples(_different(arm), TENSIONS[::3])
    pb = StaticProblem(arm, samples, 2e-5, 2e-6)
    p = pb.p0 + 0.01 * np.random.default_rng(3).standard_normal(pb.p0.size) * \
        np.concatenate([np.ones(pb.layout.n_model), np.full(pb.n_t + 6, 0.01)])
    J = pb.jacobian(p.copy())
    for j in range(pb.layout.size):
        h = 1e-6
        plus, minus = p.copy(), p.copy()
        plus[j] += h
        minus[j] -= h
        fd = (pb.residual(plus) - pb.residual(minus)) / (2 * h)
        scale = max(np.abs(fd).max(), 1.0)
        assert np.abs(J[:, j] - fd).max() < 2e-4 * scale, pb.names[j]


def test_data_that_cannot_determine_the_fit_is_refused(paper_model):
    arm = paper_model.config
    never_3 = TENSIONS.copy()
    never_3[:, 2] = 0.05
    with pytest.raises(IdentificationError, match="tendon_3 is never pulled"):
        identify_static(arm, _samples(arm, never_3))
    with pytest.raises(IdentificationError, match="at least 8 are needed"):
        identify_static(arm, _samples(arm, TENSIONS[:5]))


def test_an_identified_arm_is_written_as_a_description_every_entry_point_takes(paper_model, tmp_path):
    from soft_arm_experiments.harness import load_setup
    from soft_arm_model.config import write_arm_file
    truth = _different(paper_model.config)
    path = str(tmp_path / "identified.yaml")
    write_arm_file(path, truth, header="identified from a test\nsecond line")
    text = open(path, encoding="utf-8").read()
    assert text.startswith("# identified from a test\n# second line\n/**:")
    back = load_arm_config(path)
    assert back.material == truth.material and back.discretisation == truth.discretisation
    for a, b in zip(back.tendons, truth.tendons):
        assert a.name == b.name and a.friction == b.friction and a.offset_fraction == b.offset_fraction
        assert a.start_angle == pytest.approx(b.start_angle, abs=1e-12)
        assert a.end_angle == pytest.approx(b.end_angle, abs=1e-12)
    assert load_setup("coiling", arm_file=path).arm == back
