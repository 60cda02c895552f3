"""How fast a lockstep simulation may run against the wall clock, ROS-free.

A lockstep simulator steps when the inner loop answers, so it runs as fast as that loop and the
plant allow: two to three times real time for the graph of node processes on a two-core computer.
The nodes outside that lock (the clik node on the mocap frames, the shape estimator, the recorder)
spend wall time on each message, and every wall second they spend is that many simulated seconds
of frames they miss: a CLIK step that takes 0.36 s of a loaded computer's wall time skips a
simulated second at three times real time, where it would skip 0.36 s on the rig. What the
controller achieves then depends on the computer's speed. :class:`RealTimeLimit` holds the
simulated time to at most ``factor`` times the wall clock (1: the rig's time), so that those nodes
get the time budget the rig gives them.
"""
from __future__ import annotations

import math
import time


class RealTimeLimit:
    """Holds a simulation to at most ``factor`` simulated seconds per wall second; ``factor`` 0:
    no limit. ``clock`` [s] is monotonic, ``sleep`` waits the seconds it is given (injected for
    tests). A simulation that falls behind (the plant or the graph slower than the limit) goes on
    from where the wall clock is: it never runs faster than the limit to catch up."""

    def __init__(self, factor: float, clock=time.monotonic, sleep=time.sleep):
        if not (math.isfinite(factor) and factor >= 0.0):
            raise ValueError(f"the real-time factor limit must be a finite number >= 0, got {factor!r}")
        self.factor = float(factor)
        self.clock, self.sleep = clock, sleep
        self.due = None                 # wall time [s, clock's] at which the simulated time is due

    def hold(self, simulated: float) -> float:
        """After ``simulated`` [s] more of simulated time: waits until it is due (the first call
        anchors the limit at the wall clock's now). Returns the wall time waited [s]."""
        if self.factor == 0.0:
            return 0.0
        now = self.clock()
        self.due = now if self.due is None else max(self.due + simulated / self.factor, now)
        wait = self.due - now
        if wait > 0.0:
            self.sleep(wait)
        return wait
