"""``recorder`` node: records topics into a rosbag2 directory (metadata.yaml + .mcap, storage
version 9, CDR, ros2msg schemas with full definitions, the offered QoS) that ``ros2 bag info`` and
``ros2 bag play`` on a Jazzy machine read.

Topics: ``graph.recorder.topics``; a name of the graph (see README) is recorded with its known type,
any other as ``name:pkg/msg/Type``. Output directory: the node parameter ``output`` (default
``runs/bag-<UTC time>``). Messages are stored as received (raw CDR), stamped with the node clock
(sim time when ``use_sim_time`` is set). A chunk is flushed every ``graph.recorder.flush_period``
seconds and whenever ``graph.recorder.chunk_size`` bytes wait: SIGINT and SIGTERM close the bag
cleanly, and after SIGKILL everything but the last chunk can still be read.
"""
from __future__ import annotations

import datetime
import os
import sys

from rclpy.node import Node
from rclpy.qos import QoSProfile

from soft_arm_model.parameters import ConfigError
from soft_arm_ros.contract import QOS, TYPES, message_class
from soft_arm_ros.parameters import NodeParameters
from soft_arm_ros.runtime import run_node

from .rosbag_writer import QosProfile, RosbagWriter, TopicSpec


def _qos(profile) -> QosProfile:
    return QosProfile(reliability=profile.reliability.name.lower(),
                      durability=profile.durability.name.lower(),
                      history=profile.history.name.lower(), depth=profile.depth)


class RecorderNode(Node):
    def __init__(self, config_dir: str | None = None, **node_options):
        super().__init__("recorder", allow_undeclared_parameters=True,
                         automatically_declare_parameters_from_overrides=True, **node_options)
        graph = NodeParameters(self, config_dir).graph
        output = self.get_parameter("output").value if self.has_parameter("output") else ""
        if not output:
            stamp = datetime.datetime.now(datetime.timezone.utc).strftime("%Y%m%d-%H%M%S")
            output = os.path.join("runs", f"bag-{stamp}")
        specs, subscriptions = [], []
        for entry in graph["recorder.topics"]:
            name, _, type_name = entry.partition(":")
            known = name if name in TYPES else name.lstrip("/")       # absolute: /clock, /diagnostics
            type_name = type_name or TYPES.get(known, "")
            if not type_name:
                raise ConfigError(f"graph.recorder.topics entry {entry!r} is not valid: expected a "
                                  f"topic of the graph ({', '.join(TYPES)}) or name:pkg/msg/Type")
            qos = QOS.get(known, QOS["tendon/reference"])
            resolved = self.resolve_topic_name(name)
            specs.append(TopicSpec(resolved, type_name, _qos(qos)))
            subscriptions.append((name, resolved, type_name, qos))
        try:
            self.writer = RosbagWriter(output, specs, chunk_size=graph["recorder.chunk_size"])
        except (OSError, ValueError, LookupError) as exc:
            raise ConfigError(f"output = {output!r} is not valid: {exc}") from None
        self.output = output
        self.count = 0
        for name, resolved, type_name, qos in subscriptions:
            deep = QoSProfile(depth=1000, reliability=qos.reliability, history=qos.history)
            self.create_subscription(message_class(type_name), name, self._writer_for(resolved), deep,
                                     raw=True)
        self.create_timer(graph["recorder.flush_period"], self.writer.flush)
        self.get_logger().info(f"recording {len(specs)} topics into {output}")

    def _writer_for(self, topic: str):
        def write(data: bytes):
            self.writer.write(topic, self.get_clock().now().nanoseconds, data)
            self.count += 1
        return write

    def close(self):
        """Close the bag (idempotent): summary, footer and final metadata.yaml."""
        self.writer.close()


def main(args=None) -> int:
    return run_node(RecorderNode, "recorder", args)


if __name__ == "__main__":
    sys.exit(main())
