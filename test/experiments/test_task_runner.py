"""The task runner's core, ROS-free: goals at the window starts, the strike's timing (a deferred
first goal, the release time) and the strike measured from the ball's and the arm's frames."""
import numpy as np
import pytest

from soft_arm_experiments.harness import load_setup
from soft_arm_experiments.strike import StrikePlan, free_swing, strike_plan_for
from soft_arm_experiments.task_runner import RELEASE_LEAD, TaskRunner

FRAME = 1 / 240


def plan(send=0.0, release=0.0):
    return StrikePlan(send, release, 0.3, 0.0, 0.315, "rehearsed")


def test_goals_go_out_at_the_window_starts_and_a_plan_needs_a_pendulum():
    task = load_setup("coiling").task
    runner = TaskRunner(task, 3)
    first = runner.frame(10.0, np.zeros((4, 3)))
    phase = task.phases[0]
    assert first is not None and np.allclose(first.target, task.targets[phase.sequence[0]])
    assert (first.mode, first.phase, first.window) == (phase.mode, phase.name, phase.window)
    assert runner.frame(10.0 + FRAME, np.zeros((4, 3))) is None
    assert runner.release_at is None and runner.strike() is None
    with pytest.raises(ValueError, match="strike plan"):
        TaskRunner(task, 3, plan())
    with pytest.raises(ValueError, match="strike plan"):
        TaskRunner(load_setup("pendulum").task, 3)
    planned = load_setup("pendulum", overrides=["tasks.pendulum.pendulum.timing=planned"])
    with pytest.raises(ValueError, match="the graph does not run a planned strike"):
        strike_plan_for(planned.arm, planned.control, planned.task)


def test_the_strike_goal_waits_for_its_send_delay_and_the_release_is_timed():
    """The task starts RELEASE_LEAD after the first frame (the release, sent then, is ahead of its
    time even at the start); the goal goes out send_delay after the start."""
    setup = load_setup("pendulum")
    runner = TaskRunner(setup.task, 3, plan(send=0.1), setup.arm)
    goals = {}
    for k in range(120):
        goal = runner.frame(5.0 + k * FRAME, np.zeros((4, 3)))
        if goal is not None:
            goals[k] = goal
    # the first frame 0.1 s after the start
    assert list(goals) == [int(np.ceil((RELEASE_LEAD + 0.1) / FRAME - 1e-6))]
    assert goals[list(goals)[0]].mode == "precomputed"
    assert runner.release_at == 5.0 + RELEASE_LEAD
    delayed = TaskRunner(setup.task, 3, plan(release=0.2), setup.arm)
    assert delayed.frame(5.0, np.zeros((4, 3))) is None
    assert delayed.frame(5.0 + RELEASE_LEAD, np.zeros((4, 3))) is not None
    assert delayed.release_at == pytest.approx(5.0 + RELEASE_LEAD + 0.2)


def _frames(runner, pendulum, markers, t0, n, hit_at=None):
    """Feed n frames of a still arm and a ball on its free swing from t0 (the release), knocked
    sideways by 2 cm from ``hit_at`` [s] on."""
    rel = np.arange(n) * FRAME
    ball = free_swing(pendulum, rel)
    runner.frame(t0 - RELEASE_LEAD, markers)          # the first frame: the task starts at t0
    if hit_at is not None:
        ball[rel > hit_at] += np.outer(np.minimum((rel[rel > hit_at] - hit_at) / 0.01, 1.0), [0, 0.02, 0])
    for t, b in zip(t0 + rel, ball):
        runner.frame(t, markers)
        runner.ball(t, b)


def test_the_strike_is_measured_from_the_frames_after_the_release():
    setup = load_setup("pendulum")
    pendulum = setup.task.pendulum
    # the arm hanging still along -z, the ball swinging in the plane y = 0.138 m: it passes the arm
    # where x = 0, at z = pivot_z - sqrt(L^2 - pivot_x^2), missing it by 0.138 m less both radii there
    markers = np.array([[0.0, 0.0, -X] for X in setup.arm.marker_positions])
    z = pendulum.pivot[2] - np.sqrt(pendulum.length ** 2 - pendulum.pivot[0] ** 2)
    g = setup.arm.geometry
    arm_radius = g.base_radius + (g.tip_radius - g.base_radius) * -z / g.length
    runner = TaskRunner(setup.task, 3, plan(), setup.arm)
    _frames(runner, pendulum, markers, 2.0, 120)
    missed = runner.strike()["measured"]
    assert not missed["struck"]
    assert missed["closest_approach"] == pytest.approx(pendulum.pivot[1] - arm_radius - pendulum.ball_radius,
                                                       abs=5e-4)
    # the same ball knocked off its swing at 0.25 s: struck then, within a frame
    runner = TaskRunner(setup.task, 3, plan(), setup.arm)
    _frames(runner, pendulum, markers, 2.0, 120, hit_at=0.25)
    struck = runner.strike()["measured"]
    assert struck["struck"] and abs(struck["impact_time"] - 0.25) <= FRAME
    assert struck["ball_speed_before"] == pytest.approx(np.linalg.norm(
        np.diff(free_swing(pendulum, [0.24, 0.25]), axis=0)) / 0.01, rel=0.05)
