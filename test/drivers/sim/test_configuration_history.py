"""The plant's configuration history: the latest configuration at or before a time, in O(1), from
a ring that another process reads through a file mapping."""
import os
import subprocess
import sys

import numpy as np
import pytest

from soft_arm_drivers.sim.configuration_history import ConfigurationHistory

DT = 1e-3
T0 = 1.8e9                  # a time.time() of these years: a float resolves 0.24 us of it


def _filled(history, steps, t0=T0):
    """Append configurations q_k = (k, -k, 2k) at t0 + k DT, k = 0 .. steps - 1."""
    for k in range(steps):
        history.append(t0 + k * DT, [k, -k, 2 * k])


def test_the_latest_configuration_at_or_before_a_time():
    history = ConfigurationHistory(3, 50, DT)
    with pytest.raises(LookupError):
        history.at(T0)
    _filled(history, 20)
    assert history.count == 20
    for k in (0, 7, 19):
        np.testing.assert_array_equal(history.at(T0 + k * DT), [k, -k, 2 * k])     # at a step
        np.testing.assert_array_equal(history.at(T0 + (k + 0.6) * DT), [k, -k, 2 * k])  # after it
        np.testing.assert_array_equal(history.at(T0 + (k - 0.4) * DT), [k - 1, 1 - k, 2 * k - 2]
                                      if k else [0, 0, 0])                       # before it
    np.testing.assert_array_equal(history.at(T0 + 1.0), [19, -19, 38])          # newer: the latest
    np.testing.assert_array_equal(history.at(T0 - 1.0), [0, 0, 0])              # older: the oldest


def test_a_time_is_reached_once_the_step_at_or_before_it_is_the_last_before_it():
    """reached(t): at(t) is final. Before any step nothing is; up to step k every time before step
    k + 1 is (within the tolerance at() rounds with), later ones are the plant's future."""
    history = ConfigurationHistory(3, 50, DT)
    assert not history.reached(T0 - 1.0)
    _filled(history, 20)
    assert history.reached(T0 - 1.0) and history.reached(T0 + 19 * DT)
    assert history.reached(T0 + 19.99 * DT) and not history.reached(T0 + 20 * DT)
    assert not history.reached(T0 + 1.0)
    q = history.at(T0 + 19.5 * DT)
    _filled(history, 1, T0 + 20 * DT)                       # the next step does not change it
    np.testing.assert_array_equal(history.at(T0 + 19.5 * DT), q)
    assert history.reached(T0 + 20.5 * DT)


def test_the_ring_keeps_all_but_the_row_the_writer_reuses_next():
    history = ConfigurationHistory(3, 8, DT)
    _filled(history, 30)
    # rows - 1 readable: steps 23..29; older times get the oldest of them
    np.testing.assert_array_equal(history.at(T0 + 23 * DT), [23, -23, 46])
    np.testing.assert_array_equal(history.at(T0 + 5 * DT), [23, -23, 46])
    np.testing.assert_array_equal(history.at(T0 + 26.5 * DT), [26, -26, 52])
    # a copy: the next appends do not change what was read
    q = history.at(T0 + 29 * DT)
    _filled(history, 8, T0 + 30 * DT)
    np.testing.assert_array_equal(q, [29, -29, 58])


def test_another_process_reads_the_shared_history_as_it_grows():
    history = ConfigurationHistory.shared(3, 16, DT)
    try:
        assert os.path.exists(history.path)
        _filled(history, 5)
        reader = subprocess.Popen(
            [sys.executable, "-c", READER, history.path], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
            text=True)
        assert reader.stdout.readline().split() == ["4.0", "-4.0", "8.0"]
        history.unlink()                                    # the mappings stay
        assert not os.path.exists(history.path)
        _filled(history, 12, T0 + 5 * DT)                   # now up to k = 11 at T0 + 16 DT
        reader.stdin.write(f"{T0 + 16 * DT!r}\n")
        reader.stdin.flush()
        assert reader.stdout.readline().split() == ["11.0", "-11.0", "22.0"]
        reader.stdin.close()
        assert reader.wait(10) == 0
    finally:
        history.unlink()


READER = f"""
import sys
from soft_arm_drivers.sim.configuration_history import ConfigurationHistory
h = ConfigurationHistory.open(sys.argv[1], 3, 16, {DT!r})
print(*h.at(1e10), flush=True)
for line in sys.stdin:
    print(*h.at(float(line)), flush=True)
"""


def test_a_history_file_of_another_shape_is_refused():
    history = ConfigurationHistory.shared(3, 16, DT)
    try:
        with pytest.raises(ValueError, match="read-only"):      # a reader cannot write
            ConfigurationHistory.open(history.path, 3, 16, DT).append(0.0, [0, 0, 0])
        with pytest.raises(ValueError, match="not the"):
            ConfigurationHistory.open(history.path, 4, 16, DT)
    finally:
        history.unlink()
    with pytest.raises(ValueError, match="rows >= 2"):
        ConfigurationHistory(3, 1, DT)
