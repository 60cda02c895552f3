"""The periodic thread the motor driver's cycle runs in: deadlines on a fixed grid, no catch-up
burst (on simulated time, exactly), the lock held during a call, a clean stop (from outside, from
inside, while waiting for the lock) and an exception reported, not lost."""
import threading
import time

import numpy as np
import pytest

from soft_arm_drivers.can.periodic_thread import PeriodicThread

PERIOD = 0.25           # s, simulated: every time below is exact in binary


def _simulated_calls(calls: int, held: dict) -> list:
    """The times of the first ``calls`` calls of a thread on simulated time whose call number i
    takes ``held.get(i, 0)`` s."""
    now, times, done = [0.0], [], threading.Event()

    def sleep(seconds):
        assert seconds > 0.0
        now[0] += seconds

    def call(t):
        times.append(t)
        now[0] += held.get(len(times) - 1, 0.0)
        if len(times) == calls:
            thread.stop()
            done.set()
    thread = PeriodicThread(PERIOD, call, clock=lambda: now[0], sleep=sleep)
    thread.start()
    assert done.wait(5.0), thread.error
    thread.stop()
    return times


def test_a_late_call_is_followed_by_one_at_once_then_the_grid_again():
    """Deadlines are start + k period: call 4 held 1.5 periods ends past deadline 5, which is
    made up at once; then the calls are back on the grid (a sleep of one period after each call
    would have moved them all by half a period)."""
    assert _simulated_calls(8, {4: 1.5 * PERIOD}) == [0.0, 0.25, 0.5, 0.75, 1.0, 1.375, 1.5, 1.75]


def test_deadlines_missed_by_a_long_call_are_skipped_not_made_up():
    """Call 2 held four periods: deadlines 3, 4 and 5 are skipped, deadline 6 is made up at once,
    with no burst of calls to catch up."""
    assert _simulated_calls(6, {2: 4 * PERIOD}) == [0.0, 0.25, 0.5, 1.5, 1.75, 2.0]
    # one period late exactly: one call, not two at the same instant
    assert _simulated_calls(5, {2: 2 * PERIOD}) == [0.0, 0.25, 0.5, 1.0, 1.25]


def test_no_call_comes_before_its_deadline_on_the_real_clock():
    times = []
    thread = PeriodicThread(0.002, times.append).start()
    time.sleep(0.1)
    thread.stop()
    t = np.array(times)
    assert t.size >= 2
    k = np.arange(t.size)
    assert np.all(t - t[0] >= k * 0.002 - 1e-6)        # never early; late only by what the kernel adds
    assert np.all(np.diff(t) > 0.0)


def test_the_lock_is_held_during_each_call_and_stop_ends_a_thread_waiting_for_it():
    lock = threading.RLock()
    owned = []
    thread = PeriodicThread(0.002, lambda now: owned.append(lock._is_owned()), lock=lock).start()
    deadline = time.monotonic() + 5.0
    while len(owned) < 5:
        assert time.monotonic() < deadline
        time.sleep(0.01)
    assert all(owned)
    with lock:                                         # the thread now waits for the lock
        count = len(owned)
        time.sleep(0.02)
        assert len(owned) == count
        thread.stop()                                  # while this thread holds it: no deadlock
    assert not thread.running and len(owned) == count


def test_a_wait_for_the_lock_is_reported_while_it_lasts_and_its_length_kept():
    """The lock held elsewhere for 30 periods: ``on_wait`` hears of the wait after each period
    waited in vain, with the time waited so far, while the call has not come; the call then comes
    knowing how long it waited. An ``on_wait`` that raises ends the thread and is reported."""
    lock, waits, calls = threading.RLock(), [], []
    thread = PeriodicThread(0.002, lambda now: calls.append(thread.lock_wait), lock=lock,
                            on_wait=waits.append)
    with lock:
        thread.start()
        deadline = time.monotonic() + 5.0
        while len(waits) < 5:
            assert time.monotonic() < deadline
            time.sleep(0.01)
        assert not calls
    deadline = time.monotonic() + 5.0
    while not calls:
        assert time.monotonic() < deadline
        time.sleep(0.01)
    thread.stop()
    reported = list(waits)
    assert all(np.diff(reported) > 0.0) and reported[0] >= 0.0019     # one slice or more each
    assert calls[0] >= reported[-1] and all(wait < 0.05 for wait in calls[1:])

    errors = []

    def fails(waited):
        raise RuntimeError("the log is gone")
    failing = PeriodicThread(0.002, calls.append, lock=lock, on_wait=fails, on_error=errors.append)
    try:
        with lock:
            failing.start()
            deadline = time.monotonic() + 5.0
            while failing.running:
                assert time.monotonic() < deadline
                time.sleep(0.01)
    finally:
        failing.stop()
    assert isinstance(failing.error, RuntimeError) and errors == [failing.error]


def test_a_callback_can_stop_its_own_thread():
    calls = []

    def call(now):
        calls.append(now)
        thread.stop()
    thread = PeriodicThread(0.002, call)
    thread.start()
    time.sleep(0.05)
    assert len(calls) == 1 and not thread.running


def test_an_exception_ends_the_thread_and_is_reported():
    reported = []

    def call(now):
        raise RuntimeError("bus gone")
    thread = PeriodicThread(0.002, call, on_error=reported.append).start()
    time.sleep(0.05)
    assert not thread.running
    assert isinstance(thread.error, RuntimeError) and reported == [thread.error]


def test_stop_before_start_and_twice_is_harmless_and_a_bad_period_is_refused():
    thread = PeriodicThread(0.01, lambda now: None)
    thread.stop()
    thread.stop()
    assert not thread.running
    with pytest.raises(ValueError, match="period"):
        PeriodicThread(0.0, lambda now: None)
