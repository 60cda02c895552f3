"""The closed loop on the shape estimate (ROS-free harness), the estimate recorded against the
plant's truth. With markers seen (fused) the online CLIK closes its loop on it; with the mocap gone
from the start the tendon-only estimate is uncertain by centimetres, more than the error it shows,
and the CLIK holds the precomputed reference and says so, as it does on the mocap: on an arm whose
tendons run off their modelled paths, where that estimate is 20 mm off, stepping on it would end
three times further away. An estimate that leaves the arm is caught by the trust region, and the
reference returns to the precomputed one: closing the loop on the estimate never ends worse than
holding it."""
from dataclasses import replace

import numpy as np
import pytest

from conftest import CHI2_3_99, nees_bounded, nees_not_overconfident
from soft_arm_control.estimators import shape_estimator
from soft_arm_experiments import harness
from soft_arm_experiments.harness import load_setup, precompute_targets, run_experiment

ONE_TARGET = ["tasks.coiling.phases=[upward]", "tasks.coiling.phase.upward.sequence=[3]",
              "tasks.coiling.phase.upward.window=8.0"]
HELD_MARGIN = 1e-3          # m: an estimate the trust region refused ends within the hold's error + this
MOCAP_LOST = ["plant.mocap.occlusion.blackout=[0.0, 1.0e6]"]
DYNAMIC = ["estimator.process_model=dynamic"]


@pytest.fixture(scope="module")
def runs():
    """The target without any marker on the mocap and on the estimate; and with the declared plant's
    occlusions on the fused feedback."""
    out = {fb: run_experiment(load_setup("coiling", overrides=ONE_TARGET + MOCAP_LOST, feedback=fb),
                              truth=True)
           for fb in ("mocap", "estimate")}
    out["fused"] = run_experiment(load_setup("coiling", overrides=ONE_TARGET, feedback="fused"), truth=True)
    return out


def tip_nees(result, scale: float = 1.0) -> np.ndarray:
    """The tip's normalised estimation error squared on each frame at rest (the true tip slower than
    5 mm/s: the static balance's domain) from the estimator's first second on, with the reported
    covariance times ``scale``."""
    rec = result.record.arrays()
    t, true = rec["t_mocap"], rec["markers_true"][:, -1]
    speed = np.linalg.norm(np.gradient(true, t, axis=0), axis=1)
    rest = (t >= 1.0) & (speed < 5e-3)
    error = (rec["markers_estimated"][:, -1] - true)[rest]
    return np.einsum("ki,kij,kj->k", error, np.linalg.inv(scale * rec["marker_covariance"][rest, -1]), error)


def test_with_the_markers_the_tips_reported_uncertainty_bounds_its_error(runs):
    """Fused with the markers the cameras still see, at rest over a closed-loop run: the tip's mean
    NEES within the chi-square 1-99 % interval of one sample (3 for an exact covariance; a bound,
    not a test of honesty: conftest.nees_bounded), few frames
    beyond the 99 % bound; the same test refuses the covariance reported 100 times too small or
    too large."""
    nees = tip_nees(runs["fused"])
    assert nees.size > 50 and nees_bounded(nees), (nees.mean(), np.mean(nees > CHI2_3_99))
    assert not nees_bounded(tip_nees(runs["fused"], 0.01))
    assert not nees_bounded(tip_nees(runs["fused"], 100.0))


def test_on_the_tendons_alone_the_tips_reported_uncertainty_bounds_its_error(runs):
    """Without a marker the reported uncertainty is an upper bound, never an understatement: the
    NEES at rest is not above its chi-square bound (it is far below: docs/concepts/sensing.md,
    consistency); the covariance reported 1000 times too small would be."""
    nees = tip_nees(runs["estimate"])
    assert nees.size > 50 and nees_not_overconfident(nees), (nees.mean(), np.mean(nees > CHI2_3_99))
    assert not nees_not_overconfident(tip_nees(runs["estimate"], 1e-3))


def test_without_the_mocap_the_uncertain_estimate_holds_the_reference_and_says_so(runs):
    mocap, estimate = runs["mocap"], runs["estimate"]
    assert mocap.goals[0]["status"] == "unseen" and mocap.goals[0]["online_steps"] == 0
    goal = estimate.goals[0]
    assert goal["uncertain_frames"] > 500 and goal["online_steps"] == 0 and goal["unseen_frames"] == 0
    assert goal["status"] == "uncertain" and goal["fraction"] == 0.0, goal
    assert "within what the estimate's own uncertainty explains" in harness.goal_warning(goal)
    # the estimate's error at the end: what it showed was within its 2 sigma, and the reference held
    rec = estimate.record.arrays()
    sigma = np.sqrt(np.diagonal(rec["marker_covariance"][-1, -1])[[0, 2]])
    assert goal["error"] < 2.0 * np.sum(sigma), (goal["error"], sigma)
    assert abs(estimate.metrics[0].final_error - mocap.metrics[0].final_error) < 0.2e-3
    assert not rec["markers_seen"].any()
    error = np.linalg.norm(rec["markers_estimated"][-1] - rec["markers_true"][-1], axis=1)
    assert error[-1] < 3e-3


def test_on_the_dynamic_estimate_the_blind_loop_steps_on_what_its_uncertainty_defends(runs):
    """The dynamic estimate (``estimator.process_model: dynamic``) is sure to a few millimetres on
    the tendons alone: the CLIK steps on the part of the error its uncertainty cannot explain and
    ends nearer than holding the precomputed reference (5.38 against 8.22 mm on this target; the
    uncertainty includes the second opinion's gap at rest, so the loop takes less of the error than
    the filter's covariance alone would let it), then holds once what is left is within that
    uncertainty, and says so."""
    estimate = run_experiment(load_setup("coiling", overrides=ONE_TARGET + MOCAP_LOST + DYNAMIC,
                                         feedback="estimate"), truth=True)
    goal = estimate.goals[0]
    assert goal["online_steps"] > 0 and goal["status"] == "uncertain", goal
    assert estimate.metrics[0].final_error < runs["mocap"].metrics[0].final_error - 0.2e-3


def test_with_markers_seen_the_fused_estimate_is_sure_and_closes_the_loop(runs):
    """The tip seen (a measurement) or estimated from the markers seen: the steps take all of the
    error but while the tip is hidden after the switch; the arm ends within 1.5 mm."""
    goal, row = runs["fused"].goals[0], runs["fused"].metrics[0]
    frames = goal["online_steps"] + goal["uncertain_frames"]
    assert goal["fraction"] == 1.0 and goal["uncertain_frames"] < 0.25 * frames, goal
    assert row.final_error < 1.5e-3


def test_the_measured_metrics_of_a_run_the_mocap_never_saw_are_an_error():
    short = ["tasks.coiling.phase.upward.window=3.0"]
    setup = load_setup("coiling", overrides=ONE_TARGET + MOCAP_LOST + short)
    with pytest.raises(ValueError, match="frames saw the task's markers"):
        run_experiment(setup)


def blind_outcome_is_safe(blind, held) -> bool:
    """The blind run reached its target (1.5 mm), or it held its reference and says so (the trust
    region returned it to the precomputed one, or the estimate was too uncertain to step on),
    ending no more than HELD_MARGIN worse than holding it (``held``: the same target on the mocap
    without a marker: the precomputed reference, no step)."""
    goal = blind.goals[0]
    if blind.metrics[0].final_error <= 1.5e-3:
        return True
    said = goal["distrusts"] > 0 or goal["status"] == "uncertain"
    return said and blind.metrics[0].final_error <= held.metrics[0].final_error + HELD_MARGIN


@pytest.mark.parametrize("target", [1, 2])
def test_blind_coiling_reaches_its_target_or_holds_the_precomputed_reference(target, runs):
    one = ONE_TARGET[:1] + [f"tasks.coiling.phase.upward.sequence=[{target}]"] + ONE_TARGET[2:]
    blind, held = (run_experiment(load_setup("coiling", overrides=one + MOCAP_LOST, feedback=fb), truth=True)
                   for fb in ("estimate", "mocap"))
    assert blind_outcome_is_safe(blind, held), (blind.metrics[0].final_error, blind.goals[0])
    assert blind.goals[0]["status"] != "constrained"


def test_blind_coiling_on_target_3_reaches_it_or_holds_the_precomputed_reference(runs):
    assert blind_outcome_is_safe(runs["estimate"], runs["mocap"]), runs["estimate"].goals[0]


# a softer arm whose tendons run off their modelled paths: its tendon-only estimate is 20 mm off at
# rest, the precomputed reference 6.7 mm (stepped on, the estimate ended 18 mm away)
OFF_PATH = ["plant.youngs_modulus_scale=0.9", "plant.viscosity_scale=1.2",
            "plant.tendon.offset_fraction=[0.58,0.62,0.6,0.61]",
            "plant.tendon.start_angle_error=[0.03,-0.03,0.02,-0.02]"]


def test_on_an_arm_whose_tendons_run_off_their_paths_the_blind_loop_ends_no_worse_than_holding():
    blind, held = (run_experiment(load_setup("coiling", overrides=ONE_TARGET + MOCAP_LOST + OFF_PATH,
                                             feedback=fb), truth=True) for fb in ("estimate", "mocap"))
    assert blind_outcome_is_safe(blind, held), (blind.metrics[0].final_error, held.metrics[0].final_error,
                                                blind.goals[0])


class WalkingEstimate:
    """The configured estimator, with a bias on every marker growing at ``RATE`` along arm_base x
    from ``START`` [s] on: an estimate that walks away from the arm."""
    START, RATE = 7.0, np.array([0.005, 0.0, 0.0])

    def __init__(self, *args):
        self.inner = shape_estimator(*args)

    def __getattr__(self, name):
        return getattr(self.inner, name)

    def estimate(self):
        out = self.inner.estimate()
        return replace(out, markers=out.markers + self.RATE * max(0.0, out.t - self.START))


@pytest.fixture(scope="module")
def walking(runs):
    """Target 3 without a marker on the walking estimate, with the trust region and without; the
    walk starts when the online CLIK has brought the arm to rest (its swing below 0.3 mm)."""
    longer = ["tasks.coiling.phase.upward.window=10.0"]
    patch = pytest.MonkeyPatch()
    patch.setattr(harness, "shape_estimator", WalkingEstimate)
    try:
        return {on: run_experiment(load_setup("coiling", overrides=ONE_TARGET + MOCAP_LOST + longer + [
            f"control.clik.trust.enabled={str(on).lower()}"], feedback="estimate"), truth=True)
            for on in (True, False)}
    finally:
        patch.undo()


def test_an_estimate_walking_away_is_refused_within_half_a_second_and_the_precomputed_reference_holds(
        walking, runs):
    guarded = walking[True]
    goal = guarded.goals[0]
    assert goal["status"] == "untrusted" and goal["distrusts"] == 1, goal
    assert WalkingEstimate.START < goal["distrust_time"] <= WalkingEstimate.START + 0.5, goal
    assert "a bias" in goal["distrust"], goal["distrust"]
    setup = load_setup("coiling", overrides=ONE_TARGET, feedback="estimate")
    precomputed = precompute_targets(harness.outer_loop_for(harness.build_model(setup.arm), setup.control,
                                                            setup.task), setup.control, setup.task)[2]
    np.testing.assert_array_equal(guarded.stored[2].q, precomputed.q)
    assert guarded.metrics[0].final_error <= runs["mocap"].metrics[0].final_error + HELD_MARGIN


def test_without_the_trust_region_the_walking_estimate_drags_the_arm_away(walking):
    """Followed, the estimate's 15 mm walk takes the arm with it: at the end the tip is more than a
    third of the walk from where the guarded loop holds it."""
    unguarded = walking[False]
    assert unguarded.goals[0]["distrusts"] == 0
    tips = [walking[on].record.arrays()["tip_true"][-1] for on in (True, False)]
    walk = np.linalg.norm(WalkingEstimate.RATE) * (10.0 - WalkingEstimate.START)
    assert np.linalg.norm(tips[1] - tips[0]) > walk / 3, (np.linalg.norm(tips[1] - tips[0]), walk)


@pytest.fixture(scope="module")
def blind_triangle():
    """The triangle's three vertices from the hanging arm (its approach phase), every marker hidden:
    on the tendon-only estimate, and on the mocap (which holds the precomputed references)."""
    approach = ["tasks.triangle.phases=[approach]"]
    return {fb: run_experiment(load_setup("triangle", overrides=approach + MOCAP_LOST, feedback=fb),
                               truth=True) for fb in ("estimate", "mocap")}


def test_the_blind_triangle_reaches_every_vertex_or_holds_its_precomputed_reference(blind_triangle):
    blind, held = blind_triangle["estimate"], blind_triangle["mocap"]
    for k, (row, goal, hold) in enumerate(zip(blind.metrics, blind.goals, held.metrics)):
        said = goal["distrusts"] > 0 or goal["status"] == "uncertain"
        held_safely = said and row.final_error <= hold.final_error + HELD_MARGIN
        safe = row.final_error <= 1.5e-3 or held_safely
        assert safe and goal["status"] != "constrained", (k + 1, row.final_error, goal)
