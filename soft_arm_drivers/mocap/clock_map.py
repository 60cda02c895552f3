"""Stamping NatNet frames on the local clock: the server's tick clock mapped by the minimum-delay
offset over a sliding window."""
from __future__ import annotations

from collections import deque
from typing import Optional


class ClockMap:
    """Maps ticks of the NatNet server's high-resolution clock onto the local clock [s].

    A frame carries, in server ticks (``ServerInfo.clock_frequency`` f per second), its camera
    mid-exposure time and the time the server sent it. For each accepted frame, with ``r`` the
    local time the datagram was read and ``s`` its transmit ticks (data-received ticks, then
    mid-exposure ticks if the server leaves them zero), the sample ``o = r - s / f`` is the
    offset between the two clocks plus the frame's transport delay (network, kernel, this process),
    which is never negative. The minimum over the last ``window`` seconds therefore estimates the
    offset plus the smallest transport delay, and a frame exposed at ``m`` ticks is stamped
    ``m / f + min(o)`` on the local clock.

    The server's own latency (exposure to transmit, Motive's processing) is measured on one clock
    and kept exactly; queueing delays of single frames do not move the stamps. What remains is a
    bias: the stamps are late by the smallest one-way delay, which one-way packets cannot separate
    from the offset (tens of microseconds on loopback and a switched LAN), and the drift of the two
    clocks: an offset that shrinks is followed at once, one that grows (the local clock runs faster)
    within a window, so the stamps can be late by up to the drift over one window (2 s at 50 ppm:
    0.1 ms). A new stream (server info, frame-number restart) starts a new map.
    """

    def __init__(self, frequency: int, window: float):
        if not frequency or frequency <= 0:
            raise ValueError(f"clock frequency must be a positive number of ticks/s, got {frequency!r}")
        if not window > 0:
            raise ValueError(f"window must be positive [s], got {window!r}")
        self.frequency = int(frequency)
        self.window = float(window)
        self._base: Optional[int] = None
        self._samples: deque = deque()   # (local time, offset), offsets increasing

    def seconds(self, ticks: int) -> float:
        """Server ticks as seconds since the first observed tick (small numbers keep precision)."""
        return (ticks - self._base) / self.frequency

    def observe(self, ticks: int, local: float):
        """One offset sample: server ``ticks`` read at ``local`` [s]."""
        if self._base is None:
            self._base = ticks
        offset = local - self.seconds(ticks)
        samples = self._samples
        while samples and samples[-1][1] >= offset:
            samples.pop()
        samples.append((local, offset))
        while samples[0][0] < local - self.window:
            samples.popleft()

    @property
    def offset(self) -> Optional[float]:
        """Local time minus server time [s] (plus the smallest transport delay); None before any
        sample."""
        return self._samples[0][1] if self._samples else None

    def to_local(self, ticks: int) -> float:
        """Server ``ticks`` on the local clock [s]; ValueError before the first sample."""
        if not self._samples:
            raise ValueError("no clock sample yet")
        return self.seconds(ticks) + self._samples[0][1]
