"""``task_runner`` node: plays the experiment named by ``graph.task`` on ``mocap/markers`` time,
publishes ``task/goal`` at each window start and, at the end, logs the paper-style table and
writes the metrics as JSON to the node parameter ``output`` (if given); then it stops.
"""
from __future__ import annotations

import json
import sys

from geometry_msgs.msg import PoseArray
from rclpy.node import Node
from std_msgs.msg import Float64MultiArray


from .metrics import format_table, to_json
from .ros_interface import (QOS, TOPICS, NodeConfig, float_array, markers_of, run_node,
                            stamp_to_seconds)
from .task_runner import TaskRunner


class TaskRunnerNode(Node):
    def __init__(self, config_dir: str | None = None, **node_options):
        super().__init__("task_runner", allow_undeclared_parameters=True,
                         automatically_declare_parameters_from_overrides=True, **node_options)
        self.config = c = NodeConfig(self, config_dir)
        n_markers = len(c.arm.marker_positions)
        self.core = TaskRunner(c.task, n_markers - 1)
        self.output = self.get_parameter("output").value if self.has_parameter("output") else ""
        self.done = False
        self.pub = self.create_publisher(Float64MultiArray, TOPICS["goal"], QOS["task/goal"])
        self.create_subscription(PoseArray, TOPICS["markers"], self.on_markers, QOS["mocap/markers"])
        self.get_logger().info(f"task {c.task.name}: {len(self.core.windows)} windows, "
                               f"{self.core.duration:.1f} s")

    def on_markers(self, msg: PoseArray):
        if self.done:
            return
        goal = self.core.frame(stamp_to_seconds(msg.header.stamp), markers_of(msg))
        if goal is not None:
            x_d, mode = goal
            self.pub.publish(float_array(x_d, mode))
        if self.core.done:
            self.finish()

    def finish(self):
        rows, summary = self.core.metrics()
        if summary is not None:
            self.get_logger().info(
                f"done: RMS {summary.rms_error * 1e3:.2f} mm, {summary.reached_mm}/"
                f"{summary.transitions} transitions in the mm band")
            self.get_logger().debug("\n" + format_table(rows, summary))
            if self.output:
                with open(self.output, "w", encoding="utf-8") as fh:
                    json.dump({"task": self.core.task.name, **to_json(rows, summary)}, fh, indent=2)
        self.done = True


def main(args=None) -> int:
    return run_node(TaskRunnerNode, "task_runner", args)


if __name__ == "__main__":
    sys.exit(main())
