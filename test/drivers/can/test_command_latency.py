"""The state-to-command latency core: answers matched to the states they answer by stamp, timed
from publication; unmatched and repeated answers counted, not timed; statistics over a window."""
import math

import numpy as np
import pytest

from soft_arm_drivers.can.command_latency import REMEMBERED, RUN_BIN, RUN_RANGE, CommandLatency


def test_an_answer_is_timed_from_the_state_it_answers():
    latency = CommandLatency()
    for k in range(5):
        latency.published(100.0 + 0.002 * k, 10.0 + 0.002 * k)
    # answers to the third and the first state, stamps rounded to the nanosecond on the way
    assert latency.answered(100.004 + 4e-10, 10.0047) == pytest.approx(0.0007)
    assert latency.answered(100.0, 10.0051) == pytest.approx(0.0051)
    stats = latency.statistics()
    assert stats.answers == 2 and stats.unmatched == 0
    assert stats.max == pytest.approx(0.0051) and stats.p50 == pytest.approx(0.0029)


def test_unknown_repeated_and_forgotten_stamps_are_counted_not_timed():
    latency = CommandLatency()
    assert math.isnan(latency.statistics().p99)
    latency.published(1.0, 5.0)
    assert latency.answered(1.00001, 5.001) is None          # 10 us off: another state
    assert latency.answered(1.0, 5.001) == pytest.approx(0.001)
    assert latency.answered(1.0, 5.002) is None              # answered twice: timed once
    for k in range(REMEMBERED + 1):
        latency.published(2.0 + k, 6.0 + k)
    assert latency.answered(2.0, 100.0) is None              # too old to be remembered
    stats = latency.statistics()
    assert stats.answers == 1 and stats.unmatched == 3


def test_statistics_look_back_over_the_window():
    latency = CommandLatency(window=10)
    for k in range(30):
        latency.published(float(k), float(k))
        latency.answered(float(k), k + (0.1 if k < 20 else 0.001 * (k - 19)))
    stats = latency.statistics()
    assert stats.answers == 10
    assert stats.max == pytest.approx(0.010)
    assert stats.p50 == pytest.approx(np.median(0.001 * np.arange(1, 11)))


def test_the_whole_run_s_99th_percentile_is_counted_beyond_the_window():
    """Over 20 000 answers, 1.5 % of them 2-3 ms long and bunched in one stretch: the last window's
    p99 misses them, the run's finds them (binned: at most RUN_BIN above the sample percentile)."""
    rng = np.random.default_rng(4)
    latencies = rng.uniform(2e-4, 6e-4, 20000)
    latencies[5000:5300] = rng.uniform(2e-3, 3e-3, 300)
    latency = CommandLatency()
    for k, dt in enumerate(latencies):
        latency.published(float(k), 10.0 + k)
        latency.answered(float(k), 10.0 + k + dt)
    stats = latency.statistics()
    upper = np.sort(latencies)[int(np.ceil(0.99 * (latencies.size - 1)))]    # the sample p99 reaches to
    assert stats.run_answers == 20000 and stats.p99 < 6e-4
    assert np.percentile(latencies, 99) <= stats.run_p99 <= upper + RUN_BIN + 1e-9
    assert stats.run_p99 > 2e-3
    assert stats.run_max == pytest.approx(latencies.max(), abs=1e-9)


def test_the_run_s_percentile_bounds_the_window_s_while_the_window_holds_the_whole_run():
    """99 answers of 0.2 ms and one of 50 ms: the window's interpolated p99 (0.70 ms) is not above
    the run's."""
    latency = CommandLatency()
    for k, dt in enumerate([2e-4] * 99 + [0.05]):
        latency.published(float(k), float(k))
        latency.answered(float(k), k + dt)
    stats = latency.statistics()
    assert stats.p99 == pytest.approx(np.percentile([2e-4] * 99 + [0.05], 99))
    assert stats.p99 <= stats.run_p99 <= 0.05


def test_the_run_s_percentile_is_bounded_by_its_maximum_beyond_the_binned_range():
    latency = CommandLatency()
    for k, dt in enumerate([1e-4] * 98 + [0.25, 0.4]):          # two answers beyond RUN_RANGE
        latency.published(float(k), float(k))
        latency.answered(float(k), k + dt)
    stats = latency.statistics()
    assert RUN_RANGE < 0.25 and stats.run_p99 == pytest.approx(0.4) and stats.run_max == pytest.approx(0.4)
    one = CommandLatency()
    one.published(0.0, 0.0)
    one.answered(0.0, 3.3e-4)
    assert one.statistics().run_p99 == pytest.approx(3.3e-4)     # never above the maximum
