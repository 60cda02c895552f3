"""``task_runner`` node: plays the experiment named by ``graph.task`` on ``mocap/markers`` time,
publishes ``task/goal`` (soft_arm_interfaces/TaskGoal: the window's target, mode, phase and
duration, stamped with the frame that starts it) at each window start and, at the end, logs the
paper-style table and writes the metrics as JSON to the node parameter ``output`` (if given;
written whole or not at all), with ``goals``: per window the closest and the last measured task
error and the clik node's last report of the goal from ``/diagnostics`` (infeasible and held
steps, status; for the last goal as of the clik's last report, at most a second old); then it
stops. A task with a pendulum plans its strike at start-up (:func:`~.strike.strike_plan_for`),
publishes ``pendulum/release`` (std_msgs/Header stamped with the release time, sent ahead) with
the first frame, reads the ball on ``mocap/pendulum`` and writes the strike's plan and measurement
under ``strike``.

With the parameter ``wait_for_start`` true (on the rig: the motors are enabled first), the first
window starts with the first frame after a call of ``~/start`` (std_srvs/Trigger), and the node
stays up after the last window until it is stopped (the caller disables the motors first).
"""
from __future__ import annotations

import json
import os
import sys
from dataclasses import asdict

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseArray, PoseStamped
from rclpy.node import Node
from soft_arm_interfaces.msg import TaskGoal
from std_msgs.msg import Header
from std_srvs.srv import Trigger

from soft_arm_control.config import control_of, task_of
from soft_arm_control.loop_clock import LoopClock
from soft_arm_ros.contract import ALREADY_STARTED, FRAME, QOS, TOPICS
from soft_arm_ros.conversions import markers_of, seconds_to_stamp, stamp_to_seconds, task_goal
from soft_arm_ros.parameters import NodeParameters
from soft_arm_ros.runtime import run_node

from .metrics import format_table, to_json
from .strike import strike_plan_for
from .task_runner import TaskRunner


MAX_FRAME_GAP = 1.0      # s: the longest gap between two frames' stamps taken as time that passed


class TaskRunnerNode(Node):
    def __init__(self, config_dir: str | None = None, **node_options):
        super().__init__("task_runner", allow_undeclared_parameters=True,
                         automatically_declare_parameters_from_overrides=True, **node_options)
        params = NodeParameters(self, config_dir)
        self.task = task = task_of(params, params.arm)
        plan = None
        if task.pendulum is not None:
            plan = strike_plan_for(params.arm, control_of(params, params.arm), task)
            self.get_logger().info(f"strike plan ({plan.timing}): reference at +{plan.send_delay:.3f} s, "
                                   f"release at +{plan.release_delay:.3f} s")
            if not np.isfinite(plan.arm_time):
                self.get_logger().warning(
                    f"the rehearsed arm never touches the ball at its lowest point (it passes "
                    f"{plan.rehearsed_gap * 1e3:.1f} mm away): the strike will miss on the model")
        self.core = TaskRunner(task, len(params.arm.marker_positions) - 1, plan, params.arm)
        self.release_sent = False
        # the schedule's clock over the frames' stamps: a frame more than MAX_FRAME_GAP after the
        # last, or before it, is the stamps' clock stepping (counted, written with the metrics)
        self.clock = LoopClock(MAX_FRAME_GAP)
        self.rejected_frames = 0
        self.output = params.run_option("output")
        self.wait_for_start = params.run_option("wait_for_start")
        self.started = not self.wait_for_start
        self.finished = self.done = False
        self.create_service(Trigger, "~/start", self.on_start)
        self.pub = self.create_publisher(TaskGoal, TOPICS["goal"], QOS["task/goal"])
        self.create_subscription(PoseArray, TOPICS["markers"], self.on_markers, QOS["mocap/markers"])
        if task.pendulum is not None:
            self.release_pub = self.create_publisher(Header, TOPICS["release"], QOS["pendulum/release"])
            self.create_subscription(PoseStamped, TOPICS["ball"], self.on_ball, QOS["mocap/pendulum"])
        self.create_subscription(DiagnosticArray, "/diagnostics", self.on_diagnostics, 10)
        self.get_logger().info(f"task {task.name}: {len(self.core.windows)} windows, "
                               f"{self.core.duration:.1f} s")

    def on_start(self, request, response):
        response.success = not self.started
        response.message = ALREADY_STARTED if self.started else \
            f"task {self.core.task.name} starts with the next mocap frame"
        self.started = True
        return response

    def on_markers(self, msg: PoseArray):
        if not self.started or self.finished:
            return
        t = stamp_to_seconds(msg.header.stamp)
        try:
            advance = self.clock.check(t)
        except ValueError as exc:
            self.rejected_frames += 1
            self.get_logger().warning(f"frame left out: {exc}", throttle_duration_sec=1.0)
            return
        loop_t = self.clock.commit(t, advance)
        if advance.step is not None:
            self.get_logger().warning(f"the frames' clock stepped, the windows go on at the arm's pace: "
                                      f"{self.clock.describe()}", throttle_duration_sec=1.0)
        goal = self.core.frame(t, markers_of(msg), loop_t)
        if goal is not None:
            self.pub.publish(task_goal(t, goal.target, goal.mode, goal.phase, goal.window,
                                       self.task.space.labels()))
        if self.core.release_at is not None and not self.release_sent:
            # sent ahead, stamped with the release time: the release happens on time
            release = Header(frame_id=FRAME)
            seconds_to_stamp(release.stamp, self.core.release_at)
            self.release_pub.publish(release)
            self.release_sent = True
        if self.core.done:
            self.finish()

    def on_ball(self, msg: PoseStamped):
        p = msg.pose.position
        self.core.ball(stamp_to_seconds(msg.header.stamp), (p.x, p.y, p.z))

    def on_diagnostics(self, msg: DiagnosticArray):
        for status in msg.status:
            if status.name == "clik":
                values = {kv.key: kv.value for kv in status.values}
                try:
                    report = {k: json.loads(v) for k, v in values.items() if k != "status"}
                except ValueError:
                    self.get_logger().warning(f"unreadable clik report {values}", throttle_duration_sec=5.0)
                    continue
                if "goal" in report and "target" in report:
                    self.core.clik_report(stamp_to_seconds(msg.header.stamp),
                                          {**report, "status": values.get("status")})

    def finish(self):
        rows, summary = self.core.metrics()
        if summary is not None:
            self.get_logger().info(
                f"done: RMS {summary.rms_error * 1e3:.2f} mm, {summary.reached_mm}/"
                f"{summary.transitions} transitions in the mm band")
            self.get_logger().debug("\n" + format_table(rows, summary))
            if self.output:
                partial = self.output + ".partial"
                with open(partial, "w", encoding="utf-8") as fh:
                    strike = self.core.strike()
                    task = self.core.task
                    tracking = [asdict(r) for r in self.core.tracking()]
                    json.dump({"task": task.name, "paper_peak_speed": task.paper_peak_speed,
                               "complete": self.core.done,      # every window played (not stopped early)
                               "frame_clock_steps": self.clock.steps, "rejected_frames": self.rejected_frames,
                               **to_json(rows, summary), "goals": self.core.goals(),
                               **({"strike": strike} if strike else {}),
                               **({"tracking": tracking} if tracking else {})}, fh, indent=2)
                os.replace(partial, self.output)
        self.finished = True
        self.done = not self.wait_for_start


def main(args=None) -> int:
    return run_node(TaskRunnerNode, "task_runner", args)


if __name__ == "__main__":
    sys.exit(main())
