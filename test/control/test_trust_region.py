"""The trust region of an estimated feedback (soft_arm_control.trust_region), frame by frame at the
mocap's 240 Hz: it accepts an arm that swings and settles about a model error, and refuses an
estimate that leaves the arm (an offset beyond the radius) or walks away from it (a drift)."""
import numpy as np
import pytest

from soft_arm_control.trust_region import TrustConfig, TrustRegion

RATE = 240.0
CONFIG = TrustConfig(radius=0.04, drift=0.001, window=0.5, recover=2.0)
X_MODEL = np.array([-0.0337, -0.2573])           # coiling target 3, the model's task point [m]
MODEL_ERROR = np.array([0.001, 0.0056])          # the declared plant's offset at rest [m]


def swing(t, amplitude=0.012, frequency=1.2, damping=0.2):
    """A decaying swing of the arm's first mode about the model error [m] (the declared plant
    after a precomputed step: 12 mm at the switch)."""
    w = 2 * np.pi * frequency
    return MODEL_ERROR + amplitude * np.exp(-damping * w * t) * np.array([np.cos(w * t), np.sin(w * t)])


def first_refusal(offset, duration, config=CONFIG, seed=0):
    """The first frame time [s] the trust region refuses (None: it never does) for the estimate
    X_MODEL + offset(t) with 0.3 mm of noise per coordinate."""
    region = TrustRegion(config)
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
