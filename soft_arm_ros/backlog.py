"""A subscription whose callback can outlast its messages' period, kept from building a backlog.

rclpy's events executor queues one event per message received and serves the events in order,
each taking the newest message a depth-1 subscription holds. When the callback takes longer than
the period (a CLIK step on a loaded computer), every event still finds a newer message, the queue
grows by the difference, and whatever else the node waits for (a goal, a timer) waits behind it:
seconds, and a depth-1 goal can be overwritten by the next before it is taken.

A :class:`Backlog` ends every callback by taking, and dropping, what arrived while it ran (through
the subscription's own take, which finds nothing when nothing came): the events queued for those
messages then find nothing to take and run no callback, and the next message processed is the next
to arrive. Nothing is dropped while the callback keeps up and starts on its message's arrival
(nothing arrives while it runs; another callback or the GIL delaying its start by more than the
period minus its cost costs a frame), and the rule needs no clock: which event was queued is told
by what the subscription holds, not by how soon its callback started, which a loaded computer
stretches. See
docs/decisions/0006-clik-node-drops-frames-queued-behind-a-slow-step.md.
"""
from __future__ import annotations

MAX_TAKES = 64     # takes per drain at most: no subscription of the graph holds this many messages


class Backlog:
    """The counts of one subscription's messages (ROS-free): ``processed`` (:meth:`processed_one`)
    and ``dropped`` (taken by :meth:`drain`)."""

    def __init__(self):
        self.processed = 0
        self.dropped = 0

    def processed_one(self):
        """A callback processed its message."""
        self.processed += 1

    def drain(self, take):
        """Take and drop what arrived while the last callback ran: ``take()`` returns the next
        message the subscription holds, None when it holds none; at most :data:`MAX_TAKES`.
        Returns the newest message dropped (None: nothing had arrived)."""
        newest = None
        for _ in range(MAX_TAKES):
            message = take()
            if message is None:
                break
            newest = message
            self.dropped += 1
        return newest
