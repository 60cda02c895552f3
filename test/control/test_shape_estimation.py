"""The shape estimator against the simulated plant's truth: the tendons alone, fused with the markers
it sees, innovation gating, and the derivatives its updates use."""
from dataclasses import replace

import numpy as np
import pytest

from conftest import nees_bounded
from soft_arm_control.shape_estimation import (RESTART_AFTER, RESTART_NIS, STIFFNESS_BOUNDS, LostRule,
                                               ShapeEstimator, fused_markers, load_estimator_config)
from soft_arm_drivers.sim.plant_config import load_plant_config
from soft_arm_drivers.sim.simulated_rig import SimulatedRig
from soft_arm_model import (ArmData, build_model, evaluate, load_arm_config, marker_positions,
                            solve_equilibrium, static_residual, static_tangents, tendon_lengths)
from soft_arm_model.dynamics import STATICS
from soft_arm_model.parameters import ConfigError

NEUTRAL = {"youngs_modulus_scale": 1.0, "viscosity_scale": 1.0, "friction": "[0.1, 0.1, 0.1, 0.1]",
           "mocap.occlusion.enabled": False}
POSES = np.random.default_rng(0).uniform(0.2, 4.0, (10, 4))        # tensions [N]
PERIOD = 1 / 250                                                    # s between updates
CONFIG = load_estimator_config()


@pytest.fixture(scope="module")
def arm():
    return load_arm_config()


@pytest.fixture(scope="module")
def model(arm):
    return build_model(arm)


def _rig(arm, model, overrides=None):
    plant = load_plant_config(arm, overrides={"mocap.occlusion.enabled": False, **(overrides or {})})
    pre = np.full(4, 0.5)
    offset = model.rest_tendon_lengths - tendon_lengths(model, solve_equilibrium(model, pre).q)
    return SimulatedRig(build_model(plant.plant_arm(arm)), plant, offset, pre)


def _hold(rig, u):
    """The plant at rest under tensions u: (encoder shortenings, rates, true markers)."""
    rig.plant.settle(u)
    rig.tension = np.asarray(u, dtype=float)
    rig.plant.sense(markers=True)
    s, sd = rig.tendons()
    return s, sd, rig.plant.markers()[0]


class Clock:
    def __init__(self):
        self.t = 0.0

    def __call__(self):
        self.t += PERIOD
        return self.t


def _tip_errors(estimator, rig, poses, updates, clock, ends=None):
    """The tip's error [m] after ``updates`` updates at rest under each pose's tensions; with a list
    ``ends``, (the tip's error (3,) [m], its reported covariance (3, 3) [m^2]) of each appended."""
    errors = []
    for u in poses:
        s, sd, true = _hold(rig, u)
        for _ in range(updates):
            estimator.update(clock(), s, sd, u)
        estimate = estimator.estimate()
        errors.append(np.linalg.norm(estimate.markers[-1] - true[-1]))
        if ends is not None:
            ends.append((estimate.markers[-1] - true[-1], estimate.marker_covariance[-1]))
    return np.array(errors)


@pytest.fixture(scope="module")
def declared(arm, model):
    """The tendons alone on the declared plant: ten poses held for 100 updates (0.4 s) each, twice;
    of the second pass, the tip's error [m] at the end of each hold and (error, covariance) there."""
    rig = _rig(arm, model)
    estimator, clock = ShapeEstimator(model, CONFIG), Clock()
    _tip_errors(estimator, rig, POSES, 100, clock)
    ends = []
    errors = _tip_errors(estimator, rig, POSES, 100, clock, ends)
    return rig, estimator, errors, ends


def test_with_the_model_as_the_plant_the_tendons_alone_give_the_shape(arm, model):
    rig = _rig(arm, model, NEUTRAL)
    errors = _tip_errors(ShapeEstimator(model, CONFIG), rig, POSES[:4], 40, Clock())
    assert errors.max() < 3e-4, errors


def test_on_the_declared_plant_the_tendons_alone_put_the_tip_within_3_mm(model, declared):
    """The declared plant is 15 % stiffer with more friction: its equilibrium under the same
    tensions is centimetres from the model's. The shortenings and the estimated stiffness and
    friction bring the tip within 3 mm (median over ten poses, after one pass over them)."""
    rig, estimator, errors, _ = declared
    naive = [np.linalg.norm(marker_positions(model, solve_equilibrium(model, u).q)[-1]
                            - _hold(rig, u)[2][-1]) for u in POSES]
    assert np.median(errors) <= 3e-3 and errors.max() < 1e-2, errors
    assert np.median(naive) > 5 * np.median(errors)
    stiffness, friction = estimator.parameters
    assert 1.0 < stiffness < 1.3 and np.all((friction > 0.1) & (friction < 0.15))


def test_held_at_rest_the_tendons_alone_report_a_tip_uncertainty_that_bounds_the_error(declared):
    """At the end of each hold the tip's NEES (its error squared in units of the covariance it
    reports): the mean within the chi-square 1-99 % interval of one sample (3 for an exact
    covariance; a bound, not a test of honesty: conftest.nees_bounded), no pose beyond the 99 %
    bound (2 % of ten). The same test refuses the covariance reported 100 times too small or too
    large."""
    ends = declared[3]

    def nees(scale):
        return np.array([e @ np.linalg.solve(scale * P, e) for e, P in ends])
    assert nees_bounded(nees(1.0)), nees(1.0)
    assert not nees_bounded(nees(0.01)) and not nees_bounded(nees(100.0))


def test_with_the_markers_the_tip_stays_known_through_a_2_s_occlusion(arm, model):
    """Seen, the tip is known to the markers' noise; hidden for 2 s, the other markers and the
    tendons hold it within 2 mm, better than the tendons alone, and its error does not grow."""
    rig = _rig(arm, model)
    rng = np.random.default_rng(1)
    estimator, clock = ShapeEstimator(model, CONFIG), Clock()
    u = POSES[2]
    s, sd, true = _hold(rig, u)
    for _ in range(100):
        estimator.update(clock(), s, sd, u, true + rng.normal(0, 2e-4, true.shape))
    before = np.linalg.norm(estimator.estimate().markers[-1] - true[-1])
    during = []
    for _ in range(500):                               # 2 s without the tip marker
        seen = true + rng.normal(0, 2e-4, true.shape)
        seen[-1] = np.nan
        estimator.update(clock(), s, sd, u, seen)
        during.append(np.linalg.norm(estimator.estimate().markers[-1] - true[-1]))
    alone = _tip_errors(ShapeEstimator(model, CONFIG), rig, [u], 100, Clock())[0]
    during = np.array(during)
    assert before < 1e-3 and during.max() < 2e-3 and during.max() < alone, (before, during.max(), alone)
    assert during[250:].mean() < during[:250].mean() + 3e-4          # bounded: it does not grow


def test_one_marker_moved_5_cm_for_one_frame_is_gated_out(arm, model):
    rig = _rig(arm, model)
    estimator, clock = ShapeEstimator(model, CONFIG), Clock()
    u = POSES[4]
    s, sd, true = _hold(rig, u)
    for _ in range(50):
        estimator.update(clock(), s, sd, u, true)
    tip = estimator.estimate().markers[-1]
    outlier = true.copy()
    outlier[-1, 0] += 0.05
    report = estimator.update(clock(), s, sd, u, outlier)
    assert report.gated == [3] and report.used == [0, 1, 2] and report.marker_nis[3] > 100
    assert np.linalg.norm(estimator.estimate().markers[-1] - tip) < 3e-4
    report = estimator.update(clock(), s, sd, u, true)
    assert report.used == [0, 1, 2, 3]


def test_a_marker_that_stays_out_of_the_gate_is_taken_again_and_counted(arm, model):
    """The estimate had gone wrong (here: the mocap moved 2 cm for good): after ``regate`` frames
    the marker is believed again, and the estimate follows it."""
    rig = _rig(arm, model)
    config = replace(CONFIG, regate=10)
    estimator, clock = ShapeEstimator(model, config), Clock()
    u = POSES[4]
    s, sd, true = _hold(rig, u)
    for _ in range(50):
        estimator.update(clock(), s, sd, u, true)
    moved = true.copy()
    moved[-1, 1] += 0.02
    used = [3 in estimator.update(clock(), s, sd, u, moved).used for _ in range(40)]
    assert used[:9] == [False] * 9 and all(used[9:]) and estimator.counts["diverged"] == 1
    assert np.linalg.norm(estimator.estimate().markers[-1] - moved[-1]) < 2e-3


def test_tendons_that_contradict_the_estimate_at_rest_restart_it_and_the_parameters_come_back(arm, model):
    """Shortenings no arm can have under these tensions (15 cm more on every tendon, an encoder
    that lost its zero): the estimate cannot make them agree; it says so by restarting. Given
    consistent tendons afterwards (four poses held 0.4 s each), the stiffness and friction come
    back near the plant's (E x1.15, friction 0.12; here 1.13 and 0.109-0.112)."""
    rig = _rig(arm, model)
    estimator, clock = ShapeEstimator(model, CONFIG), Clock()
    s, sd, _ = _hold(rig, POSES[0])
    for _ in range(200):
        estimator.update(clock(), s + 0.15, sd, POSES[5])
    assert estimator.counts["restarts"] >= 1
    _tip_errors(estimator, rig, POSES[:4], 100, clock)
    stiffness, friction = estimator.parameters
    assert abs(stiffness - 1.15) < 0.05 and np.all(np.abs(friction - 0.12) < 0.02), (stiffness, friction)


def test_the_balance_derivatives_match_finite_differences(arm, model):
    """dR/dk = F_el, dR/dmu_i from the closed-form dA/dmu the estimator takes, dF_el/dq = K_t:
    against models with the stiffness and one tendon's friction changed, and a perturbed q."""
    u = POSES[1]
    q = solve_equilibrium(model, u).q
    d = evaluate(model, ArmData(model), q, level=STATICS)
    _, _, dA = static_tangents(model, q, u)
    for i in range(4):
        eps = 1e-4
        tendons = tuple(replace(t, friction=t.friction + (eps if k == i else 0.0))
                        for k, t in enumerate(arm.tendons))
        moved = build_model(replace(arm, tendons=tendons))
        fd = (static_residual(moved, q, u) - static_residual(model, q, u)) / eps
        np.testing.assert_allclose(dA[:, i] * u[i], fd, rtol=0.02, atol=1e-6 * np.abs(fd).max())
    h = 1e-6
    for b in range(0, model.n, 5):
        dq = np.zeros(model.n)
        dq[b] = h
        plus = evaluate(model, ArmData(model), q + dq, level=STATICS).Fel.copy()
        minus = evaluate(model, ArmData(model), q - dq, level=STATICS).Fel.copy()
        np.testing.assert_allclose(d.Kt[:, b], (plus - minus) / (2 * h), rtol=1e-4,
                                   atol=1e-6 * np.abs(d.Kt).max())


def test_fused_markers_take_the_mocap_where_it_saw_and_the_estimate_elsewhere():
    estimate = np.arange(12.0).reshape(4, 3)
    mocap = np.full((4, 3), np.nan)
    mocap[1] = [9.0, 9.0, 9.0]
    out = fused_markers(mocap, estimate)
    assert np.array_equal(out[1], [9.0, 9.0, 9.0]) and np.array_equal(out[[0, 2, 3]], estimate[[0, 2, 3]])
    assert np.array_equal(fused_markers(None, estimate), estimate)


def test_a_bad_estimator_value_names_the_key():
    with pytest.raises(ConfigError, match=r"estimator\.noise\.marker"):
        load_estimator_config(overrides={"noise.marker": 1.0})


def test_the_lost_rule_distrusts_says_why_and_restarts_after_a_run_of_bad_updates():
    """Both filters' rule: a pinned stiffness counts moving or not, a disagreement of the shortenings
    only where it counts, a left domain always; a good update ends the run; RESTART_AFTER in a row
    is lost."""
    rule, good = LostRule(), (1.0, 1.0, 4)
    rule.judge(STIFFNESS_BOUNDS[1], 0.0, 4, disagreement_counts=False)
    assert rule.bad == 1 and "stiffness 2.00" in rule.distrust
    rule.judge(*good, disagreement_counts=True)
    assert rule.bad == 0 and rule.distrust is None
    rule.judge(1.0, RESTART_NIS * 4 + 1.0, 4, disagreement_counts=False)
    assert rule.bad == 0 and "disagree" in rule.distrust          # said, not counted
    for k in range(RESTART_AFTER - 1):
        assert not rule.lost
        if k % 2:
            rule.judge(1.0, RESTART_NIS * 4 + 1.0, 4, disagreement_counts=True)
        else:
            rule.out_of_domain()
    assert not rule.lost
    rule.out_of_domain()
    assert rule.lost and "domain" in rule.distrust
    rule.restarted()
    assert not rule.lost and rule.distrust is None
