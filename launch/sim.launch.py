"""The experiment graph on the simulator (a ROS 2 Jazzy installation; run with
``ros2 launch soft_arm sim.launch.py task:=triangle``). Every node reads the package's parameter
files; ``soft-arm-experiment`` starts the same graph without ``launch``."""
import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

PARAMETER_FILES = ["arm.yaml", "control.yaml", "plant.yaml", "tasks.yaml", "graph.yaml"]
NODES = ["simulator", "inner_loop", "clik", "task_runner", "recorder"]
# Nodes on the simulator's /clock (use_sim_time): the recorder, whose log times are the clock's.
# The controller and the task runner run on the stamps of the messages they get (mocap exposures,
# tendon states), so they follow the simulated time whatever their clock; the simulator is the clock.
SIM_TIME_NODES = ["recorder"]


def generate_launch_description():
    config = os.path.join(get_package_share_directory("soft_arm"), "config")
    params = [os.path.join(config, name) for name in PARAMETER_FILES]
    task = {"graph.task": LaunchConfiguration("task")}
    return LaunchDescription(
        [DeclareLaunchArgument("task", default_value="triangle")]
        + [Node(package="soft_arm", executable=name, name=name, output="screen",
                parameters=params + [task, {"use_sim_time": name in SIM_TIME_NODES}]) for name in NODES])
