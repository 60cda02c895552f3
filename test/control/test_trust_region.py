"""The trust region of an estimated feedback (soft_arm_control.trust_region), frame by frame at the
mocap's 240 Hz: it accepts an arm that swings and settles about a model error, and refuses an
estimate that leaves the arm (an offset beyond the radius) or walks away from it (a drift)."""
import numpy as np
import pytest

from soft_arm_control.trust_region import TrustConfig, TrustRegion, _OffsetHistory, defensible_fraction

RATE = 240.0
CONFIG = TrustConfig(radius=0.04, drift=0.001, window=0.5, recover=2.0)
X_MODEL = np.array([-0.0337, -0.2573])           # coiling target 3, the model's task point [m]
MODEL_ERROR = np.array([0.001, 0.0056])          # the declared plant's offset at rest [m]


def swing(t, amplitude=0.012, frequency=1.2, damping=0.2):
    """A decaying swing of the arm's first mode about the model error [m] (the declared plant
    after a precomputed step: 12 mm at the switch)."""
    w = 2 * np.pi * frequency
    return MODEL_ERROR + amplitude * np.exp(-damping * w * t) * np.array([np.cos(w * t), np.sin(w * t)])


def lag(t, amplitude=0.013, period=2 * np.pi * 0.015 / 0.2):
    """The arm's steady lag behind its reference along a circle of ``period`` [s] (the tracking
    task's fast one by default, 1.5 cm at 0.2 m/s: 13 mm in the closed loop), about the model
    error [m]: a turn at the path's period and a third of it at twice that."""
    w = 2 * np.pi / period
    return (MODEL_ERROR + amplitude * np.array([np.cos(w * t), np.sin(w * t)])
            + amplitude / 3 * np.array([np.cos(2 * w * t + 1.0), np.sin(2 * w * t + 1.0)]))


def first_refusal(offset, duration, config=CONFIG, seed=0, period=None):
    """The first frame time [s] the trust region refuses (None: it never does) for the estimate
    X_MODEL + offset(t) with 0.3 mm of noise per coordinate; ``period`` [s]: a track goal's."""
    region = TrustRegion(config)
    region.new_goal(period)
    rng = np.random.default_rng(seed)
    for t in np.arange(0.0, duration, 1.0 / RATE):
        if region.judge(t, X_MODEL + offset(t) + rng.normal(0.0, 3e-4, 2), X_MODEL) is not None:
            return t
    return None


@pytest.mark.parametrize("seed", range(3))
def test_an_arm_that_swings_and_settles_about_its_model_error_is_trusted(seed):
    assert first_refusal(swing, 10.0, seed=seed) is None


def test_a_bias_walking_at_5_mm_per_s_is_refused_within_half_a_second():
    start = 4.0                                    # the swing is down to 1.4 mm by then

    def walking(t):
        return swing(t) + np.array([0.005, 0.0]) * max(0.0, t - start)
    caught = first_refusal(walking, 10.0)
    assert caught is not None and start < caught <= start + 0.5, caught


def test_a_bias_walking_slower_than_the_drift_allows_is_not_refused():
    """The bound is the drift over the window: 1 mm/s moves 0.4 mm in 0.375 s, within 1 mm."""
    assert first_refusal(lambda t: MODEL_ERROR + np.array([0.001, 0.0]) * t, 10.0) is None


def test_an_estimate_on_another_branch_is_refused_at_once_and_the_reason_names_the_radius():
    region = TrustRegion(CONFIG)
    reason = region.judge(0.0, X_MODEL + np.array([0.03, 0.18]), X_MODEL)
    assert reason is not None and "trust radius 40.0 mm" in reason and "182.5 mm" in reason


def test_a_growing_oscillation_is_refused():
    """A loop that the estimate makes unstable swings more every period: no swing before explains it."""
    assert first_refusal(lambda t: swing(t, 0.002, damping=-0.1), 10.0) is not None


def test_reset_forgets_the_offsets():
    region = TrustRegion(CONFIG)
    for t in np.arange(0.0, 1.0, 1.0 / RATE):
        region.judge(t, X_MODEL + MODEL_ERROR, X_MODEL)
    region.reset()
    # a jump of the offset right after a reset (the reference returned) is judged on its own
    assert region.judge(1.0, X_MODEL + MODEL_ERROR + 0.01, X_MODEL) is None


@pytest.mark.parametrize("span", [0.3, 6.0])
def test_the_offsets_kept_are_the_frames_of_the_span_through_every_compaction_and_growth(span):
    """The history a frame's judgement reads is exactly the frames since ``t - span``, in order, as
    its arrays fill, are compacted (a short span) and grow (a long one: more frames than they
    hold); a clear forgets them."""
    history, frames = _OffsetHistory(capacity=64), []
    rng = np.random.default_rng(3)
    t = 0.0
    for k in range(3000):
        t += rng.choice([1 / 240, 1 / 120, 0.05])
        offset = rng.normal(size=2)
        frames.append((t, offset))
        times, offsets = history.append(t, offset, t - span)
        kept = [(s, o) for s, o in frames if s >= t - span]
        np.testing.assert_array_equal(times, [s for s, _ in kept])
        np.testing.assert_array_equal(offsets, np.array([o for _, o in kept]))
        if k == 1500:
            history.clear()
            frames.clear()
    assert (history._t.size == 64) == (span < 1.0), history._t.size


def _judgement_by_definition(times, offsets, t, window, period):
    """The trust region's figures as the module docstring defines them, with numpy's whole-array
    operations (the oracle of the compiled judgement): (|mean offset over the window|, judged,
    moved, walked, swing)."""
    mean = np.linalg.norm(offsets[times >= t - window - 1e-9].mean(axis=0))
    if period is not None:          # each frame's offset averaged over the period before it
        whole = times >= times[0] + period - 1e-9
        offsets = np.array([offsets[(times >= s - period + 1e-9) & (times <= s)].mean(axis=0)
                            for s in times[whole]]).reshape(-1, offsets.shape[1])
        times = times[whole]
    if not times.size or times[0] > t - 3 * window + 1e-9:
        return mean, False, 0.0, 0.0, 0.0
    edges = t - 3 * window + 0.25 * window * np.arange(13)
    edges[-1] += 1e-9
    quarter = np.digitize(times, edges) - 1
    if any(not np.any(quarter == b) for b in range(12)):
        return mean, False, 0.0, 0.0, 0.0
    means = np.array([offsets[quarter == b].mean(axis=0) for b in range(12)])
    line = np.polyfit(np.arange(8.0), means[:8], 1)          # slope, intercept per coordinate
    before = means[:8] - (np.arange(8.0)[:, None] * line[0] + line[1])
    swing = 0.5 * max(np.linalg.norm(a - b) for a in before for b in before)
    moved = np.linalg.norm(means[11] - (11.0 * line[0] + line[1]))
    return mean, True, moved, np.linalg.norm(4.0 * line[0]), swing


@pytest.mark.parametrize("period", [None, 0.3])
def test_the_judgement_is_the_quarter_window_means_their_line_and_the_swing_about_it(period):
    """On random histories (uneven frames, gaps, two and three coordinates) the figures the judge
    compares are the definition's: the window's mean offset, the line through the quarter-window
    means of the two windows before, the latest quarter's distance from it carried on, the line's
    walk over a window and half the widest spread about it."""
    from soft_arm_control.trust_region import _judgement
    rng = np.random.default_rng(11)
    judged = 0
    for trial in range(60):
        d = 2 + trial % 2
        gaps = rng.choice([1 / 240, 1 / 120, 0.3], size=800, p=[0.7, 0.295, 0.005])
        times = np.cumsum(gaps)[-rng.integers(50, 800):]
        offsets = np.cumsum(rng.normal(scale=1e-4, size=(times.size, d)), axis=0)
        t, window = times[-1], 0.4
        got = _judgement(times, offsets, t, window, np.nan if period is None else period)
        want = _judgement_by_definition(times, offsets, t, window, period)
        assert got[1] == want[1]
        np.testing.assert_allclose(got[:1] + got[2:], want[:1] + want[2:], rtol=1e-9, atol=1e-15)
        judged += got[1]
    assert 10 < judged < 60                       # both the judged and the refused histories seen


def test_a_step_on_the_defended_fraction_never_ends_further_from_the_target_whatever_the_bias():
    """For an estimated error e and any bias b with |b_i| <= confidence sigma_i (the true error
    e + b), a step that moves the task by alpha e leaves a true error no larger than before; the
    bound is tight: a larger fraction has a bias that makes it worse."""
    rng = np.random.default_rng(0)
    for _ in range(2000):
        m = int(rng.integers(1, 5))
        e, sigma = rng.normal(0.0, 0.01, m), rng.uniform(0.0, 0.01, m)
        alpha = defensible_fraction(e, sigma, 2.0)
        worst = -2.0 * sigma * np.sign(e)                  # the bias most against the step
        for b in [worst, *rng.uniform(-2.0 * sigma, 2.0 * sigma, (20, m))]:
            assert np.linalg.norm(e + b - alpha * e) <= np.linalg.norm(e + b) + 1e-15
        if 0.0 < alpha < 1.0:
            assert np.linalg.norm(e + worst - 1.01 * alpha * e) > np.linalg.norm(e + worst)


def test_the_defended_fraction_is_none_within_the_uncertainty_and_all_beyond_twice_it():
    e = np.array([0.003, 0.004])                                  # 5 mm
    assert defensible_fraction(e, [0.0025, 0.0025], 1.0) == pytest.approx(0.6)   # B: 17.5 of 25 mm^2
    assert defensible_fraction(e, [0.001, 0.001], 2.0) == pytest.approx(2 * (1 - 2 * 7e-6 / 25e-6))
    assert defensible_fraction(e, [0.004, 0.004], 2.0) == 0.0     # within its uncertainty: no step
    assert defensible_fraction(e, [0.0005, 0.0005], 2.0) == 1.0   # beyond twice it: all of it
    assert defensible_fraction(np.zeros(2), [0.001, 0.001], 2.0) == 0.0
    assert defensible_fraction(e, [0.004, 0.004], 0.0) == 1.0     # confidence 0: taken whole
    region = TrustRegion(CONFIG)
    assert region.fraction(e, None) == 0.0 and region.fraction(e, [np.nan, 0.001]) == 0.0
    assert region.fraction(e, [0.0005, 0.0005]) == 1.0


@pytest.mark.parametrize("seed", range(3))
def test_along_a_periodic_path_the_arms_steady_lag_is_trusted(seed):
    """The judge of a track goal averages the offset over the path's period: the 13 mm lag turning
    with the fast circle is no drift. Judged as a fixed target's (quarter-window means of a swing
    whose period is not the window's), the same lag is refused."""
    period = 2 * np.pi * 0.015 / 0.2
    assert first_refusal(lag, 10.0, seed=seed, period=period) is None
    assert first_refusal(lag, 10.0, seed=seed) is not None


def test_along_a_periodic_path_a_bias_walking_at_5_mm_per_s_is_refused_within_a_second():
    """Under the 13 mm lag, which a fixed target's judge would take for the arm's swing and excuse
    a walk of that much."""
    start, period = 4.0, 2 * np.pi * 0.015 / 0.2

    def walking(t):
        return lag(t) + np.array([0.005, 0.0]) * max(0.0, t - start)
    caught = first_refusal(walking, 10.0, period=period)
    assert caught is not None and start < caught <= start + 1.0, caught


def test_only_a_path_faster_than_two_windows_is_averaged_over_its_period():
    """The fast circle (0.47 s) is judged on its period means; the slow circle (20 s), whose means
    would leave the drift unjudged for 20 s, as a fixed target; a new goal forgets the period."""
    region = TrustRegion(CONFIG)
    region.new_goal(2 * np.pi * 0.015 / 0.2)
    assert region.period == pytest.approx(2 * np.pi * 0.015 / 0.2)
    region.new_goal(20.0)
    assert region.period is None
    region.new_goal(0.47)
    region.new_goal(None)
    assert region.period is None
