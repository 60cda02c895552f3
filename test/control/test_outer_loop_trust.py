"""OuterLoop.frame on a fused feedback whose tip the mocap sees in stretches: the frames it measured
(zero sigma) are stepped on without the trust region's judgement, and the estimate's frames between
them are judged against the estimate's own offsets since the last measurement, never against the
measurement's: the estimate relaxing from the measurement to its own bias is not a walk."""
import numpy as np
import pytest

from soft_arm_control.clik import Clik, ClikGains
from soft_arm_control.collocated import build_collocated
from soft_arm_control.outer_loop import OuterLoop
from soft_arm_control.task_space import TaskSpace
from soft_arm_control.trust_region import TrustConfig, TrustRegion
from soft_arm_model import solve_equilibrium

COILING = TaskSpace((3, 3), (0, 2))
TARGET = np.array([0.0192, -0.3041])
RATE = 50.0                                  # Hz, online steps
FRAME = 1 / 240                              # s
MODEL_ERROR = np.array([0.002, -0.001])      # m: where the arm is, less where the model puts it
BIAS = np.array([0.0015, 0.0])               # m: the estimate's own bias, reached 0.2 s after the tip hides
TRUST = TrustConfig(radius=0.04, drift=0.001, window=0.5, recover=2.0)


@pytest.fixture(scope="module")
def outer(paper_model):
    cm = build_collocated(paper_model, (2, 3), held_tension=0.05)
    clik = Clik(cm, COILING, ClikGains(5.0, 20.0), (0.05, 5.0))
    start = clik.reference(solve_equilibrium(paper_model, np.full(4, 0.05)).q)
    return lambda: OuterLoop(clik, start, switch_delay=0.0, rate=RATE, trust=TrustRegion(TRUST))


def run(loop, seconds: float, hidden, walk=np.zeros(2), walk_from: float = 0.0) -> list:
    """Frames for ``seconds`` on an arm at the model's point of the current reference plus
    MODEL_ERROR; ``hidden(t)``: the tip is not seen at t [s] and the frame is the estimate's (its
    bias relaxing from the last measurement to BIAS, plus ``walk`` [m/s] from ``walk_from`` [s] on;
    sigma 0.1 mm),
    otherwise the mocap's (sigma 0). Returns the hidden frames' times."""
    since, out = None, []
    for k in range(int(seconds / FRAME)):
        t = k * FRAME
        x = loop.reference.x + MODEL_ERROR
        if hidden(t):
            since = t if since is None else since
            x = x + BIAS * min(1.0, (t - since) / 0.2) + walk * max(0.0, t - walk_from)
            loop.frame(t, x, np.full(2, 1e-4))
            out.append(t)
        else:
            since = None
            loop.frame(t, x, np.zeros(2))
    return out


def bursts(t: float) -> bool:
    """The tip hidden for 0.5 s at a time, seen for 2 s or more between (the arm settles while seen)."""
    return any(start <= t < start + 0.5 for start in (2.0, 4.5, 6.7))


def test_a_tip_hidden_in_bursts_is_stepped_on_and_the_switch_is_no_drift(outer):
    loop = outer()
    loop.goal(0.0, TARGET, "online")
    report = loop.reports[-1]
    assert run(loop, 8.0, bursts)
    assert report.distrusts == 0 and report.untrusted_frames == 0, report.distrust
    assert report.online_steps > 0.9 * 8.0 * RATE
    # the arm (the model's point plus its error) at the target within what the last burst's bias leaves
    assert np.linalg.norm(loop.reference.x + MODEL_ERROR - TARGET) < np.linalg.norm(BIAS) + 2e-4


def test_an_estimate_walking_away_between_measurements_is_still_refused(outer):
    loop = outer()
    loop.goal(0.0, TARGET, "online")
    report = loop.reports[-1]
    run(loop, 6.0, lambda t: t >= 1.0, walk=np.array([0.005, 0.0]), walk_from=3.0)
    assert report.distrusts >= 1 and "a bias" in report.distrust
    assert 3.0 < report.distrust_time <= 3.5, report.distrust_time


def test_a_measured_frame_ends_the_hold_of_a_refused_estimate(outer):
    loop = outer()
    loop.goal(0.0, TARGET, "online")
    report = loop.reports[-1]
    run(loop, 4.0, lambda t: t >= 1.0, walk=np.array([0.005, 0.0]), walk_from=3.0)
    assert report.holding and report.status == "untrusted"
    steps = report.online_steps
    loop.frame(4.0, loop.reference.x + MODEL_ERROR, np.zeros(2))
    assert not report.holding and report.online_steps == steps + 1
