"""The shape estimate through fast moves, on the tendons alone: coiling's three targets in turn on
the declared plant, each a precomputed step (the tip at up to about half a metre a second) and 4 s
of settling, every marker hidden. The dynamic estimate (the arm's dynamics between samples) keeps
the tip within millimetres where the static balance's lags it by centimetres, with a covariance
that bounds its error in motion and at rest; on plants whose tendons run off the drawing, only
with the routing considered."""
import numpy as np
import pytest

from conftest import CHI2_3_99, nees_bounded, nees_not_overconfident
from soft_arm_experiments.harness import load_setup, run_experiment

MOVES = ["tasks.coiling.phases=[upward]", "tasks.coiling.phase.upward.sequence=[1,2,3]",
         "tasks.coiling.phase.upward.window=4.0", "plant.mocap.occlusion.blackout=[0.0, 1.0e6]"]
REST_SPEED = 0.005     # m/s: the true tip slower than this is at rest


def _blind_moves(sets: list, task: str = "coiling") -> tuple:
    """``task``'s moves (coiling's: :data:`MOVES`) with every marker hidden under ``sets``: the true
    tip speed [m/s], the tip's error (3,) [m] and its reported covariance (3, 3) [m^2] at every
    estimate from the first second on."""
    moves = MOVES if task == "coiling" else ["plant.mocap.occlusion.blackout=[0.0, 1.0e6]"]
    result = run_experiment(load_setup(task, overrides=moves + sets), estimate=True, truth=True)
    rec = result.record.arrays()
    kept = rec["t_mocap"] >= 1.0
    error = rec["markers_estimated"][:, -1] - rec["markers_true"][:, -1]
    return rec["tip_speed"][kept], error[kept], rec["marker_covariance"][kept, -1]


@pytest.fixture(scope="module")
def moves():
    """Per process model: :func:`_blind_moves` on the declared plant."""
    return {model: _blind_moves([f"estimator.process_model={model}"]) for model in ("dynamic", "static")}


def test_through_fast_moves_the_tendons_alone_keep_the_tip_within_5_mm(moves):
    """95 % of the frames in motion within 5 mm; the static estimate's 95th percentile is more than
    twice that (its balance lags a moving arm). At rest the dynamic one is within 1 mm (median) and
    nearer than the static balance (0.41 against 1.10 mm on these windows, 0.49 against 0.67 mm
    with 6 s windows, where the arm rests longer)."""
    speed, error, _ = moves["dynamic"]
    moving = speed > REST_SPEED
    assert moving.sum() > 200 and speed.max() > 0.3
    dynamic = np.linalg.norm(error, axis=1)
    static = np.linalg.norm(moves["static"][1], axis=1)
    assert np.percentile(dynamic[moving], 95) <= 5e-3, np.percentile(dynamic[moving], 95)
    assert np.percentile(static[moving], 95) > 2 * np.percentile(dynamic[moving], 95)
    assert (~moving).sum() > 50 and np.median(dynamic[~moving]) <= 1e-3
    assert np.median(dynamic[~moving]) < np.median(static[~moving])


@pytest.mark.parametrize("frames", ["moving", "at rest"])
def test_the_dynamic_estimates_covariance_bounds_its_error(moves, frames):
    """The tip's NEES over the frames in motion, and over those at rest, within the bound of
    conftest.nees_bounded; the covariance 100 times too small or too large fails it."""
    speed, error, covariance = moves["dynamic"]
    kept = (speed > REST_SPEED) if frames == "moving" else (speed <= REST_SPEED)

    def nees(scale):
        return np.einsum("ki,kij,kj->k", error[kept], np.linalg.inv(scale * covariance[kept]), error[kept])
    assert kept.sum() > 100 and nees_bounded(nees(1.0)), np.mean(nees(1.0))
    assert not nees_bounded(nees(0.01)) and not nees_bounded(nees(100.0))


def test_through_the_triangle_the_tendons_alone_keep_the_tip_within_5_mm_moving_and_0_6_mm_at_rest():
    """The triangle's approach (its three vertices from the hanging arm, 10 s each, the tip at up to
    0.9 m/s) on the declared plant, every marker hidden, the loop holding its precomputed references
    (on a mocap that sees nothing): the dynamic estimate's tip within 5 mm on 95 % of the frames in
    motion and within 0.6 mm at rest (median; 3.1 and 0.36 mm here, 2.9 and 0.30 mm on the whole
    triangle, ``bench/bench_sensing.py``'s ``filters``). In motion its NEES is within conftest.nees_bounded,
    and not with the covariance 100 times smaller or larger. At rest it is not overconfident, and
    would be with the covariance 100 times smaller; it is conservative there (mean NEES 0.11-0.13,
    about nees_bounded's floor of 0.115): it covers the casting tolerance of the tendons' routing,
    which this plant, its tendons on their drawn paths, does not use. On the drawn routings below
    the same covariance is honest at rest (means 0.7-1.0)."""
    speed, error, covariance = _blind_moves(["tasks.triangle.phases=[approach]",
                                             "tasks.triangle.phase.approach.window=10.0",
                                             "estimator.process_model=dynamic"], task="triangle")
    tip = np.linalg.norm(error, axis=1)
    moving, resting = speed > REST_SPEED, speed <= REST_SPEED
    assert moving.sum() > 1000 and np.percentile(tip[moving], 95) <= 5e-3, np.percentile(tip[moving], 95)
    assert resting.sum() > 1000 and np.median(tip[resting]) <= 0.6e-3, np.median(tip[resting])

    def nees(kept, scale):
        return np.einsum("ki,kij,kj->k", error[kept], np.linalg.inv(scale * covariance[kept]), error[kept])
    assert nees_bounded(nees(moving, 1.0)), np.mean(nees(moving, 1.0))
    assert not nees_bounded(nees(moving, 0.01)) and not nees_bounded(nees(moving, 100.0))
    assert nees_not_overconfident(nees(resting, 1.0)) and not nees_not_overconfident(nees(resting, 0.01))


ROUTING_DRAWS = (0, 1, 2)       # the robustness campaign's first draws
ROUTING_KEYS = ("friction", "tendon.offset_fraction", "tendon.start_angle_error", "tendon.end_angle_error")


def _routing_plant(seed: int) -> list:
    """The declared plant with draw ``seed``'s tendons: its friction, offsets and angles."""
    from soft_arm_experiments.campaigns.plants import draw_plant, load_tolerances, plant_overrides
    drawn = draw_plant(seed, load_tolerances())
    return plant_overrides({key: drawn[key] for key in ROUTING_KEYS})


@pytest.fixture(scope="module")
def routing_nees():
    """Per (draw, whether the routing is considered): the tip's mean NEES in motion and at rest
    through coiling's moves, every marker hidden, the dynamic estimate."""
    out = {}
    for seed in ROUTING_DRAWS:
        for considered in (True, False):
            sets = _routing_plant(seed) + ["estimator.process_model=dynamic"]
            if not considered:
                sets += ["estimator.prior.tendon_offset=0.0", "estimator.prior.tendon_angle=0.0"]
            speed, error, covariance = _blind_moves(sets)
            nees = np.einsum("ki,kij,kj->k", error, np.linalg.inv(covariance), error)
            out[seed, considered] = nees[speed > REST_SPEED], nees[speed <= REST_SPEED]
    return out


@pytest.mark.parametrize("seed", ROUTING_DRAWS)
def test_on_drawn_routings_the_covariance_bounds_the_error_only_if_it_considers_them(routing_nees, seed):
    """Three plants whose tendons run where the campaign's casting tolerance draws them (offsets
    0.55-0.65 of the radius, angles within 3 deg, friction 0.05-0.2): with the routing considered
    (``prior.tendon_offset``, ``prior.tendon_angle``) the tip's NEES in motion and at rest is within
    conftest.nees_bounded (means 0.7-1.4); the same filter without those states, sure of the
    drawing's routing, fails the same bound on its mean alone, in both (means 20-127: on these draws
    the sure filter's error at rest is 4-12 mm where it reports a millimetre or less)."""
    for nees in routing_nees[seed, True]:
        assert nees.size > 100 and nees_bounded(nees), np.mean(nees)
    for nees in routing_nees[seed, False]:
        assert np.mean(nees) > CHI2_3_99, np.mean(nees)


def test_the_fast_circle_closed_on_the_estimate_tracks_as_the_mocap_does():
    """The tracking task's goal at 0.2 m/s (a 1.5 cm circle, learned; test_harness.py) closed on
    the dynamic estimate, with the markers seen as the mocap sees them and on the tendons alone
    (every marker hidden): its RMS over the window on the truth within 1.5 times the mocap-closed
    run's, and the blind goal never refused by the trust region (its judge averages the arm's lag
    over the path's period), which judged the drift on more than half of its frames."""
    period = 2 * np.pi * 0.015 / 0.2
    circle = ["tasks.tracking.phases=[approach, circle_fast]", "tasks.tracking.phase.approach.window=6.0",
              "tasks.tracking.phase.circle_fast.trajectory.size=0.015",
              f"tasks.tracking.phase.circle_fast.trajectory.period={period!r}",
              f"tasks.tracking.phase.circle_fast.window={22 * period!r}", "estimator.process_model=dynamic"]
    windows, goals = {}, {}
    blind = ["plant.mocap.occlusion.blackout=[0.0, 1.0e6]"]
    for feedback, sets in (("mocap", []), ("estimate", []), ("blind", blind)):
        setup = load_setup("tracking", overrides=circle + sets,
                           feedback="mocap" if feedback == "mocap" else "estimate")
        result = run_experiment(setup, estimate=feedback != "mocap", truth=True)
        windows[feedback], = result.tracking
        goals[feedback] = result.goals[-1]
    for feedback in ("estimate", "blind"):
        assert windows[feedback].path_speed == pytest.approx(0.2)
        assert windows[feedback].rms_error <= 1.5 * windows["mocap"].rms_error, (
            feedback, windows[feedback].rms_error, windows["mocap"].rms_error)
    blind = goals["blind"]
    assert blind["mode"] == "track" and blind["distrusts"] == 0, blind
    assert blind["judged_frames"] > 0.5 * 22 * period * 240, blind       # the judge was at work
