"""A control loop's own time, kept from the stamps of the stream that drives it.

A loop integrates over the time between its inputs' stamps. Those stamps come from a clock outside
the loop (the motors' CAN receive times on the PC's wall clock, the mocap's mapped exposure times,
``/clock`` in simulation), and such a clock can step: NTP corrects the wall clock, a message is
stamped on another computer's clock, a simulation restarts. :class:`LoopClock` takes each stamp as
it enters, refuses one that is no number (before anything changes) and turns the stamps into a
time that only moves forward by plausible amounts:

- a stamp at most ``max_step`` after the last one advances the loop by the difference;
- a stamp further ahead, or earlier than the last, is a *clock step*: it is counted (forward or
  back, with its size), the loop advances by the stream's last good interval (its period: what
  most likely passed), and the clock re-anchors on the new stamp, so that the next stamps are
  plausible again. A step never stops the loop and never puts a jump into what it integrates.
"""
from __future__ import annotations

import math
from typing import NamedTuple, Optional


class Advance(NamedTuple):
    """What a stamp does to the loop: the interval to integrate over [s] and the clock step it is
    (``"forward"``, ``"back"``) or None."""
    dt: float
    step: Optional[str]


class LoopClock:
    """Loop time [s] from stream stamps [s]; ``max_step`` [s] > 0: the longest interval between two
    stamps that is integrated over. :meth:`check` judges a stamp without changing anything;
    :meth:`commit` takes it (the two are apart so that a loop can refuse other inputs of the same
    update first); :meth:`advance` does both."""

    def __init__(self, max_step: float, origin: Optional[float] = None):
        """``origin`` [s]: the loop's time at the first stamp (None: the first stamp itself), for a
        loop that has a time of its own before its stream starts."""
        if not (math.isfinite(max_step) and max_step > 0):
            raise ValueError(f"max_step must be a finite time > 0 s, got {max_step!r}")
        if origin is not None and not math.isfinite(origin):
            raise ValueError(f"origin must be a finite time, got {origin!r}")
        self.max_step = float(max_step)
        self.origin = origin
        self.stamp: Optional[float] = None       # the last stamp taken [s, the stream's clock]
        self.time: Optional[float] = None        # the loop's time [s]: from origin at the first stamp
        self.period = 0.0                        # the last interval integrated over that was no step
        self.steps_forward = self.steps_back = 0
        self.last_step: Optional[tuple] = None   # (direction, size [s]) of the latest clock step

    @property
    def steps(self) -> int:
        """Clock steps since the start."""
        return self.steps_forward + self.steps_back

    def check(self, stamp: float) -> Advance:
        """What ``stamp`` would do; ValueError if it is NaN or infinite."""
        stamp = float(stamp)
        if not math.isfinite(stamp):
            raise ValueError(f"time stamp {stamp!r} is no finite time")
        if self.stamp is None:
            return Advance(0.0, None)
        gap = stamp - self.stamp
        if gap < 0.0:
            return Advance(self.period, "back")
        if gap > self.max_step:
            return Advance(self.period, "forward")
        return Advance(gap, None)

    def commit(self, stamp: float, advance: Advance) -> float:
        """Take ``stamp`` with what :meth:`check` said of it; the loop time [s]."""
        stamp = float(stamp)
        if advance.step == "forward":
            self.steps_forward += 1
        elif advance.step == "back":
            self.steps_back += 1
        if advance.step is not None:
            self.last_step = (advance.step, stamp - self.stamp)
        elif self.stamp is not None and advance.dt > 0.0:
            self.period = advance.dt
        if self.time is None:
            self.time = stamp if self.origin is None else float(self.origin)
        else:
            self.time += advance.dt
        self.stamp = stamp
        return self.time

    def advance(self, stamp: float) -> float:
        """Take ``stamp``; the loop time [s]. ValueError, nothing changed, for NaN or infinity."""
        return self.commit(stamp, self.check(stamp))

    def describe(self) -> str:
        """The clock steps so far, for diagnostics and logs."""
        if self.last_step is None:
            return "no clock step"
        direction, size = self.last_step
        plural = "" if self.steps == 1 else "s"
        return (f"{self.steps} clock step{plural} ({self.steps_forward} forward, {self.steps_back} "
                f"back); the latest {direction} by {abs(size):.6g} s")
