"""``live_view`` node: any run, on the simulator or the rig, as a live 3D view in the Foxglove app.

Subscribes ``arm/shape`` (the simulator's backbone; on the rig, where there is none,
``estimate/shape``; with neither, on the rig closed on the mocap alone, the arm is drawn where the
model puts it at the clik node's reference, ``arm/configuration_reference``'s q_d, and the scene's
``arm`` entity says which of the three it is), ``mocap/markers``, ``estimate/markers`` with ``estimate/tip``,
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

A viewer takes only the CPU the graph leaves, so that it cannot delay the loop:

- the process runs under SCHED_IDLE (:func:`yield_cpu`, every thread of it, and so every thread
  rclpy, the middleware and the Foxglove server start later), except for the middleware's threads
  (Fast DDS's, ``dds.*``), which go under SCHED_FIFO ``realtime.MIDDLEWARE_PRIORITY`` once the node
  is set up, like those of every other process outside the loop: the loop's writers wait on them
  (docs/decisions/0005), and one starved there would hold the motor driver's state publish.
  Where that is not permitted, nothing can lift them again, so the whole process runs at niceness
  19 instead, which still gives each thread a share of a busy CPU;
- the busy topics (``tendon/state`` at the motors' rate, the markers, the shapes, the tendon
  reference) are taken serialized (``raw``), keeping the latest bytes of each, and deserialized only
  at the view's rate (:meth:`LiveViewNode.publish`): a message the view does not show costs a copy,
  not a Python object.
"""
from __future__ import annotations

import os
import sys
import time

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseArray, PoseWithCovarianceStamped
from rclpy.node import Node
from rclpy.serialization import deserialize_message
from sensor_msgs.msg import JointState
from soft_arm_interfaces.msg import ConfigurationReference
from soft_arm_model import KINEMATICS, ArmData, OutOfDomainError, build_model, evaluate
from soft_arm_model.parameters import ConfigError
from visualization_msgs.msg import MarkerArray

from soft_arm_ros.contract import QOS, TOPICS
from soft_arm_ros.conversions import markers_of, stamp_to_seconds
from soft_arm_ros.parameters import NodeParameters
from soft_arm_ros.runtime import run_node

from . import realtime
from .live_launch import report_ready
from .live_view import VIEW_SCHEMA, LiveServer, LiveView

SHAPE_FRESH = 1.0       # s (wall): a shape this recent is the backbone (arm/shape before estimate/shape
#                         before the model at the reference)

# The topics taken serialized, the latest kept: key of TOPICS -> (message type, key of QOS)
RAW = {"shape": (MarkerArray, "arm/shape"), "estimate_shape": (MarkerArray, "estimate/shape"),
       "markers": (PoseArray, "mocap/markers"), "estimate": (PoseArray, "estimate/markers"),
       "estimate_tip": (PoseWithCovarianceStamped, "estimate/tip"),
       "state": (JointState, "tendon/state"), "reference": (JointState, "tendon/reference")}


def yield_cpu(fifo_permitted: bool | None = None) -> str:
    """Every thread of this process (and so every thread it starts from now on) under SCHED_IDLE,
    or, where its middleware threads could not be lifted above it again (SCHED_FIFO not permitted,
    :func:`~.realtime.permitted`; ``fifo_permitted`` says so instead of trying) or SCHED_IDLE is
    refused, at niceness 19. Returns the policy set: "idle" or "nice"."""
    if fifo_permitted is None:
        fifo_permitted = realtime.permitted(realtime.MIDDLEWARE_PRIORITY)
    policy = "idle" if fifo_permitted and hasattr(os, "SCHED_IDLE") else "nice"
    for tid in realtime.threads(os.getpid()):
        try:
            if policy == "idle":
                os.sched_setscheduler(tid, os.SCHED_IDLE, os.sched_param(0))
            else:
                os.setpriority(os.PRIO_PROCESS, tid, 19)      # a thread of its own on Linux
        except ProcessLookupError:
            continue                                          # ended meanwhile
        except OSError:
            policy = "nice"
            os.setpriority(os.PRIO_PROCESS, tid, 19)
    return policy


def lift_middleware():
    """This process's middleware threads (``dds.*``) under SCHED_FIFO
    ``realtime.MIDDLEWARE_PRIORITY``, as the orchestrator puts every other process's outside the
    loop; nothing where not permitted."""
    try:
        realtime.schedule(os.getpid(), realtime.MIDDLEWARE_PRIORITY, named=realtime.MIDDLEWARE_THREADS)
    except OSError:
        pass


class LiveViewNode(Node):
    def __init__(self, config_dir: str | None = None, **node_options):
        super().__init__("live_view", allow_undeclared_parameters=True,
                         automatically_declare_parameters_from_overrides=True, **node_options)
        params = NodeParameters(self, config_dir)
        view = params.section("view", VIEW_SCHEMA)
        geometry = params.arm.geometry
        self.view = LiveView(geometry.base_radius, geometry.tip_radius, view["trail"])
        try:
            self.live = LiveServer(view["host"], view["port"], view["remote"], view["backlog"],
                                   view["record"])
        except (ValueError, RuntimeError) as exc:    # beyond loopback unasked; the SDK's: a port in use
            raise ConfigError(f"the live view cannot serve {view['host']}:{view['port']}: {exc}") from None
        self.latest = {}                 # series name -> the latest value, logged at the view's rate
        self.pending = {}                # key of RAW -> the latest serialized message not yet viewed
        self.shape_at = {"shape": -np.inf, "estimate_shape": -np.inf}   # monotonic [s], last viewed
        self.arm = params.arm
        self.model = None                # the arm's model, built at the first reference it draws
        self.q_d = None                  # the latest reference configuration, not yet drawn
        subscribe = self.create_subscription
        for key, (kind, qos) in RAW.items():
            subscribe(kind, TOPICS[key], lambda raw, key=key: self.pending.__setitem__(key, raw), QOS[qos],
                      raw=True)
        subscribe(ConfigurationReference, TOPICS["configuration"], self.on_reference,
                  QOS["arm/configuration_reference"])
        subscribe(DiagnosticArray, "/diagnostics", self.on_diagnostics, 10)
        self.create_timer(1.0 / view["rate"], self.publish)
        self.get_logger().info(f"live view on {self.live.address} (open it in the Foxglove app)")

    def take(self, pending: dict):
        """The serialized messages ``pending`` (key of :data:`RAW` -> bytes) into the view and the
        series."""
        msg = {key: deserialize_message(raw, RAW[key][0]) for key, raw in pending.items()}
        now = time.monotonic()
        for key, source in (("shape", "simulator"), ("estimate_shape", "estimate")):
            shape = msg.get(key)
            if shape is not None and shape.markers:
                self.shape_at[key] = now
                self.view.take_backbone(stamp_to_seconds(shape.markers[0].header.stamp),
                                        [(p.x, p.y, p.z) for p in shape.markers[0].points], source)
                break
            if now <= self.shape_at[key] + SHAPE_FRESH:
                break                    # the fresher source's backbone stays
        else:
            self.take_reference_arm()
        if "estimate_tip" in msg:
            self.view.tip_covariance = np.array(msg["estimate_tip"].pose.covariance,
                                                dtype=float).reshape(6, 6)[:3, :3]
        for key, take in (("estimate", self.view.take_estimate), ("markers", self.view.take_mocap)):
            if key in msg:
                take(stamp_to_seconds(msg[key].header.stamp), markers_of(msg[key]))
        if "markers" in msg:
            self.latest["task"] = self.view.task()
        if "state" in msg:
            state = msg["state"]
            self.latest.setdefault("tendons", {}).update({
                "t": stamp_to_seconds(state.header.stamp), "names": list(state.name),
                "shortening": list(state.position), "rate": list(state.velocity),
                "tension": list(state.effort)})
        if "reference" in msg:
            self.latest.setdefault("tendons", {})["reference"] = list(msg["reference"].position)

    def on_reference(self, msg: ConfigurationReference):
        self.view.take_target(msg.labels, msg.target)
        self.q_d = (stamp_to_seconds(msg.header.stamp), np.array(msg.q_d, dtype=float))

    def take_reference_arm(self):
        """The backbone where the model puts the arm at the latest reference q_d (no shape is
        published: the rig closed on the mocap alone); once per new reference, some 30 us."""
        if self.q_d is None:
            return
        (t, q_d), self.q_d = self.q_d, None
        if self.model is None:
            self.model = build_model(self.arm)
            self.model_data = ArmData(self.model)
        if q_d.shape != (self.model.n,):
            self.get_logger().warning(f"a reference of {q_d.size} coordinates for a model of "
                                      f"{self.model.n}: not drawn (another arm file?)", once=True)
            return
        try:
            data = evaluate(self.model, self.model_data, q_d, level=KINEMATICS)
        except OutOfDomainError:
            return
        self.view.take_backbone(t, data.p.copy(), "model at the reference")

    def on_diagnostics(self, msg: DiagnosticArray):
        statuses = self.latest.setdefault("diagnostics", {})
        for status in msg.status:
            statuses[status.name] = {"level": int.from_bytes(status.level, "little")
                                     if isinstance(status.level, bytes) else int(status.level),
                                     "message": status.message,
                                     "values": {kv.key: kv.value for kv in status.values}}

    def publish(self):
        """What came since the last call taken in, then the scene and the latest of each series to
        whoever is connected."""
        pending, self.pending = self.pending, {}
        self.take(pending)
        self.live.publish(self.view, self.latest)

    @property
    def published(self) -> int:
        return self.live.published

    def close(self):
        self.live.close()


def _set_up() -> LiveViewNode:
    node = LiveViewNode()
    lift_middleware()                    # its threads exist once the node does
    try:
        report_ready(node.live.address)  # to a run's --live waiting on it, if any
    except ValueError as exc:
        node.get_logger().error(str(exc))
    return node


def main(args=None) -> int:
    yield_cpu()                          # before rclpy, the middleware or the server start a thread
    return run_node(_set_up, "live_view", args)


if __name__ == "__main__":
    sys.exit(main())
