"""``recorder`` node: records topics into a rosbag2 directory (metadata.yaml + .mcap, storage
version 9, CDR, ros2msg schemas with full definitions, the offered QoS) that ``ros2 bag info`` and
``ros2 bag play`` on a Jazzy machine read.

Topics: ``graph.recorder.topics``; a name of the graph (see README) is recorded with its known type,
any other as ``name:pkg/msg/Type``. Output directory: the node parameter ``output`` (default
``runs/bag-<UTC time>``).

Subscriptions adapt to the publishers, as rosbag2's do (:mod:`.adaptive_qos`): every
``graph.recorder.discovery_period`` the publishers of each topic are counted, and looked up
(``get_publishers_info_by_topic``) when their number changed or when the subscription, given
:data:`MATCH_TIME` to match them, matches fewer (a publisher whose offer it does not match
replaced another within a period); a
topic is subscribed once one appears, reliable / transient local only when every publisher offers
it (so a best-effort publisher is recorded whatever the graph's table says, and a latched goal
published before the recorder started is recorded), and subscribed again, to a weaker profile,
when a publisher appears that the subscription does not match. The bag's topic metadata (what
``ros2 bag play`` offers again) holds the graph's QoS of each topic
(:data:`~soft_arm_ros.contract.QOS`): its channels are written before any publisher is seen, and
readers match the two.

Messages are not handed to the recorder one callback at a time (an executor's wait and take, some
0.25 ms of CPU per message in rclpy, would hold the recorder at 40 % of a core for the emulated
rig's 1600 messages a second; docs/decisions/0007-recorder-takes-messages-in-batches.md): they wait
in each subscription's history (1000 deep, 2 s of a 500 Hz stream) and every
``graph.recorder.take_period`` the node takes all of them (:class:`PolledGroup` keeps the executor
off the subscriptions) and writes them in the order they were received, holding back those received
since the previous take so that a message still on its way into a history is not written after a
later one. (The composed graph's wave
executor, which delivers to each subscription itself, calls their callbacks, and :meth:`take` to
write.)

Time stamps, as rosbag2's: the receive time (the middleware's ``received_timestamp``; under
``use_sim_time`` the node clock at the take less the wall time the message waited, or at the
callback, so that the bag runs on the simulator's time) is the MCAP log time, and the publisher's
``source_timestamp`` (system time) the publish time. Messages are stored as received (raw CDR).
Messages the recorder did not receive (gaps in a publisher's sequence numbers) are counted per
topic, logged as they are found (at most once a second), stored in ``metadata.yaml``'s
``custom_data`` (``soft_arm.lost_messages``) and reported when the bag is closed.

A chunk is flushed every ``graph.recorder.flush_period`` seconds and whenever
``graph.recorder.chunk_size`` bytes wait: SIGINT and SIGTERM close the bag cleanly (everything
received until then written), and after SIGKILL everything but the last chunk and the messages not
yet taken can still be read.
"""
from __future__ import annotations

import bisect
import datetime
import json
import math
import os
import sys
import time

from rclpy.callback_groups import CallbackGroup
from rclpy.clock import Clock, ClockType
from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from soft_arm_model.parameters import ConfigError
from soft_arm_ros.contract import QOS, TYPES, message_class
from soft_arm_ros.parameters import NodeParameters
from soft_arm_ros.runtime import run_node

from .adaptive_qos import LossCounter, resubscription
from .rosbag_writer import QosProfile, RosbagWriter, TopicSpec


def to_profile(profile: QoSProfile) -> QosProfile:
    """The bag's QoS profile of an rclpy one. System-default and unknown policies read as the rmw
    defaults (reliable, volatile, keep last); discovery does not carry a publisher's history and
    depth (unknown, 0), which read as keep last 1 (only reliability and durability decide how the
    recorder subscribes)."""
    def name(policy, default):
        text = policy.name.lower()
        return default if text in ("system_default", "unknown") else text
    return QosProfile(reliability=name(profile.reliability, "reliable"),
                      durability=name(profile.durability, "volatile"),
                      history=name(profile.history, "keep_last"), depth=max(int(profile.depth), 1))


def to_rclpy(profile: QosProfile) -> QoSProfile:
    return QoSProfile(depth=profile.depth, history=HistoryPolicy.KEEP_LAST,
                      reliability=ReliabilityPolicy[profile.reliability.name],
                      durability=DurabilityPolicy[profile.durability.name])


LOSS_WARNING_PERIOD = 1.0    # s, at most one warning of lost messages per period
MATCH_TIME = 0.5             # s a new subscription has to match the publishers it was made for


class PolledGroup(CallbackGroup):
    """A callback group no executor waits on or runs anything of: its subscriptions' messages stay in
    their histories for the node to take. A subscription's QoS event handlers join its group, so
    give them none (``SubscriptionEventCallbacks(use_default_callbacks=False)``) rather than
    handlers that never run. (Handlers in a wait set would cost the recorder most of its CPU: with
    rmw_fastrtps every message wakes a wait set holding a subscription's events, and rclpy's
    executor, finding nothing ready, builds its wait set again, some 14 times per timer callback.)"""

    def can_execute(self, entity) -> bool:
        return False

    def beginning_execution(self, entity) -> bool:
        return False

    def ending_execution(self, entity) -> None:
        pass


class _Topic:
    """One recorded topic: its name as given and resolved, message class, the subscription and its
    profile (None until a publisher appears) and when it was made [s, monotonic], how many publish
    on it, whether a look-up found a publisher no profile of the recorder's matches (warned of once)."""

    def __init__(self, name: str, resolved: str, message_type):
        self.name, self.resolved, self.message_type = name, resolved, message_type
        self.subscription, self.profile, self.publishers = None, None, 0
        self.subscribed_at = -math.inf
        self.unmatchable_warned = False

    def misses_a_publisher(self, publishers: int, now: float) -> bool:
        """Whether the subscription, made at least MATCH_TIME before ``now``, matches fewer than
        ``publishers``."""
        return (self.subscription is not None and now - self.subscribed_at >= MATCH_TIME
                and self.subscription.get_publisher_count() < publishers)


class RecorderNode(Node):
    def __init__(self, config_dir: str | None = None, **node_options):
        super().__init__("recorder", allow_undeclared_parameters=True,
                         automatically_declare_parameters_from_overrides=True, **node_options)
        params = NodeParameters(self, config_dir)
        graph = params.graph
        output = params.run_option("output")
        if not output:
            stamp = datetime.datetime.now(datetime.timezone.utc).strftime("%Y%m%d-%H%M%S")
            output = os.path.join("runs", f"bag-{stamp}")
        specs, self.topics = [], {}
        for entry in graph["recorder.topics"]:
            name, _, type_name = entry.partition(":")
            known = name if name in TYPES else name.lstrip("/")       # absolute: /clock, /diagnostics
            type_name = type_name or TYPES.get(known, "")
            if not type_name:
                raise ConfigError(f"graph.recorder.topics entry {entry!r} is not valid: expected a "
                                  f"topic of the graph ({', '.join(TYPES)}) or name:pkg/msg/Type")
            resolved = self.resolve_topic_name(name)
            # the bag's metadata holds the graph's QoS of the topic (module docstring)
            specs.append(TopicSpec(resolved, type_name, to_profile(QOS.get(known, QOS["tendon/reference"]))))
            self.topics[resolved] = _Topic(name, resolved, message_class(type_name))
        try:
            self.writer = RosbagWriter(output, specs, chunk_size=graph["recorder.chunk_size"])
        except (OSError, ValueError, LookupError) as exc:
            raise ConfigError(f"output = {output!r} is not valid: {exc}") from None
        self.output = output
        self.count = 0                            # messages received (written, or held until the next take)
        self.losses = LossCounter()
        self._loss_warned = -math.inf             # monotonic time [s] of the last loss warning
        self._sim_time = self.get_parameter("use_sim_time").value
        self._polled = PolledGroup()
        # taken, not written yet: (received [ns, wall], log time [ns], topic, data, publish time [ns])
        self._held: list = []
        self._last_take = time.time_ns()          # wall time [ns] the previous take began
        self._last_log_time = 0                   # [ns] of the message written last
        self.discover()
        # on the wall clock: under use_sim_time the simulator's clock starts only once it is recorded
        wall = Clock(clock_type=ClockType.STEADY_TIME)
        self.create_timer(graph["recorder.discovery_period"], self.discover, clock=wall)
        self.create_timer(graph["recorder.flush_period"], self.flush, clock=wall)
        self.create_timer(graph["recorder.take_period"], self.take, clock=wall)
        self.get_logger().info(f"recording {len(specs)} topics into {output}")

    def discover(self):
        """Subscribe to the topics whose publishers appeared, again where a new one's offer does
        not match the subscription (:func:`~.adaptive_qos.resubscription`)."""
        now = time.monotonic()
        for topic in self.topics.values():
            publishers = self.count_publishers(topic.resolved)
            short = topic.misses_a_publisher(publishers, now)
            if publishers == topic.publishers and not short:
                continue     # the same publishers as at the last look-up (the look-up costs more)
            self._take_waiting(topic)                # counted against the publishers they came from
            offered = [to_profile(info.qos_profile)
                       for info in self.get_publishers_info_by_topic(topic.resolved)]
            topic.publishers = len(offered)
            profile = resubscription(topic.profile, offered)
            if profile is None:
                if short and not topic.unmatchable_warned:
                    topic.unmatchable_warned = True
                    self.get_logger().warning(
                        f"{topic.resolved}: {publishers - topic.subscription.get_publisher_count()} of "
                        f"{publishers} publishers do not match the subscription, whose QoS matches "
                        f"every offer {offered} (another type?): they are not recorded")
                continue
            if topic.subscription is not None:
                self.destroy_subscription(topic.subscription)
                self.get_logger().warning(
                    f"{topic.resolved}: a publisher offers {offered} which the subscription "
                    f"({topic.profile.reliability.value}, {topic.profile.durability.value}) does not "
                    f"match: subscribing again {profile.reliability.value}, {profile.durability.value}")
            topic.profile, topic.subscribed_at = profile, now
            topic.subscription = self.create_subscription(
                topic.message_type, topic.name, self._receiver(topic), to_rclpy(profile), raw=True,
                callback_group=self._polled,
                event_callbacks=SubscriptionEventCallbacks(use_default_callbacks=False))

    def unsubscribed(self, published) -> list:
        """The recorded topics among ``published`` (resolved names) not subscribed yet."""
        return sorted(t for t in published if t in self.topics and self.topics[t].subscription is None)

    def take(self, everything: bool = False):
        """Take every message waiting in the subscriptions' histories and write, in the order they
        were received, those received before the previous take began (``everything``: all, at the
        end); the rest wait for the next take. Log times never decrease in the bag: one earlier
        than the last written (a simulator's clock slower than the wall's) is written as that."""
        began = time.time_ns()
        offset = self._sim_offset()
        for topic in self.topics.values():
            self._take_waiting(topic, offset)
        self._held.sort(key=lambda m: m[0])
        ready = len(self._held) if everything else \
            bisect.bisect_left(self._held, self._last_take, key=lambda m: m[0])
        written = 0
        try:
            for _, log_time, name, data, published in self._held[:ready]:
                self._last_log_time = max(log_time, self._last_log_time)
                self.writer.write(name, self._last_log_time, data, publish_time_ns=published)
                written += 1
        finally:
            del self._held[:written]
        self._last_take = began

    def _sim_offset(self) -> int:
        """The node clock less the wall clock [ns] under ``use_sim_time``, else 0."""
        return self.get_clock().now().nanoseconds - time.time_ns() if self._sim_time else 0

    def _take_waiting(self, topic: _Topic, offset: int | None = None):
        """Hold the messages waiting in ``topic``'s subscription, each with its log time (under
        ``use_sim_time``: the node clock now less the wall time it waited; ``offset``
        [ns]: :meth:`_sim_offset`, taken now if None)."""
        subscription = topic.subscription
        if subscription is None:
            return
        if offset is None:
            offset = self._sim_offset()
        with subscription.handle:
            while (taken := subscription.handle.take_message(topic.message_type, True)) is not None:
                data, info = taken
                self._hold(topic, data, info, max(info["received_timestamp"] + offset, 0))

    def _receiver(self, topic: _Topic):
        """The subscription's callback, for an executor that delivers to it directly (the composed
        graph's :class:`~soft_arm_experiments.lockstep.WaveExecutor`, whose time is the
        simulator's): hold the message, logged at the node clock's time."""
        def receive(data: bytes, info: dict):
            log_time = self.get_clock().now().nanoseconds if self._sim_time else info["received_timestamp"]
            self._hold(topic, data, info, log_time)
        return receive

    def _hold(self, topic: _Topic, data: bytes, info: dict, log_time: int):
        """Keep a received message until a take writes it, counting it and its losses (sequence gaps)."""
        received = info["received_timestamp"]
        published = info.get("source_timestamp") or received
        self._held.append((received, log_time, topic.resolved, data, published))
        self.count += 1
        self._count_losses(topic, info.get("publication_sequence_number"))

    def _count_losses(self, topic: _Topic, sequence):
        lost = self.losses.received(topic.resolved, sequence, topic.publishers)
        if lost and time.monotonic() - self._loss_warned >= LOSS_WARNING_PERIOD:
            # throttled here: rclpy's own throttle inspects the caller's frame on every call,
            # which costs a recorder that is already losing messages more of them
            self._loss_warned = time.monotonic()
            self.get_logger().warning(f"{topic.resolved}: {lost} messages not received (publisher "
                                      f"sequence gap; {self.losses.total} lost in all)")

    def _store_losses(self):
        self.writer.set_custom_data("soft_arm.lost_messages", json.dumps(self.losses.lost, sort_keys=True))

    def flush(self):
        """Write the open chunk and the metadata, with the losses so far."""
        self._store_losses()
        self.writer.flush()

    def close(self):
        """Write every message received until now and close the bag (idempotent): summary, footer
        and final metadata.yaml; report the losses."""
        try:
            if not self.writer.closed:
                self.take(everything=True)
        finally:
            if self.losses.total:
                self.get_logger().warning(f"{self.losses.total} messages were not received: " + ", ".join(
                    f"{t} {n}" for t, n in sorted(self.losses.lost.items())))
            self._store_losses()
            self.writer.close()


def main(args=None) -> int:
    # the executor runs only the timers (the messages are taken by the node); whether rclpy's
    # EventsExecutor keeps off a callback group's subscriptions is not documented
    return run_node(RecorderNode, "recorder", args, executor_factory=SingleThreadedExecutor)


if __name__ == "__main__":
    sys.exit(main())
