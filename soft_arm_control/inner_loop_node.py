"""``inner_loop`` node: P-satI-D+ on ``tendon/state`` and ``tendon/reference``, publishing
``tendon/command`` (stamped like the state it answers) on every state message. A reference's
``velocity`` field holds its shortening rates [m/s] (the online CLIK's; empty: a fixed reference).
It regulates the tendons of the task ``graph.task``; the others get their feedforward tension.
Without a reference it holds the pretension. Parameters: ``control.*`` (gains, limits, the
thetabar_a fit), ``arm.*``, ``graph.task``; the gains and the tension limits of the inner loop
(:data:`LIVE`) may be set while it runs (``ros2 param set``) and apply from the next state on, the
integral's tension kept (a new integral gain rescales its state); every other value is read-only.

Time is the states' stamps (the motors' receive times on the rig, ``/clock`` in simulation),
checked as they enter (:class:`~soft_arm_control.loop_clock.LoopClock`): a state whose stamp is no
number is refused; a stamp more than ``control.inner_loop.max_time_step`` ahead, or one that goes
back (the PC's clock stepped by NTP), is a clock step: the state is answered, the integral advances
one period, and ``/diagnostics`` (status ``inner_loop``, WARN) names the step at once. Every second
``/diagnostics`` reports the clock steps and the refused states and references.
"""
from __future__ import annotations

import sys
import time
from dataclasses import replace

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.node import Node
from sensor_msgs.msg import JointState

from soft_arm_model import build_model
from soft_arm_ros.contract import QOS, TOPICS
from soft_arm_ros.conversions import joint_state, ordered, seconds_to_stamp, stamp_to_seconds
from soft_arm_ros.parameters import NodeParameters
from soft_arm_ros.runtime import run_node

from .actuation_map import ActuationMap, actuation_map_for
from .config import control_of, task_of
from .inner_loop import tendon_controller_for


# control.* values the node applies while it runs (the limits are the inner loop's clamp only)
LIVE = {f"control.{k}": k.rsplit(".", 1)[-1] for k in (
    "inner_loop.proportional", "inner_loop.derivative", "inner_loop.integral",
    "inner_loop.integral_saturation", "inner_loop.tension_rate_limit", "tension_min", "tension_max")}


class InnerLoopNode(Node):
    def __init__(self, config_dir: str | None = None, actuation_map: ActuationMap | None = None,
                 **node_options):
        super().__init__("inner_loop", allow_undeclared_parameters=True,
                         automatically_declare_parameters_from_overrides=True, **node_options)
        params = NodeParameters(self, config_dir, live=LIVE)
        model = build_model(params.arm)
        self.control = ctl = control_of(params, params.arm)
        task = task_of(params, params.arm)
        actuation_map = actuation_map or actuation_map_for(model, ctl)
        self.names = model.tendon_names
        self.core = tendon_controller_for(model.n_tendons, ctl, task.tendons, actuation_map)
        self.rejected = 0
        self._reported_steps, self._reported_at = 0, -float("inf")     # clock steps, monotonic [s]
        params.on_change(self.apply_gains)
        self.pub = self.create_publisher(JointState, TOPICS["command"], QOS["tendon/command"])
        self.diagnostics_pub = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.create_subscription(JointState, TOPICS["reference"], self.on_reference,
                                 QOS["tendon/reference"])
        self.create_subscription(JointState, TOPICS["state"], self.on_state, QOS["tendon/state"])
        self.get_logger().info(f"inner loop ready: regulating {actuation_map.describe()}")
        if actuation_map.slope_margin <= 0:
            self.get_logger().warning(
                f"thetabar_a is not monotone on this arm (its slope's symmetric part has the "
                f"eigenvalue {actuation_map.slope_margin:.2f}): the loop can circulate energy and "
                "settle off its reference shortenings; control.inner_loop.coordinates: shortenings "
                "regulates the shortenings themselves")

    def apply_gains(self, changes: dict):
        """Live parameter changes (full name -> checked value) into the inner loop's gains."""
        fields = {LIVE[name]: np.asarray(v, dtype=float) if isinstance(v, list) else v
                  for name, v in changes.items()}
        self.core.set_gains(replace(self.core.gains, **fields))
        self.get_logger().info("gains set: " + ", ".join(f"{k} = {v}" for k, v in changes.items()))

    def on_reference(self, msg: JointState):
        try:
            self.core.set_reference(ordered(msg, "position", self.names),
                                    ordered(msg, "effort", self.names),
                                    ordered(msg, "velocity", self.names) if msg.velocity else None)
        except ValueError as exc:
            self.rejected += 1
            self.get_logger().warning(f"reference rejected: {exc}")

    def on_state(self, msg: JointState):
        t = stamp_to_seconds(msg.header.stamp)
        try:
            u = self.core.update(t, ordered(msg, "position", self.names),
                                 ordered(msg, "velocity", self.names))
        except ValueError as exc:
            self.rejected += 1
            self.get_logger().warning(f"state rejected: {exc}", throttle_duration_sec=1.0)
            return
        self.pub.publish(joint_state(self.names, t, effort=u))
        clock = self.core.clock
        if clock.steps != self._reported_steps:
            self.get_logger().warning(f"the states' clock stepped, the loop goes on: {clock.describe()}")
            self.publish_diagnostics(t)
        elif time.monotonic() >= self._reported_at + 1.0:
            self.publish_diagnostics(t)

    def publish_diagnostics(self, stamp: float):
        """The loop's time keeping on ``/diagnostics``, stamped ``stamp`` [s]: WARN when a clock step
        is new since the last report, OK otherwise."""
        clock = self.core.clock
        new = clock.steps != self._reported_steps
        status = DiagnosticStatus(name="inner_loop", hardware_id="soft_arm",
                                  level=DiagnosticStatus.WARN if new else DiagnosticStatus.OK,
                                  message=f"clock step: {clock.describe()}" if new else
                                  ("regulating" if self.core.s_ref is not None else "no reference"))
        values = {"clock_steps_forward": clock.steps_forward, "clock_steps_back": clock.steps_back,
                  "last_clock_step_s": "" if clock.last_step is None else f"{clock.last_step[1]:.6g}",
                  "rejected": self.rejected, "max_time_step_s": clock.max_step}
        status.values = [KeyValue(key=k, value=str(v)) for k, v in values.items()]
        msg = DiagnosticArray(status=[status])
        seconds_to_stamp(msg.header.stamp, stamp)
        self.diagnostics_pub.publish(msg)
        self._reported_steps, self._reported_at = clock.steps, time.monotonic()


def main(args=None) -> int:
    return run_node(InnerLoopNode, "inner_loop", args)


if __name__ == "__main__":
    sys.exit(main())
