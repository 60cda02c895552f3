"""Targets with margin: tensions and stability of a target on arms that are not the model."""
import json
from dataclasses import replace

import numpy as np
import pytest

from soft_arm_control.clik import TargetError
from soft_arm_control.config import load_control_config, load_task_config
from soft_arm_control.input_shaping import step_modes
from soft_arm_control.outer_loop import outer_loop_for
from soft_arm_control.target_margin import (SAFE_MARGIN, MarginChecker, Variant, check_arm, is_robust,
                                            safe_point, target_frequency, target_point)
from soft_arm_control.targets_cli import main as targets_main
from soft_arm_model import ImexStepper, build_model, load_arm_config, marker_positions, solve_equilibrium
from soft_arm_control.collocated import full_tensions

COILING_LOW = (-0.0085, -0.3301)      # a default coiling target
COILING_CURL = (-0.0013, -0.2275)     # a curl that a loaded arm cannot hold


def _setup(arm_overrides=None, control_overrides=None):
    arm = load_arm_config(overrides=arm_overrides or {})
    return arm, load_control_config(arm, overrides=control_overrides or {}), load_task_config("coiling", arm)


def test_a_variant_scales_the_modulus_and_adds_the_tip_mass():
    arm = load_arm_config()
    v = Variant(0.8, 0.003).arm(arm)
    assert v.material.youngs_modulus == pytest.approx(0.8 * arm.material.youngs_modulus)
    assert v.tip_mass == pytest.approx(arm.tip_mass + 0.003)
    assert v.tendons == arm.tendons and v.discretisation == arm.discretisation


def test_weightless_arm_needs_tensions_in_proportion_to_its_modulus():
    """Without gravity the shape depends on u / E only: an arm 25 % stiffer holds the same target with
    exactly 25 % more tension (friction included), a softer one with less; a tip mass weighs
    nothing. The model itself is the identity variant. (The other tendons hang slack: a held
    pretension would not scale.)"""
    arm, control, task = _setup({"gravity": [0.0, 0.0, 0.0]}, {"tension_min": 0.0})
    checker = MarginChecker(arm, control, task, [Variant(1.0, 0.0), Variant(1.25, 0.0), Variant(0.8, 0.004)])
    cm = checker.nominal.clik.cm
    q = solve_equilibrium(cm.model, full_tensions(cm, [1.0, 1.5])).q
    x = checker.nominal.clik.task.evaluate(cm.model, q)[0]
    model_u = checker.nominal.precompute(x).u_ff
    np.testing.assert_allclose(model_u, [1.0, 1.5], rtol=1e-4)
    same, stiffer, softer = checker.check(x)
    np.testing.assert_allclose(same.tensions, model_u, rtol=1e-4)
    np.testing.assert_allclose(stiffer.tensions, 1.25 * model_u, rtol=1e-4)
    np.testing.assert_allclose(softer.tensions, 0.8 * model_u, rtol=1e-4)
    u = stiffer.tensions
    assert stiffer.margin == pytest.approx(min(u.min() - control.tension_min, control.tension_max - u.max()))
    assert all(r.stable for r in (same, stiffer, softer))


def test_a_target_out_of_the_model_limits_is_reported_by_the_cli(capsys):
    assert targets_main(["coiling", "--target", "0.1", "-0.1", "--json"]) == 1
    out = json.loads(capsys.readouterr().out)
    assert out["targets"][0]["robust"] is False and "the model itself" in out["targets"][0]["reason"]


@pytest.mark.parametrize("argv, fragment", [
    (["coiling", "--target", "0.01", "-0.3", "0.1"], "has 2 coordinates"),
    (["coiling", "--stiffness", "0"], "--stiffness"),
    (["coiling", "--set", "control.tension_max=-1"], "control.tension_max"),
    (["square"], "unknown task"),
])
def test_bad_input_exits_2_naming_it(capsys, argv, fragment):
    assert targets_main(argv) == 2
    assert fragment in capsys.readouterr().err


def test_the_default_coiling_targets_follow_the_rule(capsys):
    """The rule the README documents: every arm with E x0.8-1.25 and 0-2 g at its tip holds each
    default coiling target stably with 0.1 N of margin (exit status 0)."""
    assert targets_main(["coiling", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert len(out["targets"]) == 4 and all(t["robust"] for t in out["targets"])
    assert {(v["stiffness"], v["payload"]) for v in out["targets"][0]["variants"]} == {
        (s, p) for s in (0.8, 1.0, 1.25) for p in (0.0, 0.002)}
    assert min(t["worst_margin"] for t in out["targets"]) > 0.3


def test_stability_says_which_equilibria_the_arm_leaves():
    """Without the inner loop (K_p = 0) the stability is that of the arm under constant tensions. A
    curl with 5 g at the tip is unstable: released there with a 0.1 mm nudge under its equilibrium
    tensions, the arm buckles sideways by centimetres; the low target is stable and stays put."""
    arm, control, task = _setup(control_overrides={"inner_loop.proportional": [0.0] * 4})
    loaded = Variant(1.0, 0.005).arm(arm)
    results = check_arm(loaded, control, task, [COILING_LOW, COILING_CURL])
    assert results[0].stable and not results[1].stable
    checker = MarginChecker(loaded, control, task, variants=[])
    model = build_model(loaded)
    for target, result in zip((COILING_LOW, COILING_CURL), results):
        q0 = checker.nominal.precompute(np.array(target)).q
        tip0 = marker_positions(model, q0)[-1]
        u = full_tensions(checker.nominal.clik.cm, result.tensions)
        stepper = ImexStepper(model, 1e-3)
        q, qd = q0 + 1e-4 * np.ones(model.n) / np.sqrt(model.n), np.zeros(model.n)
        for _ in range(4000):
            stepper.prepare(q, qd)
            q, qd = stepper.advance(u)
        moved = np.linalg.norm(marker_positions(model, q)[-1] - tip0)
        assert (moved < 1e-3) if result.stable else (moved > 1e-2), (target, moved)


def test_check_arm_solves_on_the_arm_itself_whatever_its_basis():
    arm, control, task = _setup()
    finer = replace(arm, discretisation=replace(arm.discretisation, legendre_order=(5, 0)))
    results = check_arm(finer, control, task, [COILING_LOW])
    assert results[0].margin > 0.3 and results[0].stable and results[0].variant is None
    assert is_robust(results)


TRIANGLE_SIDE = (-0.03, 0.138, -0.241, 0.056)      # the default triangle's second vertex


def test_the_lowest_held_frequency_is_the_lowest_mode_and_its_sign_the_stability():
    """Without friction the held stiffness is symmetric: the frequency is the lowest mode of the
    generalised eigenproblem (input shaping's); with K_p = 0 its sign is the stability that the
    simulated release of test_stability_says_which_equilibria_the_arm_leaves confirms."""
    arm, control, task = _setup(control_overrides={"friction": False})
    outer = outer_loop_for(build_model(arm), control, task)
    point = outer.precompute(np.array(COILING_LOW))
    kp, kd = ([getattr(control, g)[k] for k in task.tendons] for g in ("proportional", "derivative"))
    modes = step_modes(outer.clik.cm, outer.clik.task, kp, kd, outer.start, point)
    assert target_frequency(outer, control, task, point) == pytest.approx(modes[0].frequency, rel=1e-6)
    arm, control, task = _setup(control_overrides={"inner_loop.proportional": [0.0] * 4})
    loaded = Variant(1.0, 0.005).arm(arm)
    outer = outer_loop_for(build_model(loaded), control, task)
    for target, stable in ((COILING_LOW, True), (COILING_CURL, False)):
        f = target_frequency(outer, control, task, outer.precompute(np.array(target)))
        assert (f > 0) == stable, (target, f)


def test_a_target_near_a_fold_is_refused_and_the_safe_point_offered_can_be_held():
    """With 3.5 g at the tip the triangle's second vertex sits near a fold of the model's
    equilibria (0.44 Hz held by the inner loop, tip mass 2 g: 0.84 Hz, none: 1.25 Hz). It is
    refused, naming the frequency; the point offered instead is held above min_frequency within
    the tension limits, and is where the model's equilibrium under its tensions is."""
    arm = load_arm_config(overrides={"tip_mass": 0.0035})
    control, task = load_control_config(arm), load_task_config("triangle", arm)
    outer = outer_loop_for(build_model(arm), control, task)
    fragile = r"fragile: .*near a fold .*0\.4\d Hz.*min_frequency 0\.8 Hz"
    with pytest.raises(TargetError, match=fragile) as info:
        target_point(outer, control, task, np.array(TRIANGLE_SIDE))
    safe = info.value.closest
    assert safe is not None
    assert target_frequency(outer, control, task, safe) >= control.min_frequency
    assert np.all(safe.u_ff >= control.tension_min) and np.all(safe.u_ff <= control.tension_max)
    cm = outer.clik.cm
    eq = solve_equilibrium(cm.model, full_tensions(cm, safe.u_ff), q_start=safe.q, friction=cm.friction)
    assert np.allclose(outer.clik.task.evaluate(cm.model, eq.q)[0], safe.x, atol=1e-6)
    assert np.allclose(target_point(outer, control, task, safe.x).q, safe.q)    # offered as it runs
    # it is the closest safe point: nearer the vertex than the last safe point on the straight
    # tension path from the hanging arm (29 mm), on the threshold (SAFE_MARGIN above it)
    on_path = safe_point(outer, control, task, outer.precompute(np.array(TRIANGLE_SIDE)))
    assert np.linalg.norm(safe.x - TRIANGLE_SIDE) < 0.5 * np.linalg.norm(on_path.x - TRIANGLE_SIDE)
    assert target_frequency(outer, control, task, safe) == pytest.approx(control.min_frequency + SAFE_MARGIN,
                                                                         abs=5e-3)
    off = replace(control, min_frequency=0.0)
    assert target_point(outer, off, task, np.array(TRIANGLE_SIDE)).x == pytest.approx(TRIANGLE_SIDE, abs=1e-5)


@pytest.mark.parametrize("task_name", ["triangle", "coiling"])
def test_the_default_targets_are_not_fragile_on_the_nominal_arm(task_name):
    arm = load_arm_config()
    control, task = load_control_config(arm), load_task_config(task_name, arm)
    outer = outer_loop_for(build_model(arm), control, task)
    for x in task.targets:
        point = target_point(outer, control, task, np.array(x))
        assert target_frequency(outer, control, task, point) > control.min_frequency + 0.3   # Hz
