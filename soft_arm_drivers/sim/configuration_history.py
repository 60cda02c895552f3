"""The plant's recent configurations, written by the thread that steps it and read by another thread
or process (the emulated Motive server samples the arm at its cameras' exposure times).

A ring of ``rows`` entries (time [s], q) on one float64 array: private memory, or a file mapping
that a second process opens (:meth:`ConfigurationHistory.shared`, :meth:`ConfigurationHistory.open`).
One writer appends on a uniform time grid (one row per plant step); readers look a time up in
O(1) and never block the writer. A row the writer overwrites while a reader copies it is detected
by its time stamp and read again. The writer is a simulation in real time that a loaded machine
holds now and then: :meth:`ConfigurationHistory.reached` tells a reader whether the configuration at
a time is written yet, or is still the plant's future.
"""
from __future__ import annotations

import math
import os
import tempfile

import numpy as np

# of a step: times this close count as equal (a time.time() of 1.8e9 s resolves 0.24 us)
_TOLERANCE = 1e-3


class ConfigurationHistory:
    """The last ``rows`` configurations q (``n`` coordinates) with the times [s] they were reached.

    ``append(t, q)`` (one writer, times on a grid of ``dt`` [s]); ``at(t)``: the latest at or before
    ``t`` (the oldest kept if ``t`` is older, the latest if ``t`` is newer); ``reached(t)``: whether
    ``at(t)`` is final.
    """

    def __init__(self, n: int, rows: int, dt: float, buffer: np.ndarray | None = None,
                 path: str | None = None):
        if n < 1 or rows < 2 or not dt > 0:
            raise ValueError(f"a history needs n >= 1, rows >= 2 and dt > 0 s, got {n}, {rows}, {dt}")
        self.n, self.rows, self.dt, self.path = int(n), int(rows), float(dt), path
        # a plain view of a mapping: indexing a np.memmap costs its subclass's bookkeeping each time
        self._buffer = np.zeros((rows + 1, n + 1)) if buffer is None else buffer.view(np.ndarray)
        if self._buffer.shape != (rows + 1, n + 1):
            raise ValueError(f"the buffer must be {(rows + 1, n + 1)}, got {self._buffer.shape}")
        self._count = self._buffer[0]           # [0]: rows appended so far
        self._ring = self._buffer[1:]

    @classmethod
    def shared(cls, n: int, rows: int, dt: float) -> "ConfigurationHistory":
        """A history on a new file mapping (in /dev/shm where there is one) that another process
        opens with :meth:`open` (``path``); :meth:`unlink` the file once it has."""
        directory = "/dev/shm" if os.path.isdir("/dev/shm") else None
        fd, path = tempfile.mkstemp(prefix="soft_arm_history_", dir=directory)
        os.close(fd)
        buffer = np.memmap(path, dtype=np.float64, mode="w+", shape=(rows + 1, n + 1))
        return cls(n, rows, dt, buffer, path)

    @classmethod
    def open(cls, path: str, n: int, rows: int, dt: float) -> "ConfigurationHistory":
        """The shared history at ``path`` (made by :meth:`shared` with the same n, rows, dt), mapped
        read-only: the writer is the process that made it."""
        expected = (rows + 1) * (n + 1) * 8
        size = os.path.getsize(path)
        if size != expected:
            raise ValueError(f"{path} holds {size} bytes, not the {expected} of a history of "
                             f"{rows} rows of {n} coordinates")
        return cls(n, rows, dt, np.memmap(path, dtype=np.float64, mode="r", shape=(rows + 1, n + 1)),
                   path)

    def unlink(self):
        """Remove the shared file (the mappings stay valid); nothing for a private history."""
        if self.path is not None:
            try:
                os.unlink(self.path)
            except FileNotFoundError:
                pass

    @property
    def count(self) -> int:
        """Configurations appended so far."""
        return int(self._count[0])

    def append(self, t: float, q):
        """Add the configuration ``q`` reached at ``t`` [s] (one ``dt`` after the previous one)."""
        c = int(self._count[0])
        row = self._ring[c % self.rows]
        row[1:] = q
        row[0] = t
        self._count[0] = c + 1              # published after the row is complete

    def reached(self, t: float) -> bool:
        """Whether the writer has stepped to ``t`` [s]: the configuration at ``t`` is written and
        :meth:`at` will not change its answer (the next step comes after ``t``)."""
        c = int(self._count[0])
        return c > 0 and float(self._ring[(c - 1) % self.rows][0]) + self.dt * (1.0 - _TOLERANCE) > t

    def at(self, t: float) -> np.ndarray:
        """A copy of the latest configuration at or before ``t`` [s]; LookupError if none was
        appended yet."""
        for _ in range(3):
            c = int(self._count[0])
            if c == 0:
                raise LookupError("no configuration appended yet")
            latest = self._ring[(c - 1) % self.rows]
            t_latest = float(latest[0])
            back = max(0, math.ceil((t_latest - t) / self.dt - _TOLERANCE))
            back = min(back, min(c, self.rows - 1) - 1)  # the oldest row the writer is not reusing
            row = self._ring[(c - 1 - back) % self.rows].copy()
            if abs(row[0] - (t_latest - back * self.dt)) < 0.5 * self.dt:   # not overwritten meanwhile
                return row[1:]
        return row[1:]                          # overwritten three times in a row: a reader held 0.5 s
