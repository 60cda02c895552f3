"""The lock a hardware node holds while it touches its hardware, and that says what holds it.

A driver's cycle thread waits for the lock that the executor's callbacks (commands, services,
transitions) hold: while one of them is held up (a publish the middleware holds, a bus send at its
timeout) the cycle does not run and the motors go unwatched. The cycle's watchdog says so once it
runs again; with the holder's name it also says what held it, and the cycle can report the wait
while it lasts (:class:`~soft_arm_drivers.can.periodic_thread.PeriodicThread`'s ``on_wait``).

The other way round, the callbacks wait for a cycle that holds the lock, and a cycle stuck in a
call that lets the other threads run (a bus that does not return, a driver that hangs) would hold
the executor with it: every service unanswered, the node's release never reached. So a holder
waits :data:`HOLD_WAIT` at most (or the bound it gives), then :class:`LockTimeout` names the holder
and how long it held; a holder that finds the lock still in the hold that ran out a wait before
does not wait again (the executor's callbacks answer at once while the cycle stays stuck). Each
callback says what it could not do (a service answers failure, a
command is dropped and counted, a release that could not send its zero torque to enabled motors
fails the node). A publish the middleware holds up is beyond this bound: rclpy publishes holding
the interpreter lock, which holds every thread of the process
(:mod:`soft_arm_drivers.can.periodic_thread`).
"""
from __future__ import annotations

import threading
import time
from contextlib import contextmanager
from typing import Callable, Iterator, Optional, Tuple

__all__ = ["HOLD_WAIT", "HardwareLock", "LockTimeout"]

HOLD_WAIT = 1.0    # s: the longest a holder waits for the lock unless it gives its own bound; a
#                    cycle holds it for one period's sends (each bounded by the bus's send timeout)
#                    and publishes: held longer, it is stuck and its own watchdog has tripped


class LockTimeout(RuntimeError):
    """A holder's wait for the hardware lock ran out; the message names the waiter, the bound, the
    holder and how long it had held the lock."""


class HardwareLock:
    """A re-entrant lock that knows what holds it: ``with lock.held_by("estop service"): ...``, or
    ``with lock:``, :meth:`acquire` (with a bound) and :meth:`release` (the holder is then the
    acquiring thread's name). :meth:`holder` says what holds it and since when [s, ``clock``,
    default monotonic]; a nested hold keeps the outermost one's name. Its record is written only
    by the thread that holds it."""

    def __init__(self, clock: Callable[[], float] = time.monotonic):
        self._lock = threading.RLock()
        self._clock = clock
        self._owner: Optional[int] = None      # the holding thread's ident
        self._depth = 0
        self._holder: Optional[Tuple[str, float]] = None
        self._stuck: Optional[Tuple[str, float]] = None     # the hold that ran out the latest wait

    def acquire(self, timeout: float, what: Optional[str] = None) -> bool:
        """Take the lock within ``timeout`` [s] (0: only if it is free now); False when it was not
        free in time. Every wait for it has a bound: there is no default, and no waiting for ever
        (a negative bound is refused). ``what`` names the holder (default: the current thread's
        name)."""
        if not timeout >= 0.0:
            raise ValueError(f"a wait for the hardware lock needs a bound >= 0 s, got {timeout!r}")
        if not self._lock.acquire(True, timeout):
            return False
        if self._depth == 0:
            self._owner = threading.get_ident()
            self._holder = (what or threading.current_thread().name, self._clock())
        self._depth += 1
        return True

    def release(self):
        """Release one hold; RuntimeError, the record untouched, from a thread that holds none."""
        if self._owner != threading.get_ident():
            raise RuntimeError("cannot release a hardware lock this thread does not hold")
        self._depth -= 1
        if self._depth == 0:
            self._owner = self._holder = None
        self._lock.release()

    def __enter__(self):
        self._hold(threading.current_thread().name, HOLD_WAIT)
        return self

    def __exit__(self, *exc):
        self.release()

    @contextmanager
    def held_by(self, what: str, timeout: Optional[float] = None) -> Iterator[None]:
        """Hold the lock for the block, named ``what``, once it is free within ``timeout`` [s]
        (default :data:`HOLD_WAIT`); :class:`LockTimeout` (the block not run) if it is not."""
        self._hold(what, HOLD_WAIT if timeout is None else timeout)
        try:
            yield
        finally:
            self.release()

    def _hold(self, what: str, timeout: float):
        if self._stuck is not None and self._holder is self._stuck:
            if self.acquire(timeout=0.0, what=what):
                return
            holder = self._holder                    # read once: it may be released meanwhile
            if holder is self._stuck:
                raise LockTimeout(f"{what} found the hardware lock held by {self._held(holder)}, as "
                                  "when a wait for it ran out (not waited again)")
        if self.acquire(timeout=timeout, what=what):     # a hold not seen stuck: waited for
            return
        holder = self._stuck = self._holder
        raise LockTimeout(f"{what} waited {timeout:g} s for the hardware lock, held by {self._held(holder)}")

    def _held(self, holder: Optional[Tuple[str, float]]) -> str:
        return (f"{holder[0]} for {self._clock() - holder[1]:.3f} s" if holder is not None
                else "a holder that released it just then")

    def holder(self) -> Optional[Tuple[str, float]]:
        """(what holds the lock, since when [s]), or None while it is free; read from any thread."""
        return self._holder
