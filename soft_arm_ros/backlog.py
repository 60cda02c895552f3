"""A subscription whose callback can outlast its messages' period, kept from building a backlog.

rclpy's events executor queues one event per message received and serves the events in order,
each taking the newest message a depth-1 subscription holds. When the callback takes longer than
the period (a CLIK step on a loaded computer), every event still finds a newer message, the queue
grows by the difference, and whatever else the node waits for (a goal, a timer) waits behind it:
seconds, and a depth-1 goal can be overwritten by the next before it is taken. A
:class:`BacklogGuard` tells such a queued event by its start: it follows the end of the
subscription's last callback within ``gap`` (the executor's own dispatch, a few hundred
microseconds at most), where a message that arrives to an idle executor starts a period minus the
callback's cost later (about 0.6 ms for 240 Hz frames and a 3.5 ms callback). The message a queued event
takes arrived during the last callback: it is dropped, the events queued behind it find nothing to
take, and the next message to arrive is processed. Nothing is dropped while the callback keeps up
(its cost below the period minus ``gap``). See
docs/decisions/0006-clik-node-drops-frames-queued-behind-a-slow-step.md for the measurements.

(The middleware's receive time would tell it exactly, but rclpy Jazzy's events executor fails on a
callback that takes the message info: "SystemError: null argument to internal routine".)

Times are a monotonic clock's [ns].
"""
from __future__ import annotations

QUEUED_GAP = 300_000     # ns: a callback that starts this soon after the last one ended was queued


class BacklogGuard:
    """Which callbacks of one subscription to run (ROS-free). ``dropped``: messages dropped so far;
    ``processed``: those processed."""

    def __init__(self, gap: int = QUEUED_GAP):
        if gap <= 0:
            raise ValueError(f"gap = {gap} is not valid: expected > 0 ns")
        self.gap = int(gap)
        self._last_end = None         # when the last callback ended [ns]
        self.dropped = 0
        self.processed = 0

    def admit(self, start: int) -> bool:
        """Whether the callback starting at ``start`` [ns] is to process its message: not if it
        starts within ``gap`` of the last callback's end (it was queued; dropped, counted). Every
        callback, admitted or not, ends with :meth:`done`."""
        if self._last_end is not None and start - self._last_end < self.gap:
            self.dropped += 1
            return False
        self.processed += 1
        return True

    def done(self, end: int):
        """The callback ended at ``end`` [ns]."""
        self._last_end = int(end)
