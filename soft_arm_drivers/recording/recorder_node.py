"""``recorder`` node: records topics into a rosbag2 directory (metadata.yaml + .mcap, storage
version 9, CDR, ros2msg schemas with full definitions, the offered QoS) that ``ros2 bag info`` and
``ros2 bag play`` on a Jazzy machine read.

Topics: ``graph.recorder.topics``; a name of the graph (see README) is recorded with its known type,
any other as ``name:pkg/msg/Type``. Output directory: the node parameter ``output`` (default
``runs/bag-<UTC time>``).

Subscriptions adapt to the publishers, as rosbag2's do (:mod:`.adaptive_qos`): every
``graph.recorder.discovery_period`` the publishers of each topic are counted, and looked up
(``get_publishers_info_by_topic``) when their number changed or the middleware reported an
offer the subscription does not match (a publisher that replaced another within a period); a
topic is subscribed once one appears, reliable / transient local only when every publisher offers
it (so a best-effort publisher is recorded whatever the graph's table says, and a latched goal
published before the recorder started is recorded), and subscribed again, to a weaker profile,
when a publisher appears that the subscription does not match. The bag's topic metadata (what
``ros2 bag play`` offers again) holds the graph's QoS of each topic
(:data:`~soft_arm_ros.contract.QOS`): its channels are written before any publisher is seen, and
readers match the two.

Time stamps, as rosbag2's: the receive time (the middleware's ``received_timestamp``; the node clock
when ``use_sim_time`` is set, so that the bag runs on the simulator's time) is the MCAP log time, and
the publisher's ``source_timestamp`` (system time) the publish time. Messages are stored as received
(raw CDR). Messages the recorder did not receive (gaps in a publisher's sequence numbers) are counted
per topic, logged as they are found (at most once a second), stored in ``metadata.yaml``'s ``custom_data``
(``soft_arm.lost_messages``) and reported when the bag is closed.

A chunk is flushed every ``graph.recorder.flush_period`` seconds and whenever
``graph.recorder.chunk_size`` bytes wait: SIGINT and SIGTERM close the bag cleanly, and after SIGKILL
everything but the last chunk can still be read.
"""
from __future__ import annotations

import datetime
import json
import math
import os
import sys
import time

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


class _Topic:
    """One recorded topic: its name as given and resolved, message class, the subscription and its
    profile (None until a publisher appears), how many publish on it, whether the middleware
    reported an offer the subscription does not match since the last look-up."""

    def __init__(self, name: str, resolved: str, message_type):
        self.name, self.resolved, self.message_type = name, resolved, message_type
        self.subscription, self.profile, self.publishers = None, None, 0
        self.unmatched = False


class RecorderNode(Node):
    def __init__(self, config_dir: str | None = None, **node_options):
        super().__init__("recorder", allow_undeclared_parameters=True,
                         automatically_declare_parameters_from_overrides=True, **node_options)
        graph = NodeParameters(self, config_dir).graph
        output = self.get_parameter("output").value if self.has_parameter("output") else ""
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
        self.count = 0
        self.losses = LossCounter()
        self._loss_warned = -math.inf             # monotonic time [s] of the last loss warning
        self._sim_time = self.get_parameter("use_sim_time").value
        self.discover()
        # on the wall clock: under use_sim_time the simulator's clock starts only once it is recorded
        wall = Clock(clock_type=ClockType.STEADY_TIME)
        self.create_timer(graph["recorder.discovery_period"], self.discover, clock=wall)
        self.create_timer(graph["recorder.flush_period"], self.flush, clock=wall)
        self.get_logger().info(f"recording {len(specs)} topics into {output}")

    def discover(self):
        """Subscribe to the topics whose publishers appeared, again where a new one's offer does
        not match the subscription (:func:`~.adaptive_qos.resubscription`)."""
        for topic in self.topics.values():
            if not topic.unmatched and self.count_publishers(topic.resolved) == topic.publishers:
                continue     # the same publishers as at the last look-up (the look-up costs more)
            topic.unmatched = False
            offered = [to_profile(info.qos_profile)
                       for info in self.get_publishers_info_by_topic(topic.resolved)]
            topic.publishers = len(offered)
            profile = resubscription(topic.profile, offered)
            if profile is None:
                continue
            if topic.subscription is not None:
                self.destroy_subscription(topic.subscription)
                self.get_logger().warning(
                    f"{topic.resolved}: a publisher offers {offered} which the subscription "
                    f"({topic.profile.reliability.value}, {topic.profile.durability.value}) does not "
                    f"match: subscribing again {profile.reliability.value}, {profile.durability.value}")
            topic.profile = profile
            topic.subscription = self.create_subscription(
                topic.message_type, topic.name, self._writer_for(topic), to_rclpy(profile), raw=True,
                # a publisher the subscription does not match: looked up at the next discovery,
                # even if the number is unchanged (it replaced another within a period)
                event_callbacks=SubscriptionEventCallbacks(
                    incompatible_qos=lambda _, topic=topic: setattr(topic, "unmatched", True)))

    def unsubscribed(self, published) -> list:
        """The recorded topics among ``published`` (resolved names) not subscribed yet."""
        return sorted(t for t in published if t in self.topics and self.topics[t].subscription is None)

    def _writer_for(self, topic: _Topic):
        def write(data: bytes, info: dict):
            received = self.get_clock().now().nanoseconds if self._sim_time else info["received_timestamp"]
            self.writer.write(topic.resolved, received, data,
                              publish_time_ns=info.get("source_timestamp") or received)
            self.count += 1
            lost = self.losses.received(topic.resolved, info.get("publication_sequence_number"),
                                        topic.publishers)
            if lost and time.monotonic() - self._loss_warned >= LOSS_WARNING_PERIOD:
                # throttled here: rclpy's own throttle inspects the caller's frame on every call,
                # which costs a recorder that is already losing messages more of them
                self._loss_warned = time.monotonic()
                self.get_logger().warning(f"{topic.resolved}: {lost} messages not received (publisher "
                                          f"sequence gap; {self.losses.total} lost in all)")
        return write

    def _store_losses(self):
        self.writer.set_custom_data("soft_arm.lost_messages", json.dumps(self.losses.lost, sort_keys=True))

    def flush(self):
        """Write the open chunk and the metadata, with the losses so far."""
        self._store_losses()
        self.writer.flush()

    def close(self):
        """Close the bag (idempotent): summary, footer and final metadata.yaml; report the losses."""
        if self.losses.total:
            self.get_logger().warning(f"{self.losses.total} messages were not received: "
                                      + ", ".join(f"{t} {n}" for t, n in sorted(self.losses.lost.items())))
        self._store_losses()
        self.writer.close()


def main(args=None) -> int:
    # rclpy Jazzy's EventsExecutor fails on a callback that takes the message info ("SystemError:
    # null argument to internal routine"), and the recorder needs the info's time stamps
    return run_node(RecorderNode, "recorder", args, executor_factory=SingleThreadedExecutor)


if __name__ == "__main__":
    sys.exit(main())
