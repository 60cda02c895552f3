"""The hardware lock names what holds it: the outermost hold of its holding thread, from any
thread, and nothing once it is free."""
import threading
import time

import pytest

from soft_arm_ros import hardware_lock
from soft_arm_ros.hardware_lock import HardwareLock, LockTimeout


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


def test_every_wait_for_the_lock_has_a_bound():
    """No wait for ever: acquire takes a bound, >= 0 s, and says when it ran out."""
    lock = HardwareLock()
    with pytest.raises(TypeError):
        lock.acquire()                                      # pylint: disable=no-value-for-parameter
    for unbounded in (-1.0, float("nan")):
        with pytest.raises(ValueError, match="needs a bound"):
            lock.acquire(timeout=unbounded)
    assert lock.holder() is None
    assert lock.acquire(timeout=0.0, what="the test") and lock.holder()[0] == "the test"
    lock.release()


def _holding(lock: HardwareLock, what: str, take: threading.Event, held: threading.Event,
             free: threading.Event) -> threading.Thread:
    """A thread that holds ``lock`` as ``what`` each time ``take`` is set (then ``held`` is set),
    until ``free`` is set; it ends when ``take`` has not been set for a second."""
    def run():
        while take.wait(1.0):
            take.clear()
            with lock.held_by(what):
                held.set()
                free.wait(10.0)
            free.clear()
    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    return thread


def test_a_holder_waits_a_bound_then_names_what_holds_the_lock(monkeypatch):
    """A cycle stuck holding the lock: a service's wait ends at its bound with LockTimeout naming
    the service, the bound, the cycle and how long it has held; the service's block never runs and
    the cycle's record stays. The next holder, finding the same hold, does not wait again (the
    executor's callbacks answer at once), ``with lock:`` among them; a new hold of the cycle's is
    waited for again. Once free, both hold."""
    lock = HardwareLock()
    take, held, free = threading.Event(), threading.Event(), threading.Event()
    thread = _holding(lock, "the motor_driver cycle", take, held, free)
    ran = []
    try:
        take.set()
        assert held.wait(5.0)
        with pytest.raises(LockTimeout, match=r"^the estop service waited 0.05 s for the hardware lock, "
                                              r"held by the motor_driver cycle for [0-9.]+ s$") as waited:
            with lock.held_by("the estop service", timeout=0.05):
                ran.append(True)
        assert float(str(waited.value).split(" for ")[-1][:-2]) >= 0.05
        assert ran == [] and lock.holder()[0] == "the motor_driver cycle"
        begin = time.monotonic()
        with pytest.raises(LockTimeout, match=r"^the zero service found the hardware lock held by the "
                                              r"motor_driver cycle for [0-9.]+ s, as when a wait for it "
                                              r"ran out \(not waited again\)$"):
            with lock.held_by("the zero service", timeout=5.0):
                ran.append(True)
        with pytest.raises(LockTimeout, match=r"^MainThread found the hardware lock held by the "
                                              r"motor_driver cycle"):
            with lock:
                ran.append(True)
        assert ran == [] and time.monotonic() - begin < 2.0                  # not the 5 s bound
        held.clear()
        free.set()                                         # the cycle lets go, and holds again
        take.set()
        assert held.wait(5.0)
        monkeypatch.setattr(hardware_lock, "HOLD_WAIT", 0.05)
        begin = time.monotonic()
        with pytest.raises(LockTimeout, match=r"^MainThread waited 0.05 s for the hardware lock, held by "
                                              r"the motor_driver cycle"):
            with lock:
                ran.append(True)
        assert ran == [] and time.monotonic() - begin >= 0.05
    finally:
        free.set()
    deadline = time.monotonic() + 5.0
    while lock.holder() is not None and time.monotonic() < deadline:       # the cycle lets go
        time.sleep(0.001)
    with lock.held_by("the estop service", timeout=5.0):
        assert lock.holder()[0] == "the estop service"
    with lock:
        assert lock.holder()[0] == "MainThread"
    thread.join(5.0)
