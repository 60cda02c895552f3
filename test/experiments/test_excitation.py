"""The identification experiment's schedule: inside the limits at every instant, the documented
order of segments, and identification.yaml refused with the key named when it is not."""
import numpy as np
import pytest

from soft_arm_experiments.excitation import (Excitation, load_excitation, load_identification,
                                             parse_fit)
from soft_arm_model.parameters import ConfigError


def _excitation(**overrides):
    return Excitation(load_excitation(4, 0.05, 5.0, overrides=overrides), 4)


def test_tensions_stay_within_low_and_high_at_every_instant_and_start_and_end_hanging():
    ex = _excitation()
    c = ex.config
    t = np.arange(0.0, ex.duration, 0.001)
    u = np.array([ex.tension(x) for x in t])
    assert u.min() >= c.low - 1e-12 and u.max() <= c.high + 1e-12
    assert np.allclose(u[0], c.low) and np.allclose(ex.tension(ex.duration + 1.0), c.low)
    assert np.allclose(ex.tension(-0.5), c.low)
    assert np.isclose(ex.duration, sum(s.duration for s in ex.segments))


def test_segments_follow_the_documented_order():
    ex = _excitation()
    c = ex.config
    kinds = [s.kind for s in ex.segments]
    n_stair = 1 + (4 + len(c.pairs)) * (2 * c.steps)
    assert kinds[:n_stair] == ["plateau"] * n_stair
    assert kinds[n_stair:n_stair + 8] == ["step", "plateau"] * 4
    assert kinds[n_stair + 8:] == ["chirp", "plateau"] * len(c.chirp_tendons)
    # every tendon is pulled to the top alone and in its pairs, loading and unloading
    top = [s for s in ex.segments if s.kind == "plateau" and s.tension.max() == c.high]
    assert {tuple(np.flatnonzero(s.tension == c.high)) for s in top} == {(0,), (1,), (2,), (3,), *c.pairs}


def test_the_chirp_starts_at_low_with_zero_slope_and_sweeps_its_band():
    ex = _excitation()
    c = ex.config
    chirp = next(s for s in ex.segments if s.kind == "chirp")
    k = chirp.tendon
    assert np.isclose(ex.tension(chirp.start)[k], c.low)
    assert abs(ex.tension(chirp.start + 1e-4)[k] - c.low) < 1e-6
    t = np.arange(chirp.start, chirp.start + chirp.duration, 1e-3)
    u = np.array([ex.tension(x)[k] for x in t])
    others = np.delete(np.array([ex.tension(x) for x in t[::50]]), k, axis=1)
    assert np.allclose(others, c.low)
    lows = np.flatnonzero(np.diff(np.sign(np.diff(u))) > 0)        # minima of the cosine
    periods = np.diff(t[lows])
    assert periods[0] > 1.0 / (c.chirp_f0 + (c.chirp_f1 - c.chirp_f0) * 0.3)
    assert periods[-1] < 1.5 / c.chirp_f1


@pytest.mark.parametrize("key, value, words", [
    ("tension_high", 6.0, "control.tension_max"),
    ("tension_low", 0.01, "control.tension_min"),
    ("pairs", [1, 1], "two different tendon numbers"),
    ("pairs", [1, 5], "1..4"),
    ("chirp.amplitude", 2.0, "peaks at low + 2 amplitude"),
    ("step.tension", 3.0, "tension_high"),
    ("average", 7.0, "identification.hold"),
])
def test_bad_values_name_the_key_and_what_is_allowed(key, value, words):
    with pytest.raises(ConfigError, match=f"identification.{key}") as err:
        load_excitation(4, 0.05, 5.0, overrides={key: value})
    assert words in str(err.value)


def test_the_fit_needs_plateaus_longer_than_their_averaged_end():
    with pytest.raises(ConfigError, match="fit.min_plateau"):
        parse_fit(load_identification(overrides={"fit.min_plateau": 1.0}))
