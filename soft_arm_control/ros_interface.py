"""What every soft_arm node shares: topic names, message types, QoS, conversions, parameter loading.

Topics, types and QoS follow DESIGN.md section 5 (README, "The ROS 2 graph"). Streams (state,
command, mocap, shape, clock) are best effort with depth 1; goals and references are reliable and
transient-local (the last one reaches a node that starts late).
Parameters come from the package's ``config/*.yaml`` overlaid with whatever the node was given
(``--params-file``, ``-p``); they are validated like everywhere else, and a node given a bad value
logs the key, the value and the allowed range and exits with status 2.
"""
from __future__ import annotations

import gc
import importlib
import json
import os
import signal

import numpy as np
import rclpy
from geometry_msgs.msg import Pose, PoseArray, PoseStamped
from rclpy.executors import ExternalShutdownException
from rclpy.signals import SignalHandlerOptions
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray, MultiArrayDimension

from soft_arm_model.config import (ConfigError, apply_overrides, default_config_dir, parse_arm_config,
                                   read_parameters, validate_tree)

from . import config as cfg

FRAME = "arm_base"
TOPICS = {
    "command": "tendon/command", "state": "tendon/state", "reference": "tendon/reference",
    "markers": "mocap/markers", "tip": "mocap/tip", "goal": "task/goal",
    "configuration": "arm/configuration_reference", "shape": "arm/shape", "clock": "/clock",
}
TYPES = {
    "tendon/command": "sensor_msgs/msg/JointState", "tendon/state": "sensor_msgs/msg/JointState",
    "tendon/reference": "sensor_msgs/msg/JointState", "mocap/markers": "geometry_msgs/msg/PoseArray",
    "mocap/tip": "geometry_msgs/msg/PoseStamped", "task/goal": "std_msgs/msg/Float64MultiArray",
    "arm/configuration_reference": "std_msgs/msg/Float64MultiArray",
    "arm/shape": "visualization_msgs/msg/MarkerArray", "/clock": "rosgraph_msgs/msg/Clock",
}
STREAM = QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT,
                    history=HistoryPolicy.KEEP_LAST)
# goals and references are state: the last one is kept for subscribers that join late
RELIABLE = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                      history=HistoryPolicy.KEEP_LAST, durability=DurabilityPolicy.TRANSIENT_LOCAL)
QOS = {"tendon/command": STREAM, "tendon/state": STREAM, "mocap/markers": STREAM, "mocap/tip": STREAM,
       "arm/shape": STREAM, "/clock": STREAM, "tendon/reference": RELIABLE, "task/goal": RELIABLE,
       "arm/configuration_reference": RELIABLE}

GRAPH_SCHEMA = {
    "task": ("str", lambda v: bool(v), "a task name of tasks.yaml"),
    "simulator.mode": ("str", lambda v: v in ("lockstep", "realtime"), "lockstep or realtime"),
    "simulator.command_timeout": ("float", lambda v: 0 < v <= 10,
                                  "a time in (0, 10] s after which a command is stale"),
    "simulator.shape_rate": ("float", lambda v: 0 <= v <= 1000, "a rate in [0, 1000] Hz (0: off)"),
    "recorder.topics": ("strs", lambda v: len(v) >= 1, "one or more topic names"),
    "recorder.chunk_size": ("int", lambda v: 1024 <= v <= 1 << 30, "a size in [1 KiB, 1 GiB] bytes"),
    "recorder.flush_period": ("float", lambda v: 0 < v <= 3600, "a period in (0, 3600] s"),
}
NAMESPACES = ("arm", "control", "plant", "tasks", "graph")
FILES = {"arm": "arm.yaml", "control": "control.yaml", "plant": "plant.yaml", "tasks": "tasks.yaml",
         "graph": "graph.yaml"}
SCHEMAS = {"control": cfg.CONTROL_SCHEMA, "plant": cfg.PLANT_SCHEMA, "tasks": cfg.TASK_SCHEMA,
           "graph": GRAPH_SCHEMA}


def message_class(type_name: str):
    """The rclpy message class of ``pkg/msg/Type``; ConfigError if it is not installed."""
    package, _, name = type_name.partition("/msg/")
    try:
        return getattr(importlib.import_module(f"{package}.msg"), name)
    except (ImportError, AttributeError, ValueError):
        raise ConfigError(f"unknown message type {type_name!r}") from None


# -- parameters ----------------------------------------------------------------------------------
def parameter_overrides(node, prefix: str) -> dict:
    """The node's parameters under ``prefix`` (from --params-file / -p) as dotted overrides relative
    to it. ROS has typed the values already: strings are passed quoted, so that the overrides' YAML
    reading keeps "4.1" or "yes" a string; arrays become lists."""
    out = {}
    for key, param in node.get_parameters_by_prefix(prefix).items():
        value = param.value
        if isinstance(value, str):
            value = json.dumps(value)
        elif isinstance(value, (list, tuple)) or hasattr(value, "tolist"):
            value = list(value)
        out[key] = value
    return out


def node_overrides(node) -> dict:
    """The node's parameters grouped by namespace (arm, control, plant, tasks, graph)."""
    return {ns: parameter_overrides(node, ns) for ns in NAMESPACES}


def _tree(namespace: str, config_dir: str) -> dict:
    params = read_parameters(os.path.join(config_dir, FILES[namespace]))
    if namespace not in params:
        raise ConfigError(f"{FILES[namespace]}: no '{namespace}' parameters")
    return params[namespace]


class NodeConfig:
    """The validated parameters a node needs: ``arm``, ``control``, ``plant``, ``graph`` (dotted
    values) and ``task`` (the task named by ``graph.task``), from the package's files overlaid with
    the node's parameters. Raises ConfigError naming the bad key."""

    def __init__(self, node, config_dir: str | None = None):
        d = config_dir or default_config_dir()
        over = node_overrides(node)
        self.arm = parse_arm_config(apply_overrides(_tree("arm", d), over["arm"]))
        trees = {ns: apply_overrides(_tree(ns, d), over[ns], SCHEMAS[ns], ns)
                 for ns in ("control", "plant", "tasks", "graph")}
        values = {ns: validate_tree(trees[ns], SCHEMAS[ns], ns) for ns in trees}
        self.control = cfg.parse_control(values["control"], self.arm)
        self.plant = cfg.parse_plant(values["plant"], self.arm)
        self.graph = values["graph"]
        name = self.graph["task"]
        known = sorted({k.split(".")[0] for k in values["tasks"]})
        if name not in known:
            raise ConfigError(f"graph.task = {name!r} is not valid: expected one of {known}")
        self.task = cfg.parse_task(name, values["tasks"], self.arm)


def make_executor(context=None):
    """The executor every soft_arm process spins: rclpy's events executor (callbacks dispatched from
    C++, about a third of the CPU time per callback of the SingleThreadedExecutor, which rebuilds
    its wait set in Python for every callback) where this rclpy has it, else the
    SingleThreadedExecutor. One thread; a node is added once."""
    try:
        from rclpy.experimental import EventsExecutor
    except ImportError:
        from rclpy.executors import SingleThreadedExecutor
        return SingleThreadedExecutor(context=context)
    return EventsExecutor(context=context)


def run_node(factory, name: str, args=None) -> int:
    """Create a node with ``factory()`` and spin it (:func:`make_executor`) until Ctrl-C, SIGTERM or
    until it sets ``done``; a ConfigError while creating it is logged and gives exit status 2.

    The first SIGINT or SIGTERM ends the spin between two callbacks (a callback is never cut short
    and the context stays valid while it runs); a second one interrupts the spin at once. A node's
    ``close()`` (if any) then runs, whatever ended the spin (a signal during start-up included), with
    signals ignored so that nothing cuts it short (a driver's zero torque), before the node, the
    executor and the context go; the previous signal handlers come back at the end. What the set-up
    allocated is frozen out of the garbage collector (``gc.freeze``)."""
    stop = []

    def request_stop(signum, frame):
        if stop:
            raise KeyboardInterrupt
        stop.append(signum)

    previous = {sig: signal.signal(sig, request_stop) for sig in (signal.SIGINT, signal.SIGTERM)}
    node = executor = None
    try:
        rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
        node = factory()
        # The set-up leaves some 10^5 long-lived objects (models, compiled kernels, rclpy): a full
        # collection would walk them all, some 50 ms at a time, in the middle of a control period.
        # Collect once now and keep them out of every later collection.
        gc.collect()
        gc.freeze()
        executor = make_executor()
        executor.add_node(node)
        while not stop and rclpy.ok() and not getattr(node, "done", False):
            executor.spin_once(timeout_sec=0.1)
    except ConfigError as exc:
        rclpy.logging.get_logger(name).fatal(f"bad parameter: {exc}")
        return 2
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        for sig in previous:
            signal.signal(sig, signal.SIG_IGN)
        try:
            if node is not None:
                close = getattr(node, "close", None)
                if close is not None:
                    close()
        finally:
            if executor is not None:
                executor.shutdown()
            if node is not None:
                node.destroy_node()
            rclpy.try_shutdown()
            for sig, handler in previous.items():
                signal.signal(sig, handler)
    return 0


# -- conversions ---------------------------------------------------------------------------------
def stamp_to_seconds(stamp) -> float:
    return stamp.sec + 1e-9 * stamp.nanosec


def seconds_to_stamp(msg_stamp, t: float):
    """Write t [s] into a builtin_interfaces/Time (rounded to the nanosecond)."""
    ns = int(round(t * 1e9))
    msg_stamp.sec, msg_stamp.nanosec = ns // 1_000_000_000, ns % 1_000_000_000
    return msg_stamp


def joint_state(names, t: float, position=None, velocity=None, effort=None) -> JointState:
    """A JointState over the tendons, stamped t [s]."""
    msg = JointState()
    seconds_to_stamp(msg.header.stamp, t)
    msg.name = list(names)
    msg.position = [float(v) for v in position] if position is not None else []
    msg.velocity = [float(v) for v in velocity] if velocity is not None else []
    msg.effort = [float(v) for v in effort] if effort is not None else []
    return msg


def ordered(msg: JointState, field: str, names) -> np.ndarray:
    """The values of ``field`` in the order of ``names``; ValueError if a tendon is missing."""
    values = getattr(msg, field)
    if len(values) != len(msg.name):
        raise ValueError(f"JointState.{field} has {len(values)} values for {len(msg.name)} names")
    index = {n: i for i, n in enumerate(msg.name)}
    missing = [n for n in names if n not in index]
    if missing:
        raise ValueError(f"JointState lacks {missing}")
    return np.array([values[index[n]] for n in names], dtype=float)


def pose_array(markers, t: float) -> PoseArray:
    """Marker positions (n, 3) [m] as a PoseArray in arm_base (orientation: identity)."""
    msg = PoseArray()
    msg.header.frame_id = FRAME
    seconds_to_stamp(msg.header.stamp, t)
    for p in markers:
        pose = Pose()
        pose.position.x, pose.position.y, pose.position.z = (float(v) for v in p)
        pose.orientation.w = 1.0
        msg.poses.append(pose)
    return msg


def pose_stamped(p, t: float) -> PoseStamped:
    msg = PoseStamped()
    msg.header.frame_id = FRAME
    seconds_to_stamp(msg.header.stamp, t)
    msg.pose.position.x, msg.pose.position.y, msg.pose.position.z = (float(v) for v in p)
    msg.pose.orientation.w = 1.0
    return msg


def markers_of(msg: PoseArray) -> np.ndarray:
    return np.array([[p.position.x, p.position.y, p.position.z] for p in msg.poses], dtype=float)


def float_array(values, label: str = "") -> Float64MultiArray:
    """A Float64MultiArray with one dimension labelled ``label`` (task/goal: the goal mode)."""
    msg = Float64MultiArray()
    values = [float(v) for v in values]
    msg.layout.dim.append(MultiArrayDimension(label=label, size=len(values), stride=len(values)))
    msg.data = values
    return msg
