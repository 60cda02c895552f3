"""Message conversions between the graph's messages and numpy (SI units, times in seconds)."""
from __future__ import annotations

import math

import numpy as np
from geometry_msgs.msg import Pose, PoseArray, PoseStamped
from sensor_msgs.msg import JointState
from soft_arm_interfaces.msg import ConfigurationReference, TaskGoal

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
    """Marker positions (n, 3) [m] as a PoseArray in arm_base (orientation: identity). A marker that
    was not seen (a row with a NaN) goes out as the frame's *invalid marker*: NaN position and a
    zero quaternion, so that no reader can take it for a pose (:func:`markers_of` reads it back as
    NaN)."""
    msg = PoseArray()
    msg.header.frame_id = FRAME
    seconds_to_stamp(msg.header.stamp, t)
    for p in np.asarray(markers, dtype=float):
        pose = Pose()
        if np.all(np.isfinite(p)):
            pose.position.x, pose.position.y, pose.position.z = (float(v) for v in p)
            pose.orientation.w = 1.0
        else:
            pose.position.x = pose.position.y = pose.position.z = math.nan
            pose.orientation.w = 0.0
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
    """Marker positions (n, 3) [m] of a PoseArray; NaN rows for the invalid markers (a non-finite
    position or a zero quaternion: :func:`pose_array`)."""
    out = np.array([[p.position.x, p.position.y, p.position.z] for p in msg.poses], dtype=float)
    invalid = [p.orientation.w == 0.0 and p.orientation.x == 0.0 and p.orientation.y == 0.0
               and p.orientation.z == 0.0 for p in msg.poses]
    if any(invalid):
        out[np.array(invalid)] = np.nan
    return out.reshape(-1, 3)


def task_goal(t: float, target, mode: str, phase: str, window: float, labels) -> TaskGoal:
    """A TaskGoal stamped t [s] in arm_base: ``target`` [m] in the order of ``labels`` (the task
    coordinates' names), ``mode`` one of ``TaskGoal.MODE_*``, the ``phase`` it belongs to and
    ``window`` [s], how long it stands."""
    msg = TaskGoal(mode=mode, phase=phase, window=float(window), labels=list(labels),
                   target=[float(v) for v in target])
    msg.header.frame_id = FRAME
    seconds_to_stamp(msg.header.stamp, t)
    return msg


def goal_of(msg: TaskGoal, labels) -> tuple:
    """(target [m] in the order of ``labels``, mode, phase) of a TaskGoal for the task coordinates
    ``labels``: the goal's coordinates are taken by their labels (none: in the task's order) and an
    empty mode is ``clik``. ValueError saying what does not fit: another frame than arm_base,
    coordinates that are not the task's."""
    if msg.header.frame_id not in ("", FRAME):
        raise ValueError(f"a goal's target is in {FRAME}, got frame {msg.header.frame_id!r}")
    target = np.array(msg.target, dtype=float)
    if list(msg.labels):
        if len(msg.labels) != len(target) or sorted(msg.labels) != sorted(labels):
            raise ValueError(f"a goal's coordinates are {', '.join(labels)} (in any order, one "
                             f"value each), got {list(msg.labels)} with {len(target)} values")
        index = {label: k for k, label in enumerate(msg.labels)}
        target = target[[index[label] for label in labels]]
    return target, msg.mode or TaskGoal.MODE_CLIK, msg.phase


def configuration_reference(t: float, goal: int, mode: str, q_d, labels, target,
                            x_model) -> ConfigurationReference:
    """A ConfigurationReference stamped t [s] in arm_base: the reference configuration ``q_d``
    (generalised coordinates) answering goal number ``goal`` (``mode``), with the goal's ``target``
    [m] at t and the task coordinates ``x_model`` [m] the model puts at q_d, both in the order of
    ``labels``."""
    msg = ConfigurationReference(goal=int(goal), mode=mode, q_d=[float(v) for v in q_d],
                                 labels=list(labels), target=[float(v) for v in target],
                                 x_model=[float(v) for v in x_model])
    msg.header.frame_id = FRAME
    seconds_to_stamp(msg.header.stamp, t)
    return msg
