"""A thread that calls a function at a fixed rate on the monotonic clock, apart from any executor.

The motor driver's cycle runs in one, as a ros2_control hardware loop runs apart from its node's
executor: its deadlines are kept by the kernel's sleep, not by a timer event posted through the
executor, and it cycles whether or not anything spins the node (see
docs/decisions/0002-motor-driver-cycle-runs-on-a-thread-of-its-own.md). It does not help against
what blocks the whole process: rclpy publishes holding the interpreter lock, so a publish held up
inside the middleware (the driver's own state publish among them) holds every thread of the process
(docs/decisions/0005-middleware-threads-of-the-other-processes-run-under-sched-fifo.md).
"""
from __future__ import annotations

import threading
import time
from typing import Callable, Optional


class PeriodicThread:
    """Call ``callback(now)`` every ``period`` [s], ``now`` from ``clock`` [s] (default
    :func:`time.monotonic`), from a daemon thread of its own.

    - Deadlines are absolute, ``start + k period``: a late call does not move the later ones. When a
      call ends a period or more past the next deadline, the deadlines already past are skipped
      (no burst of calls to catch up) but the latest of them: one call follows at once.
    - ``lock`` (optional) is held during each call. The thread waits for it in slices of a period,
      so that :meth:`stop` ends a thread blocked on a lock its caller holds; ``on_wait(waited)``
      (optional) is called after each slice it waited in vain, ``waited`` [s] since it began to
      wait, so that a wait past a deadline is said while it lasts. :attr:`lock_wait` [s] is how long
      the latest call waited for the lock.
    - An exception from ``callback`` (or ``on_wait``) ends the thread; ``on_error(exc)`` is called
      with it from the thread (the exception is kept in :attr:`error` either way).
    - ``clock`` and ``sleep`` (default :func:`time.sleep`) are the thread's time: tests give it a
      simulated one.

    The thread inherits its creator's scheduling policy and CPUs (Linux), as any thread does.
    """

    def __init__(self, period: float, callback: Callable[[float], None], *, lock=None,
                 on_error: Optional[Callable[[BaseException], None]] = None,
                 on_wait: Optional[Callable[[float], None]] = None, name: str = "periodic",
                 clock: Callable[[], float] = time.monotonic, sleep: Callable[[float], None] = time.sleep):
        if not period > 0.0:
            raise ValueError(f"period must be > 0 s, got {period!r}")
        self.period, self.callback, self.lock, self.on_error = float(period), callback, lock, on_error
        self.on_wait = on_wait
        self.lock_wait = 0.0
        self.error: Optional[BaseException] = None
        self._clock, self._sleep = clock, sleep
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)

    def start(self) -> "PeriodicThread":
        self._thread.start()
        return self

    @property
    def running(self) -> bool:
        return self._thread.is_alive()

    def stop(self, timeout: float = 1.0):
        """Ask the thread to end and wait for it (at most ``timeout`` [s]; RuntimeError if it has
        not ended by then); from the thread itself (a callback stopping its own cycle) only ask.
        Idempotent."""
        self._stop.set()
        if self._thread.ident is not None and threading.current_thread() is not self._thread:
            self._thread.join(timeout)
            if self._thread.is_alive():
                raise RuntimeError(f"thread {self._thread.name} did not end within {timeout:g} s")

    def _run(self):
        start, k = self._clock(), 0
        while not self._stop.is_set():
            delay = start + k * self.period - self._clock()
            if delay > 0.0:
                self._sleep(delay)
            try:
                if not self._acquire():
                    return
            except BaseException as exc:        # noqa: B902 - on_wait raised: the thread's end, reported
                self._end(exc)
                return
            try:
                if self._stop.is_set():
                    return
                self.callback(self._clock())
            except BaseException as exc:        # noqa: B902 - the thread's end, reported
                self._end(exc)
                return
            finally:
                if self.lock is not None:
                    self.lock.release()
            k += 1
            behind = self._clock() - (start + k * self.period)
            if behind >= self.period:
                k += int(behind // self.period)

    def _end(self, exc: BaseException):
        self.error = exc
        if self.on_error is not None:
            self.on_error(exc)

    def _acquire(self) -> bool:
        """Take the lock, unless asked to stop while waiting for it."""
        if self.lock is None:
            return True
        start = self._clock()
        while not self.lock.acquire(timeout=self.period):
            if self._stop.is_set():
                return False
            if self.on_wait is not None:
                self.on_wait(self._clock() - start)
        self.lock_wait = self._clock() - start
        return True
