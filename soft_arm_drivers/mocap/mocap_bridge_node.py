"""``mocap_bridge`` node: the rig's NatNet motion capture on ``mocap/markers`` and ``mocap/tip``.

Publishes what the simulator publishes in its place: ``mocap/markers`` (geometry_msgs/PoseArray in
``arm_base``, the arm's markers base to tip, identity orientations) and ``mocap/tip``
(PoseStamped, the last marker, when it was seen), both stamped at mid-exposure on the node's clock,
best effort, depth 1; and once a second ``/diagnostics`` (diagnostic_msgs/DiagnosticArray: lifecycle and
connection state, the bridge's counters). A thread waits on the NatNet sockets and publishes each
frame as it arrives; a marker that is occluded or missing goes out as an invalid marker of its frame
(NaN position, zero quaternion: :func:`soft_arm_ros.conversions.pose_array`), and a frame with no
marker seen is not published (see :mod:`soft_arm_drivers.mocap.mocap_bridge`).

A managed (lifecycle) node (:mod:`soft_arm_ros.lifecycle`): ``configure`` opens the sockets and
waits for the Motive server's answer to the connect request (refused, sockets closed, when none
comes within ``rig.mocap.timeout``), then the thread runs; ``activate`` publishes the frames (an
inactive bridge keeps the stream and counts its frames, publishes none); ``deactivate`` stops
publishing; ``cleanup`` and ``shutdown`` stop the thread and close the sockets.

Parameters: ``rig.mocap.*`` of ``config/mocap.yaml`` overlaid with the node's own parameters
(``--params-file``, ``-p rig.mocap.command_port:=1510``); the number of marker ids must match
``arm.markers.positions`` of ``config/arm.yaml`` (with the node's ``arm.*`` overrides). A bad value,
or sockets that cannot be bound, stop the node with the key, the value and what is allowed (exit
status 2). The rig runs on the system clock (no ``use_sim_time``).
"""
from __future__ import annotations

import gc
import os
import sys
import threading
import time

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PoseArray, PoseStamped

from soft_arm_model.parameters import ConfigError
from soft_arm_ros.contract import QOS, TOPICS
from soft_arm_ros.lifecycle import SUCCESS, ManagedHardwareNode, transition
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


class MocapBridgeNode(ManagedHardwareNode):
    """Created unconfigured: the sockets open at ``configure``."""

    def __init__(self, config_dir: str | None = None, **node_options):
        super().__init__("mocap_bridge", allow_undeclared_parameters=True,
                         automatically_declare_parameters_from_overrides=True, **node_options)
        self.config = load_node_config(self, config_dir)
        self.bridge: MocapBridge | None = None
        self.markers_pub = self.create_publisher(PoseArray, TOPICS["markers"], QOS["mocap/markers"])
        self.tip_pub = self.create_publisher(PoseStamped, TOPICS["tip"], QOS["mocap/tip"])
        self.diagnostics_pub = self.create_publisher(DiagnosticArray, DIAGNOSTICS_TOPIC, 10)
        self.published = self.received = 0
        self.last_latency = float("nan")
        self._received_at_last_report = 0
        self.create_timer(DIAGNOSTICS_PERIOD, self.publish_diagnostics)
        self._stop = threading.Event()
        self._publishing = threading.Event()
        self._thread: threading.Thread | None = None
        # the receive thread's end by an error, or its not stopping when released: the process then
        # exits with status 1 (run_node), so that a run it served is no result
        self.failure: BaseException | None = None
        self.get_logger().info(f"mocap_bridge unconfigured: NatNet server {self.config.server_address}:"
                               f"{self.config.command_port} (configure opens the sockets)")

    # -- lifecycle -------------------------------------------------------------------------------
    @transition
    def on_configure(self, state):
        c = self.config
        if self._thread is not None:            # released, but its receive thread never stopped
            return self.refuse("configure", "the last receive thread has not stopped (held in the "
                                            "middleware?): restart the node")
        try:
            bridge = MocapBridge(c, clock=self.now, timer=time.monotonic)
        except OSError as exc:
            return self.refuse("configure", f"{NAMESPACE}.mocap.local_address = {c.local_address!r}, "
                                            f"data_port = {c.data_port}: cannot open the NatNet "
                                            f"sockets ({exc})")
        bridge.connect()
        deadline = time.monotonic() + c.timeout
        while bridge.server_info is None and time.monotonic() < deadline:
            bridge.poll(_POLL_TIMEOUT)
        if bridge.server_info is None:
            bridge.close()
            return self.refuse("configure", f"no NatNet server answered at {c.server_address}:"
                                            f"{c.command_port} within {c.timeout:g} s (is Motive streaming?)")
        self.bridge = bridge
        # The set-up loaded the frame reader's compiled code (numba's registries, some 10^4 objects)
        # after run_node froze the process's start-up: frozen too, so that no collection in the
        # receive thread walks them (docs/decisions/0001)
        gc.collect()
        gc.freeze()
        self._stop.clear()
        self._thread = threading.Thread(target=self._receive, name="natnet", daemon=True)
        self._thread.start()
        group = f", multicast {c.multicast_group}" if c.multicast else ""
        self.get_logger().info(
            f"mocap_bridge configured: {bridge.server_info.app_name} at {c.server_address}:{c.command_port}"
            f"{group}, {c.source} {list(c.ids)} base to tip, frames on {bridge.command_address} and "
            f"{bridge.data_address} (activate to publish them)")
        return SUCCESS

    @transition
    def on_activate(self, state):
        self._publishing.set()
        return SUCCESS

    @transition
    def on_deactivate(self, state):
        self._publishing.clear()
        return SUCCESS

    def now(self) -> float:
        """The node's clock [s]: the time base of the published stamps."""
        return self.get_clock().now().nanoseconds * 1e-9

    def _receive(self):
        """The receive thread: wait for datagrams, publish each frame. It ends with :meth:`close`
        or, quietly, when the context is shut down under it (Ctrl-C); an error ends it as the node's
        :attr:`failure` (and on /diagnostics) before it is raised into the thread's log."""
        try:
            self._receive_frames()
        except BaseException as exc:
            self.failure = self.failure or RuntimeError(
                f"the receive thread stopped: {type(exc).__name__}: {exc}")
            raise

    def _receive_frames(self):
        while not self._stop.is_set():
            for frame in self.bridge.poll(_POLL_TIMEOUT):
                self.received += 1
                self.last_latency = frame.latency
                if not self._publishing.is_set():
                    continue
                try:
                    self.markers_pub.publish(pose_array(frame.markers, frame.stamp))
                    if np.all(np.isfinite(frame.markers[-1])):      # mocap/tip: seen tips only
                        self.tip_pub.publish(pose_stamped(frame.markers[-1], frame.stamp))
                except RuntimeError:        # rclpy's RCLError: publisher's context is invalid
                    if self.context.ok():
                        raise
                    return
                self.published += 1

    def status(self, fresh: int) -> DiagnosticStatus:
        """The bridge's state and counters as one DiagnosticStatus; ``fresh``: frames received in
        the last diagnostics period."""
        b, c = self.bridge, self.config
        hardware_id = f"natnet://{c.server_address}:{c.command_port}"
        lifecycle = self.lifecycle_state
        if b is None:
            return DiagnosticStatus(level=DiagnosticStatus.OK, name="mocap_bridge: NatNet",
                                    message=f"{lifecycle}: no sockets open", hardware_id=hardware_id,
                                    values=[KeyValue(key="lifecycle_state", value=lifecycle)])
        version = f"{b.version.major}.{b.version.minor}" if b.version else ""
        level, message = DiagnosticStatus.OK, f"streaming NatNet {version}" + (
            "" if lifecycle == "active" else f" ({lifecycle}: not published)")
        if not self._thread.is_alive():
            level, message = DiagnosticStatus.ERROR, "the receive thread stopped (see the log)"
        elif b.state == "unsupported":
            level, message = DiagnosticStatus.ERROR, b.note
        elif b.state != "streaming":
            level, message = DiagnosticStatus.WARN, f"{b.state} {b.note}".strip()
        elif fresh == 0:
            level, message = DiagnosticStatus.WARN, "no frame in the last period " \
                                                    "(every marker occluded or missing)"
        values = {"lifecycle_state": lifecycle, "state": b.state, "note": b.note,
                  "natnet_version": version, "server": b.server_info.app_name if b.server_info else "",
                  "received": self.received, "published": self.published,
                  "rate_hz": fresh / DIAGNOSTICS_PERIOD, "latency_ms": 1e3 * self.last_latency,
                  "unseen": b.unseen, **b.counters}
        return DiagnosticStatus(level=level, name="mocap_bridge: NatNet", message=message,
                                hardware_id=hardware_id,
                                values=[KeyValue(key=k, value=str(v)) for k, v in values.items()])

    def publish_diagnostics(self):
        msg = DiagnosticArray()
        seconds_to_stamp(msg.header.stamp, self.now())
        received = self.received
        msg.status.append(self.status(received - self._received_at_last_report))
        self._received_at_last_report = received
        self.diagnostics_pub.publish(msg)

    def release(self):
        """Stop publishing and the receive thread, close the sockets; idempotent."""
        self._publishing.clear()
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            if self._thread.is_alive():         # kept: a configure refuses to start a second one
                self.failure = self.failure or RuntimeError("the receive thread did not stop within 2 s")
                self.get_logger().error("the receive thread did not stop within 2 s: the node has failed")
            else:
                self._thread = None
        bridge, self.bridge = self.bridge, None
        if bridge is not None:
            bridge.close()


def main(args=None) -> int:
    return run_node(MocapBridgeNode, "mocap_bridge", args)


if __name__ == "__main__":
    sys.exit(main())
