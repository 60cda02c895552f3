"""A loop's time from its input stamps: stamps that are no number are refused, clock steps are
counted and never lock the loop or jump its integral."""
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from soft_arm_control.actuation_map import ActuationMap
from soft_arm_control.inner_loop import InnerLoopGains, PSatID, TendonController
from soft_arm_control.loop_clock import LoopClock

PERIOD = 0.002
MAX_STEP = 0.1
E_SAT = 0.01


def test_stamps_advance_the_loop_and_steps_advance_it_one_period():
    clock = LoopClock(MAX_STEP)
    times = [clock.advance(k * PERIOD) for k in range(5)]
    np.testing.assert_allclose(times, np.arange(5) * PERIOD)
    assert clock.advance(1e9) == pytest.approx(5 * PERIOD)                     # forward: one period
    assert clock.advance(1e9 + PERIOD) == pytest.approx(6 * PERIOD, abs=1e-6)  # re-anchored there
    assert clock.advance(10 * PERIOD) == pytest.approx(7 * PERIOD, abs=1e-6)   # back: one period
    assert clock.advance(11 * PERIOD) == pytest.approx(8 * PERIOD, abs=1e-6)
    assert (clock.steps_forward, clock.steps_back) == (1, 1)
    assert clock.last_step[0] == "back" and clock.last_step[1] == pytest.approx(10 * PERIOD - 1e9 - PERIOD)
    assert "2 clock steps (1 forward, 1 back); the latest back by" in clock.describe()
    for bad in (math.nan, math.inf, -math.inf):
        with pytest.raises(ValueError, match="no finite time"):
            clock.advance(bad)
    assert clock.stamp == 11 * PERIOD and clock.steps == 2
    assert clock.advance(11 * PERIOD) == pytest.approx(8 * PERIOD, abs=1e-6)   # a repeat: no time, no step


def test_a_clock_with_an_origin_starts_there_and_goes_on_by_the_stamps():
    """A loop with a time of its own before its stream starts (the CLIK takes goals at 0 before the
    first frame) starts at that origin on the first stamp, whatever clock the stamps are on."""
    clock = LoopClock(MAX_STEP, origin=0.0)
    start = 1.7e9
    times = [clock.advance(start + k * PERIOD) for k in range(4)]
    np.testing.assert_allclose(times, np.arange(4) * PERIOD, atol=1e-6)
    assert clock.steps == 0 and clock.stamp == start + 3 * PERIOD
    for bad in (math.nan, math.inf):
        with pytest.raises(ValueError, match="origin"):
            LoopClock(MAX_STEP, origin=bad)


GAPS = st.one_of(st.floats(0.0, 0.01), st.floats(-1e9, 1e9), st.sampled_from([-5.0, 1e9, -1e9, 0.5]))


@settings(max_examples=300, deadline=None)
@given(gaps=st.lists(GAPS, min_size=1, max_size=60))
def test_the_loop_time_only_moves_forward_by_bounded_intervals(gaps):
    clock, stamp = LoopClock(MAX_STEP), 100.0
    last = clock.advance(stamp)
    steps = 0
    for gap in gaps:
        previous, stamp = stamp, stamp + gap
        now = clock.advance(stamp)
        assert 0.0 <= now - last <= MAX_STEP
        steps += not 0.0 <= stamp - previous <= MAX_STEP
        last = now
    assert clock.steps == steps


def _pid():
    gains = InnerLoopGains(np.full(4, 1500.0), np.full(4, 120.0), np.full(4, 3000.0), E_SAT, 0.05, 5.0)
    return PSatID(gains, ActuationMap.identity(), (0, 1, 2, 3), 4, max_time_step=MAX_STEP)


ERROR = np.array([0.0004, 0.0003, 0.0002, 0.0001])        # m: the output stays within the limits


def _run(pid, stamps):
    """Regulate a fixed error at the given stamps; the integrals after each update."""
    z = np.zeros(4)
    out = []
    for t in stamps:
        pid.update(t, z, z, ERROR, z)
        out.append(pid.xi.copy())
    return np.array(out)


def test_a_stamp_that_is_no_number_is_refused_and_the_integral_stays():
    pid = _pid()
    _run(pid, np.arange(10) * PERIOD)
    before = pid.xi.copy()
    with pytest.raises(ValueError, match="no finite time"):
        pid.update(math.nan, np.zeros(4), np.zeros(4), ERROR, np.zeros(4))
    np.testing.assert_array_equal(pid.xi, before)
    assert np.all(np.isfinite(_run(pid, [10 * PERIOD])))


def test_one_state_from_far_ahead_does_not_lock_the_loop():
    """A state stamped 1e9 s ahead, then the normal stamps: every state is taken (250 of 250 in
    the next 0.5 s), the two steps are counted, and the integral grows as over 252 periods."""
    pid = _pid()
    normal = np.arange(100) * PERIOD
    xi = _run(pid, list(normal) + [1e9] + list(normal[-1] + np.arange(1, 251) * PERIOD))
    assert len(xi) == 351 and (pid.clock.steps_forward, pid.clock.steps_back) == (1, 1)
    expected = 350 * PERIOD * E_SAT * np.tanh(ERROR / E_SAT)
    np.testing.assert_allclose(xi[-1], expected, rtol=1e-9)


def test_stamps_stepped_back_five_seconds_keep_the_loop_running():
    pid = _pid()
    stamps = list(np.arange(100) * PERIOD)
    stamps += list(stamps[-1] - 5.0 + np.arange(1, 251) * PERIOD)        # NTP stepped the clock back
    xi = _run(pid, stamps)
    assert pid.clock.steps_back == 1 and pid.clock.steps_forward == 0
    assert np.all(np.diff(np.abs(xi[:, 0])) > 0)                        # integrating at every state


@settings(max_examples=100, deadline=None)
@given(gaps=st.lists(GAPS, min_size=1, max_size=40))
def test_no_stamp_sequence_jumps_the_integral(gaps):
    """Whatever the stamps, each update moves each tendon's integral by what the P-satI-D+ law gives
    over a plausible interval, dt * e_sat * tanh(e / e_sat): dt the stamps' gap when it is in
    [0, max_time_step], otherwise (a clock step) the last such gap, the stream's period."""
    pid = _pid()
    stamps = 50.0 + np.cumsum([0.0] + gaps)
    xi = _run(pid, stamps)
    period, allowed = 0.0, []
    for gap in np.diff(stamps):
        if 0.0 <= gap <= MAX_STEP:
            period = gap if gap > 0.0 else period
            allowed.append(gap)
        else:
            allowed.append(period)
    per_second = E_SAT * np.tanh(ERROR / E_SAT)          # m: the integrand, the same every update
    np.testing.assert_allclose(np.diff(xi, axis=0), np.outer(allowed, per_second), rtol=1e-9, atol=1e-18)


def test_the_reference_rate_hold_counts_loop_time_not_stamps():
    """A moving reference's rate counts for rate_hold seconds of the loop's time: a clock step back
    does not stretch it, one forward does not cut it."""
    gains = InnerLoopGains(np.full(4, 1500.0), np.full(4, 120.0), np.zeros(4), E_SAT, 0.05, 5.0)
    z = np.zeros(4)
    for jump in (-5.0, 1e6):
        tc = TendonController(4, gains, ActuationMap.identity(), (0, 1, 2, 3), rate_hold=0.01,
                              max_time_step=MAX_STEP)
        tc.set_reference(z + 0.001, z + 1.0, z + 0.01)
        moving = [tc.update(t, z, z)[0] for t in (0.0, PERIOD, 2 * PERIOD + jump)]
        later = [tc.update(2 * PERIOD + jump + k * PERIOD, z, z)[0] for k in range(1, 8)]
        assert moving[0] == moving[1] == moving[2]                      # the rate counts through the step
        assert later[:2] == [moving[0]] * 2 and later[-1] < moving[0]   # and ends 10 ms of loop time on
