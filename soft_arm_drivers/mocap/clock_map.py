"""Stamping NatNet frames on the local clock: the server's tick clock mapped by the minimum-delay
offset over a sliding window, with outliers held until consecutive frames confirm them."""
from __future__ import annotations

from collections import deque
from typing import Optional

TOLERANCE = 1e-3        # s: a sample this far below the offset is believed at once (drift, jitter)
MAX_DELAY = 0.5         # s: a sample this far above it is no transport delay but a clock jump
CONFIRM = 3             # consecutive samples that confirm a jump
AGREEMENT = 0.05        # s: the spread within which they must agree
PACE = 0.5              # their reads at least this fraction of their server time apart


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

    A minimum believes its lowest sample, so one sample is not allowed to set it: a sample more than
    ``tolerance`` below the offset, or more than ``max_delay`` above it (no transport delay is that
    long), is an outlier (a frame with impossible ticks, or the first of a clock jump). It is held,
    not used; when ``confirm`` consecutive samples are outliers that agree within ``agreement`` and
    were read at least ``pace`` of their server time apart, the server's clock has jumped and the map
    re-anchors on them at once, forgetting the samples before. A single outlier among good samples
    is dropped and counted (:attr:`outliers`).

    The pace tells a jump from a queue. Frames that waited in the socket while this process did not
    read (starved longer than ``max_delay``) are read at once: their offsets are high and fall
    frame by frame as the server's clock runs, so that three of them agree within ``agreement``,
    yet their reads are microseconds apart where their ticks are frame periods apart. Taken for a
    jump they would re-anchor the map on the moment they were read, and frames seconds old would be
    stamped as exposed when they were read; held as outliers they keep the map's offset, and their
    stamps say how old they are. After a real jump the server's clock and this one run on together.
    A stall longer than the window is the one that moves the map: the window then holds only late
    reads, the first within ``max_delay`` sets the offset, and the stamps are late by up to
    ``max_delay`` until three frames on time re-anchor the map (a jump, counted).

    The server's own latency (exposure to transmit, Motive's processing) is measured on one clock
    and kept exactly; queueing delays of single frames do not move the stamps. What remains is a
    bias: the stamps are late by the smallest one-way delay, which one-way packets cannot separate
    from the offset (tens of microseconds on loopback and a switched LAN), and the drift of the two
    clocks: an offset that shrinks is followed at once (within ``tolerance`` per sample), one that
    grows (the local clock runs faster) within a window, so the stamps can be late by up to the
    drift over one window (2 s at 50 ppm: 0.1 ms). A new stream (server info, frame-number restart)
    starts a new map.
    """

    def __init__(self, frequency: int, window: float, *, tolerance: float = TOLERANCE,
                 max_delay: float = MAX_DELAY, confirm: int = CONFIRM, agreement: float = AGREEMENT,
                 pace: float = PACE):
        if not frequency or frequency <= 0:
            raise ValueError(f"clock frequency must be a positive number of ticks/s, got {frequency!r}")
        if not window > 0:
            raise ValueError(f"window must be positive [s], got {window!r}")
        if not (tolerance >= 0 and max_delay > 0 and confirm >= 1 and agreement >= 0 and 0 <= pace <= 1):
            raise ValueError("tolerance and agreement must be >= 0, max_delay > 0, confirm >= 1 and "
                             "pace in [0, 1]")
        self.frequency = int(frequency)
        self.window = float(window)
        self.tolerance, self.max_delay = tolerance, max_delay
        self.confirm, self.agreement, self.pace = confirm, agreement, pace
        self._base: Optional[int] = None
        self._samples: deque = deque()   # (local time, offset), offsets increasing
        self._held: list = []            # consecutive outliers: (local time, offset)
        self.outliers = 0                # samples dropped as outliers
        self.jumps = 0                   # re-anchorings on a confirmed jump

    def seconds(self, ticks: int) -> float:
        """Server ticks as seconds since the first observed tick (small numbers keep precision)."""
        return (ticks - self._base) / self.frequency

    def observe(self, ticks: int, local: float) -> bool:
        """One offset sample: server ``ticks`` read at ``local`` [s]. Whether it was believed (an
        outlier is held until confirmed, and dropped if it is not)."""
        if self._base is None:
            self._base = ticks
        offset = local - self.seconds(ticks)
        current = self.offset
        if current is None or current - self.tolerance <= offset <= current + self.max_delay:
            self.outliers += len(self._held)
            self._held.clear()
            self._add(local, offset)
            return True
        self._held.append((local, offset))
        if not self._confirmed():
            if len(self._held) > self.confirm:
                self.outliers += len(self._held) - self.confirm
                del self._held[:-self.confirm]
            return False
        self.jumps += 1
        self._samples.clear()
        for sample in self._held[-self.confirm:]:     # the agreeing samples, not an outlier before them
            self._add(*sample)
        self.outliers += len(self._held) - self.confirm
        self._held.clear()
        return True

    def _confirmed(self) -> bool:
        """Whether the last ``confirm`` held samples confirm a jump: they agree within ``agreement``
        and were read at least ``pace`` of their server time apart (class docstring)."""
        held = self._held[-self.confirm:]
        if len(held) < self.confirm:
            return False
        offsets = [o for _, o in held]
        if max(offsets) - min(offsets) > self.agreement:
            return False
        (first_read, first_offset), (last_read, last_offset) = held[0], held[-1]
        server = (last_read - last_offset) - (first_read - first_offset)
        return last_read - first_read >= self.pace * server

    def _add(self, local: float, offset: float):
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
