"""Task trajectories: velocities are the derivatives of the positions, paths start and end at their
target, the circle's path speed; bad trajectories are refused."""
import numpy as np
import pytest

from soft_arm_control.trajectories import SHAPES, Trajectory

P0 = np.array([0.02, -0.3, 0.01])


@pytest.mark.parametrize("shape", SHAPES)
def test_the_velocity_and_the_acceleration_are_the_derivatives_of_the_position(shape):
    traj = Trajectory(shape, 0.01, 4.0, (2, 0))
    h = 1e-6
    for t in np.linspace(0.0, 4.0, 17):
        x, v = traj.at(P0, t)
        numeric = (traj.at(P0, t + h)[0] - traj.at(P0, t - h)[0]) / (2 * h)
        np.testing.assert_allclose(v, numeric, atol=1e-8)
        assert x[1] == P0[1] and v[1] == 0.0                 # the coordinate off the plane stays
        acc = traj.acceleration(len(P0), t)
        np.testing.assert_allclose(acc, (traj.at(P0, t + h)[1] - traj.at(P0, t - h)[1]) / (2 * h),
                                   atol=1e-7)
        assert acc[1] == 0.0


@pytest.mark.parametrize("shape", SHAPES)
def test_a_path_starts_and_ends_its_period_at_the_target(shape):
    traj = Trajectory(shape, 0.01, 4.0)
    for t in (0.0, 4.0, 8.0):
        np.testing.assert_allclose(traj.at(P0[:2], t)[0], P0[:2], atol=1e-12)


def test_path_sizes_and_speeds():
    circle = Trajectory("circle", 0.01, 5.0)
    assert circle.path_speed() == pytest.approx(2 * np.pi * 0.01 / 5.0, rel=1e-9)
    points = np.array([circle.at([0.0, 0.0], t)[0] for t in np.linspace(0, 5, 50)])
    np.testing.assert_allclose(np.linalg.norm(points - [-0.01, 0.0], axis=1), 0.01, atol=1e-12)
    line = Trajectory("line", 0.01, 5.0)
    assert line.path_speed() == pytest.approx(4 * 0.01 / 5.0, rel=1e-3)      # 4 a per period


@pytest.mark.parametrize("args", [("spiral", 0.01, 1.0), ("circle", 0.0, 1.0), ("circle", 0.01, -1.0),
                                  ("circle", 0.01, 1.0, (1, 1))])
def test_bad_trajectories_are_refused(args):
    with pytest.raises(ValueError):
        Trajectory(*args)
