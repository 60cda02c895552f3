"""``simulator`` node: the Variable-Strain model as the plant, standing in for the rig.

Publishes what the motor driver and the mocap bridge publish on the rig: ``tendon/state``
(position: encoder shortening [m], velocity [m/s], effort: applied tension [N]), ``mocap/markers``
and ``mocap/tip`` (mid-exposure stamps, at the mocap rate, with noise, latency and the occlusions
of ``plant.mocap.occlusion``: an unseen marker is an invalid marker of the frame, an unseen tip is
no ``mocap/tip`` message), plus ``/clock``
and ``arm/shape`` (MarkerArray). Subscribes ``tendon/command`` (effort: tensions [N]). With a
task's pendulum (``tasks.<graph.task>.pendulum``): the ball swings with the arm and strikes it, its
marker goes out on ``mocap/pendulum`` (PoseStamped, the same exposures as the arm's markers; on the
rig the mocap bridge publishes it as a second rigid body) and it is released at the stamp of a
``pendulum/release`` message (std_msgs/Header).

Modes (``graph.simulator.mode``): ``lockstep`` advances one inner-loop period per received command
(deterministic, as fast as the graph answers, and at most ``graph.simulator.max_real_time_factor``
times as fast as the wall clock, so that the nodes outside the lock get the rig's time budget:
:mod:`.real_time_limit`); ``realtime`` advances on the wall clock. A command
that is missing (lockstep: none within ``command_timeout`` of wall time; realtime: older than
``command_timeout`` of sim time) or malformed holds the last tension and is counted, never a crash.
The plant's parameters are ``plant.*`` over ``arm.*``, so plant and controller models differ;
given ``rig.mocap.calibration`` (an identified arm file carries one), the markers come through it
as the mocap bridge would publish them (``plant.mocap.frame_error`` is the error of mocap.yaml's).
"""
from __future__ import annotations

import os
import sys
import time

import numpy as np
from geometry_msgs.msg import Point, PoseArray, PoseStamped
from rclpy.node import Node
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState
from std_msgs.msg import Header
from visualization_msgs.msg import Marker, MarkerArray

from soft_arm_control.config import control_of, payload_of, pendulum_of
from soft_arm_model import build_model, solve_equilibrium, tendon_lengths
from soft_arm_ros.contract import FRAME, QOS, TOPICS
from soft_arm_ros.conversions import (joint_state, ordered, pose_array, pose_stamped, seconds_to_stamp,
                                      stamp_to_seconds)
from soft_arm_ros.parameters import NodeParameters, parameter_overrides
from soft_arm_ros.runtime import run_node

from .plant_config import describe_plant, plant_of, with_bridge_calibration
from .real_time_limit import RealTimeLimit
from .simulated_rig import SimulatedRig


class SimulatorNode(Node):
    def __init__(self, config_dir: str | None = None, in_waves: bool = False, **node_options):
        """In lockstep, the simulator steps on the held tension when no command comes within
        ``command_timeout`` of wall time, and keeps to ``max_real_time_factor``; neither with
        ``in_waves`` (a wave executor runs every node in the lock and delivers every message)."""
        super().__init__("simulator", allow_undeclared_parameters=True,
                         automatically_declare_parameters_from_overrides=True, **node_options)
        params = NodeParameters(self, config_dir)
        arm, graph = params.arm, params.graph
        self.control = control = control_of(params, arm)
        # an arm file with its own mocap calibration (soft-arm-identify's): the markers go out as
        # the bridge given that file would publish them
        calibration = {f"mocap.calibration.{k}": v
                       for k, v in parameter_overrides(self, "rig.mocap.calibration").items()}
        self.plant = plant = with_bridge_calibration(plant_of(params, arm),
                                                     os.path.join(params.config_dir, "mocap.yaml"),
                                                     calibration)
        model = build_model(arm)                       # the controller's view of start-up
        pretension = np.full(model.n_tendons, control.tension_min)
        q_rest = solve_equilibrium(model, pretension).q
        offset = model.rest_tendon_lengths - tendon_lengths(model, q_rest)
        self.rig = SimulatedRig(build_model(plant.plant_arm(arm)), plant, offset, pretension,
                                payload_of(params, arm), pendulum_of(params, arm))
        self.release_at = None
        self.names = model.tendon_names
        self.steps_per_command = max(1, int(round(1.0 / (control.inner_rate * plant.timestep))))
        self.mode = graph["simulator.mode"]
        self.limit = RealTimeLimit(graph["simulator.max_real_time_factor"]
                                   if self.mode == "lockstep" and not in_waves else 0.0)
        self.timeout = graph["simulator.command_timeout"]
        shape_rate = graph["simulator.shape_rate"]
        self.shape_every = max(1, int(round(1.0 / (shape_rate * plant.timestep)))) if shape_rate else 0
        self.tension = pretension
        self.last_command_t = None
        self.missing_commands = 0
        self.bad_commands = 0
        self.state_pub = self.create_publisher(JointState, TOPICS["state"], QOS["tendon/state"])
        self.markers_pub = self.create_publisher(PoseArray, TOPICS["markers"], QOS["mocap/markers"])
        self.tip_pub = self.create_publisher(PoseStamped, TOPICS["tip"], QOS["mocap/tip"])
        self.clock_pub = self.create_publisher(Clock, TOPICS["clock"], QOS["/clock"])
        self.shape_pub = self.create_publisher(MarkerArray, TOPICS["shape"], QOS["arm/shape"])
        sub = self.create_subscription(JointState, TOPICS["command"], self.on_command,
                                       QOS["tendon/command"])
        if self.rig.pendulum is not None:
            self.ball_pub = self.create_publisher(PoseStamped, TOPICS["ball"], QOS["mocap/pendulum"])
            self.create_subscription(Header, TOPICS["release"], self.on_release, QOS["pendulum/release"])
        self.command_topic = sub.topic_name
        self.waiting_since = time.monotonic()
        period = 1.0 / control.inner_rate
        if self.mode == "realtime":
            self.create_timer(period, self.advance)
        elif not in_waves:
            self.create_timer(self.timeout, self.watchdog)
        self._started = False
        self.start_timer = self.create_timer(0.01, self.start)
        self.get_logger().info(
            f"simulator ({self.mode}) ready: plant {describe_plant(plant)}")

    def start(self):
        """Publish the state at t = 0 once, as soon as a controller (a publisher of
        ``tendon/command``) and a mocap consumer are there; lockstep: the first command answers it."""
        if self._started or self.count_publishers(self.command_topic) == 0 \
                or self.markers_pub.get_subscription_count() == 0:
            return
        self.start_timer.cancel()
        self._started = True
        self.publish_state()

    def on_command(self, msg: JointState):
        try:
            u = ordered(msg, "effort", self.names)
            if not np.all(np.isfinite(u)):
                raise ValueError("non-finite tension")
        except ValueError as exc:
            self.bad_commands += 1
            self.get_logger().warning(f"command ignored: {exc}", throttle_duration_sec=1.0)
            return
        self.tension = np.clip(u, 0.0, None)
        self.last_command_t = stamp_to_seconds(msg.header.stamp)
        if self.mode == "lockstep":
            self.advance()

    def on_release(self, msg: Header):
        """The ball goes at the message's stamp (at once if that has passed)."""
        self.release_at = stamp_to_seconds(msg.stamp)
        if self.release_at < self.rig.t - 1e-9:
            self.get_logger().warning(f"release for t = {self.release_at:.4f} s came at {self.rig.t:.4f} s: "
                                      "the ball goes now")

    def watchdog(self):
        """Lockstep: no command for ``command_timeout`` of wall time: step on the held tension."""
        if self._started and time.monotonic() - self.waiting_since > self.timeout:
            self.missing_commands += 1
            self.advance()

    def advance(self):
        """One inner-loop period of the plant under the current tension, then publish."""
        if self.mode == "realtime" and (self.last_command_t is None
                                        or self.rig.t - self.last_command_t > self.timeout):
            self.missing_commands += 1
        for _ in range(self.steps_per_command):
            self._step()
        self.limit.hold(self.steps_per_command * self.plant.timestep)
        self.publish_state()

    def _publish_frames(self, frames):
        for frame in frames:
            self.markers_pub.publish(pose_array(frame.markers, frame.stamp))
            if np.all(np.isfinite(frame.markers[-1])):          # mocap/tip carries seen tips only
                self.tip_pub.publish(pose_stamped(frame.markers[-1], frame.stamp))
            if frame.ball is not None:
                self.ball_pub.publish(pose_stamped(frame.ball, frame.stamp))

    def _step(self):
        if self.release_at is not None and self.rig.t >= self.release_at - 1e-9:
            self.rig.release_pendulum()
        _, delivered = self.rig.begin_step()
        self._publish_frames(delivered)
        if self.shape_every and self.rig.step_index % self.shape_every == 0:
            self.shape_pub.publish(self.shape())
        self.rig.end_step(self.tension)

    def publish_state(self):
        """Sense the current state (mocap frames due now go out first), publish state and clock."""
        _, delivered = self.rig.begin_step()
        self._publish_frames(delivered)
        t = self.rig.t
        s, sd = self.rig.tendons()
        self.state_pub.publish(joint_state(self.names, t, position=s, velocity=sd,
                                           effort=self.rig.tension))
        clock = Clock()
        seconds_to_stamp(clock.clock, t)
        self.clock_pub.publish(clock)
        self.waiting_since = time.monotonic()

    def shape(self) -> MarkerArray:
        """The backbone at the sensed state as a line strip in arm_base."""
        m = Marker()
        m.header.frame_id = FRAME
        seconds_to_stamp(m.header.stamp, self.rig.t)
        m.ns, m.id, m.type, m.action = "backbone", 0, Marker.LINE_STRIP, Marker.ADD
        m.scale.x = 0.01
        m.color.r, m.color.g, m.color.b, m.color.a = 0.9, 0.5, 0.1, 1.0
        m.pose.orientation.w = 1.0
        m.points = [Point(x=float(p[0]), y=float(p[1]), z=float(p[2]))
                    for p in self.rig.plant.stepper.data.p]
        out = MarkerArray()
        out.markers.append(m)
        return out


def main(args=None) -> int:
    return run_node(SimulatorNode, "simulator", args)


if __name__ == "__main__":
    sys.exit(main())
