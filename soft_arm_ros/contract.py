"""The graph's contract: topic names, their message types and QoS, the frame of every pose.

A marker the mocap did not see is an *invalid marker* of its ``mocap/markers`` frame (and of
``fused/markers``, ``estimate/markers``' layout): NaN position and a zero quaternion
(:func:`soft_arm_ros.conversions.pose_array`); every reader takes it as not seen.

Topics are relative names (a node moved under a namespace, or remapped, keeps the wiring). Streams
(state, command, mocap, clock) are best effort with depth 1: a late sample is worth nothing. What a
viewer draws (the shape) is reliable with depth 1, the QoS RViz and Foxglove ask for by default.
Goals and references are state: reliable and transient-local, so that the last one reaches a node
that starts late. The README's topic table is this module in prose.
"""
from __future__ import annotations

import importlib

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from soft_arm_model.parameters import ConfigError

FRAME = "arm_base"
# a runner's ~/start (std_srvs/Trigger) called again answers success = False with this message: a
# caller whose first answer was lost in discovery learns from it that the first call took effect
ALREADY_STARTED = "already started"
TOPICS = {
    "command": "tendon/command", "state": "tendon/state", "reference": "tendon/reference",
    "markers": "mocap/markers", "tip": "mocap/tip", "goal": "task/goal",
    "configuration": "arm/configuration_reference", "shape": "arm/shape", "clock": "/clock",
    "ball": "mocap/pendulum", "release": "pendulum/release",
    "estimate": "estimate/markers", "fused": "fused/markers", "estimate_tip": "estimate/tip",
    "fused_tip": "fused/tip", "estimate_shape": "estimate/shape",
}
TYPES = {
    "tendon/command": "sensor_msgs/msg/JointState", "tendon/state": "sensor_msgs/msg/JointState",
    "tendon/reference": "sensor_msgs/msg/JointState", "mocap/markers": "geometry_msgs/msg/PoseArray",
    "mocap/tip": "geometry_msgs/msg/PoseStamped", "task/goal": "soft_arm_interfaces/msg/TaskGoal",
    "arm/configuration_reference": "soft_arm_interfaces/msg/ConfigurationReference",
    "arm/shape": "visualization_msgs/msg/MarkerArray", "/clock": "rosgraph_msgs/msg/Clock",
    "mocap/pendulum": "geometry_msgs/msg/PoseStamped", "pendulum/release": "std_msgs/msg/Header",
    "/diagnostics": "diagnostic_msgs/msg/DiagnosticArray",
    "estimate/markers": "geometry_msgs/msg/PoseArray", "fused/markers": "geometry_msgs/msg/PoseArray",
    "estimate/tip": "geometry_msgs/msg/PoseWithCovarianceStamped",
    "fused/tip": "geometry_msgs/msg/PoseWithCovarianceStamped",
    "estimate/shape": "visualization_msgs/msg/MarkerArray",
}
STREAM = QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT,
                    history=HistoryPolicy.KEEP_LAST)
# goals and references are state: the last one is kept for subscribers that join late
RELIABLE = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                      history=HistoryPolicy.KEEP_LAST, durability=DurabilityPolicy.TRANSIENT_LOCAL)
# what a viewer draws: reliable, so that RViz's and Foxglove's default (reliable) subscriptions
# receive it (a best-effort publisher gives a reliable subscriber nothing); only the latest counts
VISUAL = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST,
                    durability=DurabilityPolicy.VOLATILE)
# /diagnostics as every node publishes it (rclpy's default profile, depth 10)
EVENTS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST,
                    durability=DurabilityPolicy.VOLATILE)
QOS = {"tendon/command": STREAM, "tendon/state": STREAM, "mocap/markers": STREAM, "mocap/tip": STREAM,
       "arm/shape": VISUAL, "/clock": STREAM, "tendon/reference": RELIABLE, "task/goal": RELIABLE,
       "arm/configuration_reference": RELIABLE, "mocap/pendulum": STREAM, "pendulum/release": RELIABLE,
       "/diagnostics": EVENTS, "estimate/markers": STREAM, "fused/markers": STREAM, "estimate/tip": STREAM,
       "fused/tip": STREAM, "estimate/shape": VISUAL}


def message_class(type_name: str):
    """The rclpy message class of ``pkg/msg/Type``; ConfigError if it is not installed."""
    package, _, name = type_name.partition("/msg/")
    try:
        return getattr(importlib.import_module(f"{package}.msg"), name)
    except (ImportError, AttributeError, ValueError):
        raise ConfigError(f"unknown message type {type_name!r}") from None
