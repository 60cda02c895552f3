"""The second-order Rosenbrock-W step (ROS2): its order, its limit, its stability at long steps."""
import numpy as np
import pytest

from soft_arm_model import (ArmData, ImexStepper, Ros2Stepper, evaluate, simulate, solve_equilibrium,
                            tip_frame)

ROTORS = np.array([0.6, 0.3, 0.6, 0.2])   # kg, unequal so that a tendon mixed up shows
TENSIONS = np.array([1.0, 0.0, 0.5, 0.0])  # N, a step from rest: bending and torsion
DURATION = 0.3                             # s
SAMPLE = 0.02                              # s between the tip samples compared


def _tips(model, stepper_class, h, f_ext):
    """Tip positions [m] every SAMPLE s of a tension step from rest, stepped at h [s]."""
    stepper = stepper_class(model, h, rotor_mass=ROTORS)
    q, qd = solve_equilibrium(model, np.zeros(4)).q, np.zeros(model.n)
    every = int(round(SAMPLE / h))
    tips = []
    for i in range(int(round(DURATION / h))):
        stepper.prepare(q, qd)
        q, qd = stepper.advance(TENSIONS, f_ext)
        if (i + 1) % every == 0:
            tips.append(tip_frame(model, q).p)
    return np.array(tips)


@pytest.fixture(scope="module")
def convergence(paper_model):
    """Largest tip error [m] over the run for ROS2 and the Euler step at 4, 2 and 1 ms, against the
    Euler step's Richardson limit (2 x(h/2) - x(h) at 0.0625 ms): the reference is the other scheme,
    so that ROS2 is checked against a limit it did not make. Friction on, rotors, and a constant
    external generalised force, a 5 g payload's weight at the start (both stages must hold it)."""
    m = paper_model
    data = ArmData(m)
    evaluate(m, data, solve_equilibrium(m, np.zeros(4)).q, markers=True)
    f_ext = 5e-3 * data.marker_J[-1][3:].T @ (data.marker_R[-1].T @ m.gravity)
    limit = 2.0 * _tips(m, ImexStepper, 6.25e-5, f_ext) - _tips(m, ImexStepper, 1.25e-4, f_ext)
    steps = (4e-3, 2e-3, 1e-3)
    return {name: np.array([np.linalg.norm(_tips(m, cls, h, f_ext) - limit, axis=1).max() for h in steps])
            for name, cls in (("ros2", Ros2Stepper), ("imex", ImexStepper))}


def test_ros2_converges_at_second_order_to_the_limit_the_euler_step_converges_to(convergence):
    ros2, imex = convergence["ros2"], convergence["imex"]
    assert np.all(imex[:-1] / imex[1:] > 1.7) and np.all(imex[:-1] / imex[1:] < 2.3)   # first order
    assert np.all(ros2[:-1] / ros2[1:] > 2.6), ros2                                    # second order
    assert ros2[0] < imex[2]          # ROS2 at 4 ms is closer than the Euler step at 1 ms
    assert ros2[2] < 0.05 * imex[2]   # and at the same step twenty times closer


def test_ros2_is_stable_at_long_steps_and_settles_on_the_static_equilibrium(paper_model):
    m = paper_model
    u = np.array([5.0, 0.0, 5.0, 0.0])
    q0 = solve_equilibrium(m, np.zeros(4)).q
    traj = simulate(m, q0, np.zeros(m.n), lambda t: u if t >= 0.1 else np.zeros(4), 8.0, dt=1e-2,
                    method="ros2")
    assert np.all(np.isfinite(traj.q))
    target = solve_equilibrium(m, u).q
    np.testing.assert_allclose(tip_frame(m, traj.q[-1]).p, tip_frame(m, target).p, atol=1e-5)


def test_an_unknown_method_is_refused(paper_model):
    with pytest.raises(ValueError, match="method must be one of"):
        simulate(paper_model, np.zeros(paper_model.n), np.zeros(paper_model.n), lambda t: np.zeros(4),
                 0.01, method="rk4")
