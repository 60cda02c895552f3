"""Deterministic execution of nodes composed in one process: delivery in waves.

DDS orders messages per topic, not across topics, so two runs of a graph can interleave callbacks
differently. In a wave executor every ``publish`` of the composed nodes is held back; a wave
publishes everything held and spins until each message has reached every in-process subscription
of its topic; what the callbacks publish meanwhile forms the next wave. The order in which a node
sees its inputs is then fixed by the graph's causality, and with a lockstep simulator (one step per
command) two runs with the same seed exchange the same messages.
"""
from __future__ import annotations

import time

from rclpy.executors import SingleThreadedExecutor
from rclpy.subscription import Subscription


class DeliveryTimeout(RuntimeError):
    """A wave's messages did not all arrive (lost on the way, or a subscriber is missing)."""


class WaveExecutor:
    """Runs ``nodes`` in waves. ``timeout`` [s]: the longest a wave may take to be delivered.

    Subscriptions are served directly (their messages taken and their callbacks called in node
    order), which is much cheaper than a full executor pass per message; timers run when
    :meth:`spin_timers` is called.
    """

    def __init__(self, nodes, timeout: float = 5.0):
        self.executor = SingleThreadedExecutor()
        self.nodes = list(nodes)
        self.timeout = timeout
        self.held = []
        self.waves = 0
        for node in self.nodes:
            self.executor.add_node(node)
        self._index_subscriptions()
        for node in self.nodes:
            for pub in node.publishers:
                if pub.topic_name in ("/parameter_events", "/rosout"):
                    continue
                pub.publish = self._holding(pub, pub.publish)

    def _holding(self, pub, publish):
        def held(msg):
            self.held.append((pub, publish, msg))
        return held

    def _index_subscriptions(self):
        self._subscriptions = {}
        for node in self.nodes:
            for sub in node.subscriptions:
                self._subscriptions.setdefault(sub.topic_name, []).append(sub)

    def spin_timers(self, timeout_sec: float = 0.0):
        """Let timers and anything else ready run once (e.g. a simulator's start-up timer, the
        recorder's subscribing to the publishers it found)."""
        self.executor.spin_once(timeout_sec=timeout_sec)
        self._index_subscriptions()

    def wave(self) -> int:
        """Deliver the held messages; returns how many were published."""
        batch, self.held = self.held, []
        waiting = []
        for pub, publish, msg in batch:
            publish(msg)
            waiting.extend(self._subscriptions.get(pub.topic_name, ()))
        deadline = time.monotonic() + self.timeout
        while waiting:
            left = []
            for sub in waiting:
                with sub.handle:
                    taken = sub.handle.take_message(sub.msg_type, sub.raw)
                if taken is None:
                    left.append(sub)
                elif sub._callback_type is Subscription.CallbackType.MessageOnly:
                    sub.callback(taken[0])
                else:
                    sub.callback(*taken)                    # message and message info
            waiting = left
            if waiting and time.monotonic() > deadline:
                raise DeliveryTimeout(f"{len(waiting)} deliveries of wave {self.waves} did not "
                                      f"arrive within {self.timeout} s (topics: "
                                      f"{sorted({s.topic_name for s in waiting})})")
        self.waves += 1
        return len(batch)

    def shutdown(self):
        for node in self.nodes:
            self.executor.remove_node(node)
        self.executor.shutdown()
