"""The strike planner: a tension profile within the limits that brings the task point to the target
at the planned time, found faster than the step; the outer loop hands it to the inner loop."""
import os
from dataclasses import replace

import numpy as np
import pytest

from soft_arm_control.config import load_control_config, load_task_config
from soft_arm_control.outer_loop import outer_loop_for
from soft_arm_control.strike_planner import FIT_STEP, StrikeShooter, fit_levels, plan_strike_move
from soft_arm_model import ImexStepper, build_model, load_arm_config, solve_equilibrium
from soft_arm_model.parameters import default_config_dir


@pytest.fixture(scope="module")
def strike():
    """The pendulum task's model, controller, outer loop and precomputed strike target."""
    d = default_config_dir()
    arm = load_arm_config(os.path.join(d, "arm.yaml"))
    control = load_control_config(arm, os.path.join(d, "control.yaml"))
    task = load_task_config("pendulum", arm, os.path.join(d, "tasks.yaml"))
    model = build_model(arm)
    outer = outer_loop_for(model, control, task)
    goal = outer.precompute(np.array(task.targets[0]))
    return model, control, task, outer, goal


@pytest.fixture(scope="module")
def planned(strike):
    model, control, task, _, goal = strike
    return plan_strike_move(model, control, task.space, task.tendons, goal, goal.x)


def _replay(model, control, task, tensions, dt):
    """The task coordinates after the tensions (one row per step) applied to the hanging arm,
    stepped here (ImexStepper.step and the model's kinematics), not by the planner's shooter: the
    recorded tensions and the miss the plan reports, checked."""
    stepper = ImexStepper(model, dt, rotor_mass=np.full(model.n_tendons, control.rotor_mass))
    q, qd = solve_equilibrium(model, np.full(model.n_tendons, control.tension_min)).q, np.zeros(model.n)
    for u in tensions[:-1]:
        q, qd = stepper.step(q, qd, u)
    return task.space.evaluate(model, q)[0]


def test_the_plan_reaches_the_target_at_its_duration_within_the_limits_faster_than_the_step(strike, planned):
    """Replayed independently, the planned tensions put the task point within 1 mm of the target at
    the plan's duration; every tension is inside the limits; the plan is shorter than the time the
    precomputed step needs to bring the arm within 1 cm (the arm moving at speed there); its
    recorded shortenings are the model's at the end."""
    model, control, task, _, goal = strike
    p = planned
    assert np.all(p.tensions >= control.tension_min - 1e-12)
    assert np.all(p.tensions <= control.tension_max + 1e-12)
    x = _replay(model, control, task, p.tensions, p.sample_times[1] - p.sample_times[0])
    assert np.linalg.norm(x - goal.x) <= 1e-3
    assert p.miss == pytest.approx(np.linalg.norm(x - goal.x), abs=1e-6)
    assert p.arrival_speed > 0.2                      # a strike: it passes through, moving
    # the step: the precomputed tensions at once, on the same model
    step = np.tile(np.asarray(goal.u_ff), (int(0.6 / 1e-3), 1))
    arrivals = []
    stepper = ImexStepper(model, 1e-3, rotor_mass=np.full(model.n_tendons, control.rotor_mass))
    q, qd = solve_equilibrium(model, np.full(model.n_tendons, control.tension_min)).q, np.zeros(model.n)
    for k, u in enumerate(step):
        q, qd = stepper.step(q, qd, u)
        if k % 10 == 0:
            arrivals.append(np.linalg.norm(task.space.evaluate(model, q)[0] - goal.x) < 0.01)
    step_time = (int(np.argmax(arrivals)) * 10 + 1) * 1e-3 if any(arrivals) else np.inf
    assert p.duration < step_time


def test_the_reference_is_the_plans_sample_at_or_before_the_time(planned):
    p = planned
    k = 37
    s, sd, u = p.reference(p.sample_times[k] + 0.4 * (p.sample_times[1] - p.sample_times[0]))
    assert np.array_equal(s, p.shortening[k]) and np.array_equal(sd, p.shortening_rate[k])
    assert np.array_equal(u, p.tensions[k])
    assert np.array_equal(p.reference(-1.0)[0], p.shortening[0])
    assert np.array_equal(p.reference(10.0)[2], p.tensions[-1])
    # the rates are the shortenings' own: finite differences of the recorded samples
    dt = p.sample_times[1] - p.sample_times[0]
    fd = (p.shortening[k + 1] - p.shortening[k - 1]) / (2 * dt)
    assert np.allclose(fd, p.shortening_rate[k], atol=0.02 * np.abs(p.shortening_rate[k]).max())


def test_a_rate_limit_bounds_every_change_of_the_profile(strike):
    """With control.inner_loop.tension_rate_limit on, a step of the levels becomes a ramp at the
    limit, no tension changes faster, and the plan fitted through it still reaches the target."""
    model, control, task, _, goal = strike
    limited = replace(control, tension_rate_limit=20.0)
    shooter = StrikeShooter(model, task.space, task.tendons, control.tension_min, control.rotor_mass,
                            1e-3, limited.tension_rate_limit)
    levels = np.array([[5.0, 0.05, 5.0, 0.05], [0.05, 5.0, 0.05, 5.0]])
    u = shooter.commands(levels, np.asarray(goal.u_ff), 0.3)
    assert np.abs(np.diff(u, axis=0)).max() <= 20.0 * 1e-3 + 1e-12
    assert u[1, 0] - u[0, 0] == pytest.approx(20.0 * 1e-3)       # the 5 N level: ramped at the limit
    assert u[100, 0] == pytest.approx(control.tension_min + 101 * 20.0 * 1e-3)   # from the first step
    free = StrikeShooter(model, task.space, task.tendons, control.tension_min, control.rotor_mass, 1e-3)
    v = free.commands(levels, np.asarray(goal.u_ff), 0.3)
    assert np.array_equal(v[1], levels[0]) and np.array_equal(v[-1], np.asarray(goal.u_ff))
    plan = plan_strike_move(model, limited, task.space, task.tendons, goal, goal.x, bisections=1)
    assert np.abs(np.diff(plan.tensions, axis=0)).max() <= 20.0 * 1e-3 + 1e-12
    assert plan.miss <= 1e-3


def test_the_fit_ends_at_the_first_levels_within_enough(strike):
    """Every simulation the fit runs before its last misses by more than ``enough``; its last one
    is within it, and the fit returns those levels (with ``enough`` 0 it goes on past them)."""
    model, control, task, _, goal = strike
    shooter = StrikeShooter(model, task.space, task.tendons, control.tension_min, control.rotor_mass,
                            FIT_STEP)
    misses, run = [], shooter.run

    def counted(levels, hold, duration, record=False):
        out = run(levels, hold, duration, record)
        misses.append((np.linalg.norm(out[0] - goal.x), levels.copy()))
        return out
    shooter.run = counted
    hold = np.asarray(goal.u_ff)
    guess = np.tile(hold, (3, 1))
    levels, miss = fit_levels(shooter, goal.x, hold, 0.3, guess, (control.tension_min, control.tension_max),
                              enough=1e-3)
    assert miss <= 1e-3 and miss == pytest.approx(misses[-1][0], abs=1e-12)
    assert np.array_equal(levels, misses[-1][1])
    assert all(m > 1e-3 for m, _ in misses[:-1])
    stopped = len(misses)
    misses.clear()
    _, exact = fit_levels(shooter, goal.x, hold, 0.3, guess, (control.tension_min, control.tension_max))
    assert exact < miss and len(misses) > stopped


def test_a_run_without_its_record_ends_where_the_recorded_run_ends(strike):
    """The fit's runs (one compiled loop, the end read once) end where the recorded runs (stepped
    one at a time from Python, every sample read) end, to rounding (the same kernels: bit for bit
    where the compiler inlines them alike), with and without a rate limit; a run that leaves the
    model's domain is NaN in both."""
    model, control, task, _, goal = strike
    hold = np.asarray(goal.u_ff)
    for limit in (0.0, 20.0):
        shooter = StrikeShooter(model, task.space, task.tendons, control.tension_min, control.rotor_mass,
                                FIT_STEP, limit)
        for level in (0.5, 2.0, 5.0):
            levels = np.array([[level, 0.05, level, 0.05], [0.05, level, 0.05, level]])
            x, speed, samples = shooter.run(levels, hold, 0.3)
            x_rec, speed_rec, recorded = shooter.run(levels, hold, 0.3, record=True)
            assert samples is None
            assert np.allclose(x, x_rec, rtol=0, atol=1e-12) and speed == pytest.approx(speed_rec, rel=1e-9)
            assert np.all(np.isfinite(x)) and recorded[2].shape == (recorded[0].size, model.n_tendons)
    free = StrikeShooter(model, task.space, task.tendons, control.tension_min, control.rotor_mass, FIT_STEP)
    away = np.full((2, 4), 1000.0)                      # a kN on every tendon: out of the domain
    for record in (False, True):
        x, speed, samples = free.run(away, hold, 0.3, record=record)
        assert np.all(np.isnan(x)) and np.isnan(speed) and samples is None


def _recorded_off_by(monkeypatch, offset, below: float):
    """The planner's recorded runs (``record=True``) shifted by ``offset`` [m] on every task
    coordinate when shorter than ``below`` [s]: a finer step that moves the arm's end point
    (``offset`` None: those runs leave the model's domain, as the shooter reports it)."""
    import soft_arm_control.strike_planner as planner

    class Shifted(StrikeShooter):
        def run(self, levels, hold, duration, record=False):
            x, speed, samples = super().run(levels, hold, duration, record)
            if not (record and duration < below):
                return x, speed, samples
            if offset is None:
                return np.full_like(x, np.nan), np.nan, None
            return x + offset, speed, samples
    monkeypatch.setattr(planner, "StrikeShooter", Shifted)


def test_a_recorded_plan_that_misses_gives_way_to_the_next_longer_duration(strike, monkeypatch):
    """The bisection finds 0.3 s and 0.5 s within the tolerance; recorded, 0.3 s misses by 20 mm (10
    mm on each of the four task coordinates), so the plan is the 0.5 s one, within it. Missing at
    every duration, or leaving the model's domain, the plan is refused with each miss."""
    model, control, task, _, goal = strike
    _recorded_off_by(monkeypatch, 0.01, 0.45)
    plan = plan_strike_move(model, control, task.space, task.tendons, goal, goal.x, bisections=1)
    assert plan.duration == pytest.approx(0.5) and plan.miss <= 1e-3
    _recorded_off_by(monkeypatch, 0.01, 1.0)
    with pytest.raises(ValueError, match=r"at every duration the fit found: (19|20)\.\d mm in 0.300 s, "
                                         r"(19|20)\.\d mm in 0.500 s"):
        plan_strike_move(model, control, task.space, task.tendons, goal, goal.x, bisections=1)
    _recorded_off_by(monkeypatch, None, 1.0)                 # every recorded run out of the domain
    with pytest.raises(ValueError, match="out of the model's domain in 0.300 s, out of the model's "
                                         "domain in 0.500 s"):
        plan_strike_move(model, control, task.space, task.tendons, goal, goal.x, bisections=1)


def test_a_target_out_of_reach_in_the_time_allowed_is_refused(strike):
    model, control, task, _, goal = strike
    with pytest.raises(ValueError, match="brings the task point to the target in 0.05 s: the closest misses"):
        plan_strike_move(model, control, task.space, task.tendons, goal, goal.x, min_duration=0.02,
                         max_duration=0.05)


def test_the_outer_loop_hands_the_plan_to_the_inner_loop_then_holds_the_target(strike, planned):
    """A precomputed goal with a planned move: the command is the plan's sample half a CLIK period
    ahead, with its rates, at every frame until the move's duration, then the precomputed reference
    with no rate; only a precomputed goal takes a move."""
    model, control, task, _, goal = strike
    outer = outer_loop_for(model, control, task)
    first = outer.goal(1.0, goal.x, "precomputed", goal, move=planned)
    half = 0.5 * outer.period
    assert np.array_equal(first.shortening, planned.reference(half)[0])
    t = 1.0 + 0.1
    ref = outer.frame(t, goal.x)
    s, sd, u = planned.reference(0.1 + half)
    assert np.array_equal(ref.shortening, s) and np.array_equal(outer.reference_rate, sd)
    assert np.array_equal(ref.u_ff, u[list(outer.clik.cm.active)]) and np.array_equal(ref.q, goal.q)
    assert np.abs(sd).max() > 0.01
    done = outer.frame(1.0 + planned.duration + 1e-3, goal.x)
    assert done is goal and not np.any(outer.reference_rate)
    assert outer.frame(1.0 + planned.duration + 0.1, goal.x) is None        # the step is held
    with pytest.raises(ValueError, match="only a precomputed goal takes a planned move"):
        outer.goal(3.0, goal.x, "clik", goal, move=planned)
