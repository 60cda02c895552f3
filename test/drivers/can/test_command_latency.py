"""The state-to-command latency core: answers matched to the states they answer by stamp, timed
from publication; unmatched and repeated answers counted, not timed; statistics over a window."""
import math

import numpy as np
import pytest

from soft_arm_drivers.can.command_latency import REMEMBERED, CommandLatency


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
