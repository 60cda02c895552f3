"""OuterLoop.frame on frames whose task markers were not seen (NaN): no online step is taken on
them, the goal says so (``unseen``), and the steps resume with the next frame that sees them."""
import numpy as np
import pytest

from soft_arm_control.clik import Clik, ClikGains
from soft_arm_control.collocated import build_collocated
from soft_arm_control.outer_loop import OuterLoop
from soft_arm_control.task_space import TaskSpace
from soft_arm_model import solve_equilibrium

COILING = TaskSpace((3, 3), (0, 2))
TARGET = np.array([0.0192, -0.3041])
RATE = 50.0                                  # Hz, online steps
FRAME = 1 / 240                              # s


@pytest.fixture(scope="module")
def outer(paper_model):
    cm = build_collocated(paper_model, (2, 3), held_tension=0.05)
    clik = Clik(cm, COILING, ClikGains(5.0, 20.0), (0.05, 5.0))
    start = clik.reference(solve_equilibrium(paper_model, np.full(4, 0.05)).q)
    return lambda: OuterLoop(clik, start, switch_delay=0.0, rate=RATE)


def test_frames_without_the_task_markers_take_no_step_and_the_goal_reports_unseen(outer):
    loop = outer()
    loop.goal(0.0, TARGET, "online")
    report = loop.reports[-1]
    x_seen = np.array([0.0, -0.33])
    t, steps = 0.0, []
    for k in range(240):                     # 1 s: seen, then 0.5 s unseen, then seen again
        t = k * FRAME
        unseen = 0.25 <= t < 0.75
        x = np.array([np.nan, -0.33]) if unseen else x_seen
        before = report.online_steps
        loop.frame(t, x)
        steps.append(report.online_steps - before)
        if unseen and t > 0.25 + 2 / RATE:
            assert report.status == "unseen" and report.unseen_time > 1 / RATE
        if 0.25 <= t < 0.75:
            assert steps[-1] == 0
    t_steps = np.arange(240)[np.array(steps) == 1] * FRAME
    assert not np.any((t_steps >= 0.25) & (t_steps < 0.75))
    assert np.any(t_steps >= 0.75) and np.min(t_steps[t_steps >= 0.75]) < 0.75 + FRAME + 1e-9
    assert report.unseen_frames >= 0.5 * RATE and report.unseen_time == 0.0
    assert report.status != "unseen" and report.as_dict()["unseen_frames"] == report.unseen_frames


def test_one_unseen_frame_delays_the_step_by_one_frame_and_is_not_a_status(outer):
    loop = outer()
    loop.goal(0.0, TARGET, "online")
    report = loop.reports[-1]
    loop.frame(0.0, np.array([np.nan, -0.33]))
    assert report.online_steps == 0 and report.status == "ok"
    loop.frame(FRAME, np.array([0.0, -0.33]))
    assert report.online_steps == 1 and report.unseen_frames == 1
