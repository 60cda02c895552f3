"""The experiment graph on the simulator (a ROS 2 Jazzy installation; run with
``ros2 launch soft_arm sim.launch.py task:=triangle [feedback:=fused]``). Every node reads the
package's parameter files; ``soft-arm-experiment`` starts the same graph without ``launch``.
``feedback`` (mocap, fused or estimate): what the clik closes its loop on; other than mocap, the
shape estimator joins the graph, the clik's ``mocap/markers`` is remapped onto its topic and its
``control.clik.feedback`` set (the trust region judges the estimate)."""
import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.conditions import IfCondition
from launch.substitutions import LaunchConfiguration, PythonExpression
from launch_ros.actions import Node

# arm.yaml last: an identified arm put in its place carries the estimator priors of its fit
PARAMETER_FILES = ["control.yaml", "plant.yaml", "tasks.yaml", "graph.yaml", "estimator.yaml", "arm.yaml"]
# the clik's mocap/markers per feedback (soft_arm_experiments.orchestration.FEEDBACK_TOPICS)
FEEDBACK = {"mocap": "mocap/markers", "fused": "fused/markers", "estimate": "estimate/markers"}
NODES = ["simulator", "inner_loop", "clik", "task_runner", "recorder"]
# Nodes on the simulator's /clock (use_sim_time): the recorder, whose log times are the clock's.
# The controller and the task runner run on the stamps of the messages they get (mocap exposures,
# tendon states), so they follow the simulated time whatever their clock; the simulator is the clock.
SIM_TIME_NODES = ["recorder"]


def generate_launch_description():
    config = os.path.join(get_package_share_directory("soft_arm"), "config")
    params = [os.path.join(config, name) for name in PARAMETER_FILES]
    task = {"graph.task": LaunchConfiguration("task")}
    feedback = LaunchConfiguration("feedback")
    topic = PythonExpression([repr(FEEDBACK), "['", feedback, "']"])
    return LaunchDescription(
        [DeclareLaunchArgument("task", default_value="triangle"),
         DeclareLaunchArgument("feedback", default_value="mocap", choices=list(FEEDBACK))]
        + [Node(package="soft_arm", executable=name, name=name, output="screen",
                parameters=params + [task, {"use_sim_time": name in SIM_TIME_NODES}]
                + ([{"control.clik.feedback": feedback}] if name == "clik" else []),
                remappings=[("mocap/markers", topic)] if name == "clik" else []) for name in NODES]
        + [Node(package="soft_arm", executable="shape_estimator", name="shape_estimator", output="screen",
                parameters=params, condition=IfCondition(PythonExpression(["'", feedback, "' != 'mocap'"])))])
