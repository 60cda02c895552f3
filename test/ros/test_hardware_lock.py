"""The hardware lock names what holds it: the outermost hold of its holding thread, from any
thread, and nothing once it is free."""
import threading

import pytest

from soft_arm_ros.hardware_lock import HardwareLock


def test_the_lock_names_its_outermost_holder_until_it_is_free():
    now = [10.0]
    lock = HardwareLock(clock=lambda: now[0])
    assert lock.holder() is None
    with lock.held_by("the estop service"):
        now[0] = 11.0
        with lock.held_by("the deactivate transition"):              # re-entered: the outer name
            assert lock.holder() == ("the estop service", 10.0)
        assert lock.holder() == ("the estop service", 10.0)
        seen, taken = [], []

        def other():
            seen.append(lock.holder())
            taken.append(lock.acquire(timeout=0.01))

        def wrong_release():
            with pytest.raises(RuntimeError, match="does not hold"):
                lock.release()
            seen.append(lock.holder())
        for target in (other, wrong_release):
            thread = threading.Thread(target=target, name="motor_driver cycle")
            thread.start()
            thread.join(5.0)
        assert seen == [("the estop service", 10.0)] * 2 and taken == [False]    # the record untouched
    assert lock.holder() is None
    with pytest.raises(RuntimeError, match="does not hold"):                     # free: nothing to release
        lock.release()
    with lock:                                                                 # unnamed: the thread's name
        assert lock.holder() == ("MainThread", 11.0)
    with lock.held_by("the zero service"):                                     # the record still sound
        assert lock.holder() == ("the zero service", 11.0)
    assert lock.holder() is None
