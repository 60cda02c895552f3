"""OuterLoop.target_at: the goal as asked (the clik node's ConfigurationReference.target), against
OuterLoop.path_at, the path the CLIK tracks (a track goal's trajectory plus the learned correction)."""
import numpy as np
import pytest

from soft_arm_control.clik import Clik, ClikGains
from soft_arm_control.collocated import build_collocated
from soft_arm_control.outer_loop import OuterLoop
from soft_arm_control.task_space import TaskSpace
from soft_arm_control.trajectories import Trajectory
from soft_arm_model import solve_equilibrium

COILING = TaskSpace((3, 3), (0, 2))
TARGET = np.array([0.0192, -0.3041])
CIRCLE = Trajectory("circle", 0.01, 2.0)
T0 = 1.5                       # s: when the track goal starts
TIMES = (T0, T0 + 0.3, T0 + 1.1, T0 + 2.7)


@pytest.fixture(scope="module")
def clik(paper_model):
    cm = build_collocated(paper_model, (2, 3), held_tension=0.05)
    return Clik(cm, COILING, ClikGains(5.0, 20.0), (0.05, 5.0))


def outer_loop(clik, paper_model, **options):
    start = clik.reference(solve_equilibrium(paper_model, np.full(4, 0.05)).q)
    return OuterLoop(clik, start, switch_delay=0.0, rate=50.0, **options)


def test_a_fixed_goal_s_target_is_itself_without_a_velocity(clik, paper_model):
    outer = outer_loop(clik, paper_model)
    outer.goal(0.0, TARGET, "online")
    for t in (0.0, 0.5, 7.0):
        x_d, velocity = outer.target_at(t)
        assert np.array_equal(x_d, TARGET) and velocity is None


@pytest.mark.parametrize("feedforward", [True, False])
def test_an_unlearned_track_goal_s_target_is_its_trajectory_point_and_the_path(
        clik, paper_model, feedforward):
    """Without a learner the trajectory is the path; its velocity comes with the target only when
    it is the CLIK's feedforward."""
    outer = outer_loop(clik, paper_model, track_feedforward=feedforward)
    outer.goal(T0, TARGET, "track", trajectory=CIRCLE)
    assert outer.learner is None
    for t in TIMES:
        w, tau = 2 * np.pi / CIRCLE.period, t - T0
        point = TARGET + 0.01 * np.array([np.cos(w * tau) - 1, np.sin(w * tau)])
        x_d, velocity = outer.target_at(t)
        assert x_d == pytest.approx(point, abs=1e-12)
        if feedforward:
            point_velocity = 0.01 * w * np.array([-np.sin(w * tau), np.cos(w * tau)])
            assert velocity == pytest.approx(point_velocity, abs=1e-12)
        else:
            assert velocity is None
        path, path_velocity, _ = outer.path_at(t)
        assert np.array_equal(path, x_d)
        assert np.array_equal(path_velocity, CIRCLE.at(TARGET, tau)[1])


def test_a_learned_track_goal_s_target_leaves_out_the_correction_the_clik_tracks(clik, paper_model):
    """With a learned correction c (a mean and a first harmonic, fully blended in) target_at gives the
    trajectory's point and velocity, path_at the trajectory plus c and its velocity; the CLIK's
    online step measures its error against the corrected path."""
    outer = outer_loop(clik, paper_model, track_learning=0.5, track_harmonics=1)
    outer.goal(T0, TARGET, "track", trajectory=CIRCLE)
    C = np.array([[0.001, -0.0005], [0.002 - 0.001j, 0.0015j]])
    outer.learner.previous = outer.learner.current = C
    w = 2 * np.pi / CIRCLE.period
    for t in TIMES:
        tau = t - T0
        c = np.real(C[0] + C[1] * np.exp(1j * w * tau))
        c_velocity = np.real(1j * w * C[1] * np.exp(1j * w * tau))
        x_d, velocity = outer.target_at(t)
        point, point_velocity = CIRCLE.at(TARGET, tau)
        assert np.array_equal(x_d, point) and np.array_equal(velocity, point_velocity)
        path, path_velocity, _ = outer.path_at(t)
        assert path == pytest.approx(point + c, abs=1e-12)
        assert path_velocity == pytest.approx(point_velocity + c_velocity, abs=1e-12)
        assert np.linalg.norm(path - x_d) > 1e-3
    t = T0 + 0.02
    expected = np.linalg.norm(outer.path_at(t)[0] - TARGET)
    outer.frame(t, TARGET)                          # the arm measured at the goal's start point
    assert outer.reports[-1].error == pytest.approx(expected, rel=1e-12)
    assert abs(outer.reports[-1].error - np.linalg.norm(outer.target_at(t)[0] - TARGET)) > 1e-3
