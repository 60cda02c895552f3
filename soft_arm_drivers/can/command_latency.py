"""State-to-command latency through the graph, seen from the motor driver, without ROS.

The driver publishes each motor state stamped with its sensor time; the inner loop answers with a
command stamped like the state it was computed from. The latency of an answer is the time on the
driver's monotonic clock from publishing the state to receiving the command: the whole path
through the middleware, the controller and back, which the watchdog bounds from above. Commands
whose stamp matches no recently published state (another controller, a replayed bag) are counted,
not timed.
"""
from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

WINDOW = 1000           # answers the statistics look back over (2 s at 500 Hz)
REMEMBERED = 64         # published states an answer is matched against (128 ms at 500 Hz)
STAMP_TOLERANCE = 1e-6  # s: a command's stamp matches a state's within this (stamps are rounded to ns)


@dataclass(frozen=True)
class LatencyStatistics:
    """The latency [s] of the last ``answers`` matched commands (at most :data:`WINDOW`): median, 99th
    percentile and maximum (nan before the first), and the commands that matched no published state
    since the start."""
    answers: int
    p50: float
    p99: float
    max: float
    unmatched: int


class CommandLatency:
    """Pairs published states with the commands that answer them. Not thread-safe."""

    def __init__(self, window: int = WINDOW, remembered: int = REMEMBERED):
        self._published: deque = deque(maxlen=remembered)    # (stamp [s], published at [s])
        self._latencies = np.zeros(window)
        self.answers = self.unmatched = 0

    def published(self, stamp: float, now: float):
        """A state stamped ``stamp`` [s] was published at ``now`` [s, monotonic]."""
        self._published.append((float(stamp), float(now)))

    def answered(self, stamp: float, now: float) -> float | None:
        """A command stamped ``stamp`` [s] arrived at ``now`` [s]: its latency [s], or None when no
        remembered state has that stamp (a state is timed at its first answer; a second one is unmatched)."""
        for k in range(len(self._published) - 1, -1, -1):
            state_stamp, sent = self._published[k]
            if abs(state_stamp - stamp) <= STAMP_TOLERANCE:
                del self._published[k]
                latency = now - sent
                self._latencies[self.answers % self._latencies.size] = latency
                self.answers += 1
                return latency
        self.unmatched += 1
        return None

    def statistics(self) -> LatencyStatistics:
        """The statistics of the last answers (not computed per command: call it when reporting)."""
        recent = self._latencies[:min(self.answers, self._latencies.size)]
        if recent.size == 0:
            return LatencyStatistics(0, math.nan, math.nan, math.nan, self.unmatched)
        p50, p99 = np.percentile(recent, [50, 99])
        return LatencyStatistics(int(recent.size), float(p50), float(p99), float(recent.max()),
                                 self.unmatched)
