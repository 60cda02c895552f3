"""``excitation`` node: plays the identification experiment (``identification.yaml``,
:mod:`.excitation`) open loop, in tension: on every ``tendon/state`` it publishes
``tendon/command`` (effort: the schedule's tensions [N], stamped like the state it answers), in the
inner loop's place. The schedule's clock starts with the first state after start-up, or, with the
parameter ``wait_for_start`` true (on the rig: the motors are enabled first), after a call of
``~/start`` (std_srvs/Trigger); until then and after the end the tendons hold ``tension_low``. At
the end it writes the schedule as JSON to the parameter ``output`` (if given; written whole or not
at all) and stops (with ``wait_for_start``: stays up, holding, until it is stopped).
"""
from __future__ import annotations

import json
import os
import sys

from rclpy.node import Node
from sensor_msgs.msg import JointState
from std_srvs.srv import Trigger

from soft_arm_control.config import control_of
from soft_arm_ros.contract import ALREADY_STARTED, QOS, TOPICS
from soft_arm_ros.conversions import joint_state, stamp_to_seconds
from soft_arm_ros.parameters import NodeParameters
from soft_arm_ros.runtime import run_node

from .excitation import NAMESPACE, SCHEMA, Excitation, parse_excitation


class ExcitationNode(Node):
    def __init__(self, config_dir: str | None = None, **node_options):
        super().__init__("excitation", allow_undeclared_parameters=True,
                         automatically_declare_parameters_from_overrides=True, **node_options)
        params = NodeParameters(self, config_dir)
        arm = params.arm
        control = control_of(params, arm)
        self.names = [t.name for t in arm.tendons]
        config = parse_excitation(params.section(NAMESPACE, SCHEMA), len(self.names),
                                  control.tension_min, control.tension_max)
        self.core = Excitation(config, len(self.names))
        self.output = params.run_option("output")
        self.wait_for_start = params.run_option("wait_for_start")
        self.started = not self.wait_for_start
        self.t0 = None
        self.last = None                # the latest state's stamp [s]
        self.finished = self.done = False
        self.create_service(Trigger, "~/start", self.on_start)
        self.pub = self.create_publisher(JointState, TOPICS["command"], QOS["tendon/command"])
        self.create_subscription(JointState, TOPICS["state"], self.on_state, QOS["tendon/state"])
        self.get_logger().info(f"identification experiment: {len(self.core.segments)} segments, "
                               f"{self.core.duration:.1f} s")

    def on_start(self, request, response):
        response.success = not self.started
        response.message = ALREADY_STARTED if self.started else \
            "the identification experiment starts with the next tendon state"
        self.started = True
        return response

    def on_state(self, msg: JointState):
        t = stamp_to_seconds(msg.header.stamp)
        self.last = t
        if self.started and self.t0 is None:
            self.t0 = t
        u = self.core.tension(t - self.t0 if self.t0 is not None else -1.0)     # -1: before the start
        self.pub.publish(joint_state(self.names, t, effort=u))
        if self.t0 is not None and t - self.t0 >= self.core.duration and not self.finished:
            self.finish()

    def finish(self):
        """Write the schedule (with its start on the state clock, and whether it played to its
        end) to ``output``; stop unless the caller stops this node."""
        if self.output and self.t0 is not None:
            partial = self.output + ".partial"
            complete = self.last is not None and self.last - self.t0 >= self.core.duration
            with open(partial, "w", encoding="utf-8") as fh:
                json.dump({"task": "identification", "start": self.t0, "complete": complete,
                           **self.core.summary()}, fh, indent=2)
            os.replace(partial, self.output)
        self.finished = True
        self.done = not self.wait_for_start


def main(args=None) -> int:
    return run_node(ExcitationNode, "excitation", args)


if __name__ == "__main__":
    sys.exit(main())
