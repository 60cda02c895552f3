"""Message conversions between the graph's messages and numpy (SI units, times in seconds)."""
from __future__ import annotations

import numpy as np
from geometry_msgs.msg import Pose, PoseArray, PoseStamped
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray, MultiArrayDimension

from .contract import FRAME


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
