"""State-to-command latency through the graph, seen from the motor driver, without ROS.

The driver publishes each motor state stamped with its sensor time; the inner loop answers with a
command stamped like the state it was computed from. The latency of an answer is the time on the
driver's monotonic clock from publishing the state to receiving the command: the whole path
through the middleware, the controller and back, which the watchdog bounds from above. Commands
whose stamp matches no recently published state (another controller, a replayed bag) are counted,
not timed. The statistics cover the last :data:`WINDOW` answers, and every answer since the start
(counted in :data:`RUN_BIN` bins: the whole run's 99th percentile without keeping its samples).
"""
from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from .order_statistics import percentile

WINDOW = 1000           # answers the statistics look back over (2 s at 500 Hz)
REMEMBERED = 64         # published states an answer is matched against (128 ms at 500 Hz)
STAMP_TOLERANCE = 1e-6  # s: a command's stamp matches a state's within this (stamps are rounded to ns)
RUN_BIN = 1e-5          # s: the width of the bins the whole run's latencies are counted in
RUN_RANGE = 0.1         # s: latencies from here on share the last bin


@dataclass(frozen=True)
class LatencyStatistics:
    """The latency [s] of the last ``answers`` matched commands (at most :data:`WINDOW`): median, 99th
    percentile and maximum (nan before the first), and the commands that matched no published state
    since the start; over all ``run_answers`` matched since the start: the 99th percentile (an
    upper bound of the interpolated one ``p99`` gives over a window, at most :data:`RUN_BIN` above
    the sample it interpolates towards below :data:`RUN_RANGE`, and never above the maximum) and
    the maximum."""
    answers: int
    p50: float
    p99: float
    max: float
    unmatched: int
    run_answers: int = 0
    run_p99: float = math.nan
    run_max: float = math.nan


class CommandLatency:
    """Pairs published states with the commands that answer them. Not thread-safe."""

    def __init__(self, window: int = WINDOW, remembered: int = REMEMBERED):
        self._published: deque = deque(maxlen=remembered)    # (stamp [s], published at [s])
        self._latencies = np.zeros(window)
        self._run_counts = np.zeros(int(round(RUN_RANGE / RUN_BIN)) + 1, dtype=np.int64)
        self._run_max = -math.inf
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
                self._run_counts[min(max(int(latency / RUN_BIN), 0), self._run_counts.size - 1)] += 1
                self._run_max = max(self._run_max, latency)
                self.answers += 1
                return latency
        self.unmatched += 1
        return None

    def statistics(self) -> LatencyStatistics:
        """The statistics of the last answers (not computed per command: call it when reporting)."""
        recent = self._latencies[:min(self.answers, self._latencies.size)]
        if recent.size == 0:
            return LatencyStatistics(0, math.nan, math.nan, math.nan, self.unmatched)
        ascending = np.sort(recent)
        p50, p99 = percentile(ascending, 50), percentile(ascending, 99)
        below = np.cumsum(self._run_counts)            # answers in this bin or a shorter one
        # the bin of the sample the interpolated p99 reaches up to (0-based rank)
        k = int(np.searchsorted(below, math.ceil(0.99 * (self.answers - 1)) + 1))
        run_p99 = self._run_max if k >= below.size - 1 else min((k + 1) * RUN_BIN, self._run_max)
        return LatencyStatistics(int(recent.size), p50, p99, float(ascending[-1]),
                                 self.unmatched, self.answers, float(run_p99), float(self._run_max))
