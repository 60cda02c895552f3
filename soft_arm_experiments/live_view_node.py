"""``live_view`` node: any run, on the simulator or the rig, as a live 3D view in the Foxglove app.

Subscribes ``arm/shape`` (the simulator's backbone; on the rig, where there is none,
``estimate/shape``), ``mocap/markers``, ``estimate/markers`` with ``estimate/tip``,
``arm/configuration_reference`` (the goal's target), ``tendon/state``, ``tendon/reference`` and
``/diagnostics``, and serves what :class:`~.live_view.LiveView` makes of them on a Foxglove
WebSocket server (the Foxglove SDK): ``/view/scene`` at ``view.rate`` and the series
``/view/tendons``, ``/view/task`` and ``/view/diagnostics`` at the same rate, the latest of each. Open
``ws://HOST:PORT`` in the Foxglove app (Open connection, Foxglove WebSocket); the layout
``config/foxglove_layout.json`` arranges the panels.

The server binds ``view.host`` (default 127.0.0.1: this computer only; an address other computers
reach needs ``view.remote: true``) on ``view.port`` (0: a free one, logged). A viewer that reads
slower than the view is sent loses its oldest messages beyond ``view.backlog``; nothing in the
graph waits for it. With ``view.record`` the same channels go into an MCAP file as well, which the
Foxglove app opens with the same layout after the run. Parameters: ``view.*`` of
``config/view.yaml``, overlaid as every node's.
"""
from __future__ import annotations

import sys
import time

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseArray, PoseWithCovarianceStamped
from rclpy.node import Node
from sensor_msgs.msg import JointState
from soft_arm_interfaces.msg import ConfigurationReference
from visualization_msgs.msg import MarkerArray

from soft_arm_ros.contract import QOS, TOPICS
from soft_arm_ros.conversions import markers_of, stamp_to_seconds
from soft_arm_ros.parameters import NodeParameters
from soft_arm_ros.runtime import run_node

from .live_view import VIEW_SCHEMA, LiveServer, LiveView

SHAPE_FRESH = 1.0       # s (wall): arm/shape this recent is the backbone; otherwise estimate/shape


class LiveViewNode(Node):
    def __init__(self, config_dir: str | None = None, **node_options):
        super().__init__("live_view", allow_undeclared_parameters=True,
                         automatically_declare_parameters_from_overrides=True, **node_options)
        params = NodeParameters(self, config_dir)
        view = params.section("view", VIEW_SCHEMA)
        geometry = params.arm.geometry
        self.view = LiveView(geometry.base_radius, geometry.tip_radius, view["trail"])
        self.live = LiveServer(view["host"], view["port"], view["remote"], view["backlog"], view["record"])
        self.latest = {}                 # series name -> the latest value, logged at the view's rate
        self.shape_at = -np.inf          # monotonic time [s] of the last arm/shape
        subscribe = self.create_subscription
        subscribe(MarkerArray, TOPICS["shape"], self.on_shape, QOS["arm/shape"])
        subscribe(MarkerArray, TOPICS["estimate_shape"], self.on_estimate_shape, QOS["estimate/shape"])
        subscribe(PoseArray, TOPICS["markers"], self.on_markers, QOS["mocap/markers"])
        subscribe(PoseArray, TOPICS["estimate"], self.on_estimate, QOS["estimate/markers"])
        subscribe(PoseWithCovarianceStamped, TOPICS["estimate_tip"], self.on_tip, QOS["estimate/tip"])
        subscribe(ConfigurationReference, TOPICS["configuration"], self.on_reference,
                  QOS["arm/configuration_reference"])
        subscribe(JointState, TOPICS["state"], self.on_state, QOS["tendon/state"])
        subscribe(JointState, TOPICS["reference"], self.on_tendon_reference, QOS["tendon/reference"])
        subscribe(DiagnosticArray, "/diagnostics", self.on_diagnostics, 10)
        self.create_timer(1.0 / view["rate"], self.publish)
        self.get_logger().info(f"live view on {self.live.address} (open it in the Foxglove app)")

    def on_shape(self, msg: MarkerArray):
        if msg.markers:
            self.shape_at = time.monotonic()
            self.view.take_backbone(stamp_to_seconds(msg.markers[0].header.stamp),
                                    [(p.x, p.y, p.z) for p in msg.markers[0].points])

    def on_estimate_shape(self, msg: MarkerArray):
        if msg.markers and time.monotonic() > self.shape_at + SHAPE_FRESH:
            self.view.take_backbone(stamp_to_seconds(msg.markers[0].header.stamp),
                                    [(p.x, p.y, p.z) for p in msg.markers[0].points])

    def on_markers(self, msg: PoseArray):
        self.view.take_mocap(stamp_to_seconds(msg.header.stamp), markers_of(msg))
        self.latest["task"] = self.view.task()

    def on_estimate(self, msg: PoseArray):
        self.view.take_estimate(stamp_to_seconds(msg.header.stamp), markers_of(msg))

    def on_tip(self, msg: PoseWithCovarianceStamped):
        self.view.tip_covariance = np.array(msg.pose.covariance, dtype=float).reshape(6, 6)[:3, :3]

    def on_reference(self, msg: ConfigurationReference):
        self.view.take_target(msg.labels, msg.target)

    def on_state(self, msg: JointState):
        tendons = self.latest.setdefault("tendons", {})
        tendons.update({"t": stamp_to_seconds(msg.header.stamp), "names": list(msg.name),
                        "shortening": list(msg.position), "rate": list(msg.velocity),
                        "tension": list(msg.effort)})

    def on_tendon_reference(self, msg: JointState):
        self.latest.setdefault("tendons", {})["reference"] = list(msg.position)

    def on_diagnostics(self, msg: DiagnosticArray):
        statuses = self.latest.setdefault("diagnostics", {})
        for status in msg.status:
            statuses[status.name] = {"level": int.from_bytes(status.level, "little")
                                     if isinstance(status.level, bytes) else int(status.level),
                                     "message": status.message,
                                     "values": {kv.key: kv.value for kv in status.values}}

    def publish(self):
        """The scene and the latest of each series, to whoever is connected."""
        self.live.publish(self.view, self.latest)

    @property
    def published(self) -> int:
        return self.live.published

    def close(self):
        self.live.close()


def main(args=None) -> int:
    return run_node(LiveViewNode, "live_view", args)


if __name__ == "__main__":
    sys.exit(main())
