"""``mocap_bridge`` node: the rig's NatNet motion capture on ``mocap/markers`` and ``mocap/tip``.

Publishes what the simulator publishes in its place: ``mocap/markers`` (geometry_msgs/PoseArray in
``arm_base``, the arm's markers base to tip, identity orientations) and ``mocap/tip``
(PoseStamped, the last marker), both stamped at mid-exposure on the node's clock, best effort,
depth 1; and once a second ``/diagnostics`` (diagnostic_msgs/DiagnosticArray: connection state and
the bridge's counters). A thread waits on the NatNet sockets and publishes each frame as it
arrives; frames with an occluded or missing marker are not published (see
:mod:`soft_arm_drivers.mocap.mocap_bridge`).

Parameters: ``rig.mocap.*`` of ``config/mocap.yaml`` overlaid with the node's own parameters
(``--params-file``, ``-p rig.mocap.command_port:=1510``); the number of marker ids must match
``arm.markers.positions`` of ``config/arm.yaml`` (with the node's ``arm.*`` overrides). A bad value,
or sockets that cannot be bound, stop the node with the key, the value and what is allowed (exit
status 2). The rig runs on the system clock (no ``use_sim_time``).
"""
from __future__ import annotations

import os
import sys
import threading

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PoseArray, PoseStamped
from rclpy.node import Node

from soft_arm_model.parameters import ConfigError
from soft_arm_ros.contract import QOS, TOPICS
from soft_arm_ros.conversions import pose_array, pose_stamped, seconds_to_stamp
from soft_arm_ros.parameters import NodeParameters, parameter_overrides
from soft_arm_ros.runtime import run_node

from .bridge_config import MOCAP_SCHEMA, NAMESPACE, BridgeConfig, bridge_config, mocap_values
from .mocap_bridge import MocapBridge

DIAGNOSTICS_TOPIC = "/diagnostics"
DIAGNOSTICS_PERIOD = 1.0   # s
_POLL_TIMEOUT = 0.05       # s, how long the receive thread waits before checking for shutdown


def load_node_config(node, config_dir: str | None = None) -> BridgeConfig:
    """``rig.mocap`` of ``mocap.yaml`` with the node's parameters, checked against the arm's markers;
    each value declared read-only with its description and range
    (:class:`~soft_arm_ros.parameters.NodeParameters`)."""
    params = NodeParameters(node, config_dir)
    overrides = {f"mocap.{k}": v for k, v in parameter_overrides(node, "rig.mocap").items()}
    values = mocap_values(os.path.join(params.config_dir, "mocap.yaml"), overrides)
    config = bridge_config(values)
    params.describe(NAMESPACE, MOCAP_SCHEMA, values)
    n = len(params.arm.marker_positions)
    if len(config.ids) != n:
        raise ConfigError(f"{NAMESPACE}.mocap.markers.ids = {list(config.ids)} is not valid: expected "
                          f"{n} ids, one per marker of arm.markers.positions, base to tip")
    return config


class MocapBridgeNode(Node):
    def __init__(self, config_dir: str | None = None, **node_options):
        super().__init__("mocap_bridge", allow_undeclared_parameters=True,
                         automatically_declare_parameters_from_overrides=True, **node_options)
        self.config = c = load_node_config(self, config_dir)
        try:
            self.bridge = MocapBridge(c, clock=self.now)
        except OSError as exc:
            raise ConfigError(f"{NAMESPACE}.mocap.local_address = {c.local_address!r} / data_port = "
                              f"{c.data_port} is not valid: cannot open the NatNet sockets ({exc})") from None
        self.markers_pub = self.create_publisher(PoseArray, TOPICS["markers"], QOS["mocap/markers"])
        self.tip_pub = self.create_publisher(PoseStamped, TOPICS["tip"], QOS["mocap/tip"])
        self.diagnostics_pub = self.create_publisher(DiagnosticArray, DIAGNOSTICS_TOPIC, 10)
        self.published = 0
        self.last_latency = float("nan")
        self._published_at_last_report = 0
        self.create_timer(DIAGNOSTICS_PERIOD, self.publish_diagnostics)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._receive, name="natnet", daemon=True)
        self._thread.start()
        group = f", multicast {c.multicast_group}" if c.multicast else ""
        self.get_logger().info(
            f"mocap_bridge ready: NatNet server {c.server_address}:{c.command_port}{group}, "
            f"{c.source} {list(c.ids)} base to tip, frames on {self.bridge.command_address} and "
            f"{self.bridge.data_address}")

    def now(self) -> float:
        """The node's clock [s]: the time base of the published stamps."""
        return self.get_clock().now().nanoseconds * 1e-9

    def _receive(self):
        """The receive thread: wait for datagrams, publish each frame. It ends with :meth:`close`
        or, quietly, when the context is shut down under it (Ctrl-C)."""
        self.bridge.connect()
        while not self._stop.is_set():
            for frame in self.bridge.poll(_POLL_TIMEOUT):
                try:
                    self.markers_pub.publish(pose_array(frame.markers, frame.stamp))
                    self.tip_pub.publish(pose_stamped(frame.markers[-1], frame.stamp))
                except RuntimeError:        # rclpy's RCLError: publisher's context is invalid
                    if self.context.ok():
                        raise
                    return
                self.published += 1
                self.last_latency = frame.latency

    def status(self, fresh: int) -> DiagnosticStatus:
        """The bridge's state and counters as one DiagnosticStatus; ``fresh``: frames published in
        the last diagnostics period."""
        b, c = self.bridge, self.config
        version = f"{b.version.major}.{b.version.minor}" if b.version else ""
        level, message = DiagnosticStatus.OK, f"streaming NatNet {version}"
        if not self._thread.is_alive():
            level, message = DiagnosticStatus.ERROR, "the receive thread stopped (see the log)"
        elif b.state == "unsupported":
            level, message = DiagnosticStatus.ERROR, b.note
        elif b.state != "streaming":
            level, message = DiagnosticStatus.WARN, f"{b.state} {b.note}".strip()
        elif fresh == 0:
            level, message = DiagnosticStatus.WARN, "no complete frame in the last period " \
                                                    "(occluded or missing markers)"
        values = {"state": b.state, "note": b.note, "natnet_version": version,
                  "server": b.server_info.app_name if b.server_info else "",
                  "published": self.published, "rate_hz": fresh / DIAGNOSTICS_PERIOD,
                  "latency_ms": 1e3 * self.last_latency, **b.counters}
        return DiagnosticStatus(level=level, name="mocap_bridge: NatNet", message=message,
                                hardware_id=f"natnet://{c.server_address}:{c.command_port}",
                                values=[KeyValue(key=k, value=str(v)) for k, v in values.items()])

    def publish_diagnostics(self):
        msg = DiagnosticArray()
        seconds_to_stamp(msg.header.stamp, self.now())
        published = self.published
        msg.status.append(self.status(published - self._published_at_last_report))
        self._published_at_last_report = published
        self.diagnostics_pub.publish(msg)

    def close(self):
        """Stop the receive thread and close the sockets (run_node calls this on the way out)."""
        self._stop.set()
        self._thread.join(timeout=2.0)
        self.bridge.close()


def main(args=None) -> int:
    return run_node(MocapBridgeNode, "mocap_bridge", args)


if __name__ == "__main__":
    sys.exit(main())
